"""The closed loops' speed against their chunk size: compile and warm throughput.

    python benchmarks/bench_closed_loop.py                    # airborne_radar.toml, prints
    python benchmarks/bench_closed_loop.py --file experiments/dekf_on_axis.toml --runs 64 --chunks 16,32,64

For each chunk size the file's world is compiled (no persistent cache; the seconds the
runner reports) and then run twice; the second, warm call's runs·steps/s is the
throughput (a step: a filter period). Every chunk size gives the same statistics (the
runner's run keys); the script checks the headline numbers agree before it reports.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--file", default="experiments/airborne_radar.toml")
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--chunks", default="64,256,1000", help="comma-separated runs per chunk")
    args = ap.parse_args()
    os.environ["TRACKLAB_CACHE_DIR"] = ""
    import tracklab

    tracklab.configure()
    import jax

    from tracklab.config import load_experiment
    from tracklab.montecarlo import runner

    exp = load_experiment(ROOT / args.file)
    print(f"{args.file}: {args.runs} runs x {exp.steps} periods, {jax.device_count()} device(s) ({jax.devices()[0]})")
    print("| chunk | compile (s) | warm wall (s) | runs·steps/s |\n|---|---|---|---|")
    ref = None
    for chunk in (int(c) for c in args.chunks.split(",")):
        world, params = exp.world(exp.structure(chunk)), exp.params()
        first = runner.run(world, params, args.runs, exp.seed)
        t1 = time.perf_counter()
        warm = runner.run(world, params, args.runs, exp.seed)
        wall = time.perf_counter() - t1
        flat = {l: float(sum(float(x.sum()) for x in jax.tree_util.tree_leaves(v))) for l, v in warm.sums.items()
                if isinstance(v, dict)}
        if ref is None:
            ref = flat
        for l, v in flat.items():  # the same runs whatever the chunk
            assert abs(v - ref[l]) <= 1e-9 * max(abs(ref[l]), 1.0), (chunk, l, v, ref[l])
        print(f"| {chunk} | {first.compile_s:.1f} | {wall:.2f} | {args.runs * exp.steps / wall:.3g} |", flush=True)


if __name__ == "__main__":
    main()
