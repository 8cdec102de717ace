"""What one element of an operation costs inside a compiled scan, as tracklab compiles it.

    python benchmarks/elementwise.py              # 1 000 and 5 000 runs, 200 steps

Each case is a ``lax.scan`` of 200 steps over a per-run value (runs last, as the filters lay
them out) compiled under ``tracklab.configure()`` on one device; the time of a step, best of
30 calls, minus that of the same scan doing only its additions, divided by the runs: the
cost of the operation per run and step. It shows which operations of a filter's step the CPU
runs vectorised and which it runs as a library call per element (``log``, ``atan2``), and what
a concatenation of rows costs against whole blocks.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from tracklab.runtime import configure

BASELINE = "baseline: the whole step, an add"


def _cases():
    """name -> (a step's operation on a (2, runs) value a, the rows it adds to the carry)."""
    rows = lambda a: [a[0], a[1], a[0] * a[1], a[0] - a[1], a[0] + a[1], a[0] * a[0], a[1] * a[1], a[0] / a[1]]
    return {
        BASELINE: (lambda a: a[0] + a[1], 1),
        "multiply": (lambda a: a[0] * a[1], 1),
        "divide": (lambda a: a[0] / a[1], 1),
        "sqrt": (lambda a: jnp.sqrt(a[0] * a[0] + a[1] * a[1]), 1),
        "log": (lambda a: jnp.log(a[0]), 1),
        "atan2": (lambda a: jnp.arctan2(a[1], a[0]), 1),
        "8 rows concatenated": (lambda a: jnp.concatenate([r[None] for r in rows(a)]), 8),
        "8 rows stacked as 2 blocks of 4": (lambda a: jnp.concatenate([jnp.stack(rows(a)[:4]), jnp.stack(rows(a)[4:])]), 8),
    }


def _step_time(op, width, B, T=200, calls=30):
    def step(carry, k):
        a, acc = carry
        a = a * 0.999 + 1e-3  # a new value every step, positive
        return (a, acc + op(a).reshape(width, B)), None

    run = jax.jit(lambda a0: jax.lax.scan(step, (a0, jnp.zeros((width, B))), jnp.arange(T))[0])
    a0 = jnp.ones((2, B)) + jnp.arange(B) / B
    jax.block_until_ready(run(a0))
    best = float("inf")
    for _ in range(calls):
        t = time.perf_counter()
        jax.block_until_ready(run(a0))
        best = min(best, time.perf_counter() - t)
    return best / T


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, nargs="+", default=[1000, 5000])
    args = ap.parse_args()
    configure(cpu_devices=1)
    times = {B: {name: _step_time(op, width, B) for name, (op, width) in _cases().items()} for B in args.runs}
    print("| operation | " + " | ".join(f"ns per run and step ({B} runs)" for B in args.runs) + " |")
    print("|---|" + "---:|" * len(args.runs))
    for name in _cases():  # the baseline whole, the others beyond it
        cells = [(t[name] - (0.0 if name == BASELINE else t[BASELINE])) / B * 1e9 for B, t in times.items()]
        print(f"| {name} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")


if __name__ == "__main__":
    main()
