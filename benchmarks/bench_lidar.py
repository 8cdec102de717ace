"""Throughput, compile time and peak memory of the lidar experiment.

    python benchmarks/bench_lidar.py            # full benchmark (~5-8 min on 2 cores), writes benchmarks/lidar.md
    python benchmarks/bench_lidar.py --quick    # smoke version (fewer runs), prints only

See benchmarks/README.md for what is measured and how.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from written import write_run

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENT = ROOT / "experiments" / "lidar_crossing.toml"
DEFAULT_CHUNK = 1000  # runs per chunk of the per-filter table


# ----------------------------------------------------------------------------- helpers


def _load(labels=None):
    from tracklab.config import load_experiment

    exp = load_experiment(EXPERIMENT)
    if labels is not None:
        exp.filters = [f for f in exp.filters if f.label in labels]
        assert [f.label for f in exp.filters] == list(labels), labels
    return exp


def _restricted(labels, chunk):
    """The lidar experiment's structure and params for its filters ``labels`` (a subset of the
    structure's filters and the matching subset of the params' filters), chunk ``chunk``."""
    import dataclasses

    exp = _load()
    structure, params = exp.structure(chunk=chunk), exp.params()
    keep = [i for i, f in enumerate(structure.filters) if f.label in labels]
    structure = dataclasses.replace(structure, filters=tuple(structure.filters[i] for i in keep))
    params = params._replace(filters=[params.filters[i] for i in keep])
    assert structure.labels == list(labels), (structure.labels, labels)
    return exp, structure, params


def simulation_world(chunk):
    """The simulation alone, as a world of its own on the runner (same keys, devices, padding and
    host-side sums as the tracking world), because the tracking world cannot run with no filter
    (its chunk stacks one divergence row per filter). Each run's truth (``scenario.simulate``), its
    measurements (``sensor.measure``), its prior mean, and the expected measurement information
    the PCRLB needs, from the run's key split as the tracking world splits it; reduced over the
    runs to per-step sums so that nothing is computed for nothing. It draws a run whole, as the
    tracking world does for filters whose view needs every step; for the lidar's filters that
    world draws the same numbers step by step inside its scan, so this row is the simulation's
    cost measured apart, not a subtraction from the rows with filters."""
    import jax
    import jax.numpy as jnp

    from tracklab import random
    from tracklab.montecarlo import runner

    def chunk_fn(params, keys, live, exclude):
        scenario, sensor = params.scenario, params.sensor
        T = scenario.steps
        split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
        truth = jax.vmap(scenario.simulate)(split[:, 0])  # (B, T+1, 2d)
        pos = truth[:, 1:, 0::2]
        z = jax.vmap(sensor.measure)(split[:, 1], pos)  # (B, T, M)
        L0 = jnp.linalg.cholesky(params.P0)
        w0 = jax.vmap(lambda k: random.normal(k, (L0.shape[0],), L0.dtype))(split[:, 2])
        prior = truth[:, 0] + w0 @ L0.T
        w = live.astype(truth.dtype)
        out = {"sum_truth": jnp.einsum("b,bti->ti", w, truth), "sum_z": jnp.einsum("b,bti->ti", w, jnp.nan_to_num(z)),
               "sum_prior": w @ prior}
        if scenario.gaussian:
            info = 0.0
            for s in sensor.sensors:
                I = jax.vmap(jax.vmap(s.information))(pos)  # (B, T, d, d)
                info = info + jnp.asarray(s.report_mask(T), truth.dtype)[:, None, None] * jnp.einsum("b,btij->tij", w, I)
            out["_info"] = info
        return out

    return runner.World(("bench_lidar: simulation alone", chunk), chunk_fn, 1, chunk)


def _chunks(runs, chunk):
    import jax.numpy as jnp
    import numpy as np

    out = []
    for c in range(-(-runs // chunk)):
        idx = np.arange(c * chunk, (c + 1) * chunk, dtype=np.uint32)
        out.append((jnp.asarray(idx), jnp.asarray(idx < runs)))
    return out


def _pass(fn, params, key, chunks, lanes):
    """One pass over all chunks with the compiled program ``fn``, as ``runner.run`` does it: call,
    transfer the result and combine the devices' parts (``runner.host_sums``), run the chunk again
    without the runs that diverged (none do in these benchmarks, but it would be charged), add on
    the host (``runner.Accumulator``).
    Returns (per-chunk seconds, accumulator, chunks run twice)."""
    import jax.numpy as jnp

    from tracklab.montecarlo import runner

    acc = runner.Accumulator()
    B = chunks[0][0].shape[0]
    no_exclusion = jnp.zeros((lanes, B), bool)
    times, twice = [], 0
    for idx, live in chunks:
        t0 = time.perf_counter()
        sums = runner.host_sums(fn(params, key, idx, live, no_exclusion), B)
        flags = sums.diverged
        if flags is not None and flags.any():
            sums = runner.host_sums(fn(params, key, idx, live, jnp.asarray(flags)), B)
            twice += 1
        acc.add(sums)
        times.append(time.perf_counter() - t0)
    return times, acc, twice


def time_program(world, params, runs, seed=0, repeat=1):
    """Compile ``world``'s program for ``params`` (``runner.program``, float64), call it once on the
    first chunk (not timed as part of a pass), then time ``repeat`` full passes over ``runs`` runs;
    the fastest is kept (other load on the machine only slows a pass down)."""
    import jax

    from tracklab.montecarlo import runner

    with jax.enable_x64(True):
        params = runner.in_precision(params, "float64")
        fn, compile_s = runner.program(world, params, "float64")
        key = jax.random.key(seed)
        chunks = _chunks(runs, world.chunk_size)
        t0 = time.perf_counter()
        _pass(fn, params, key, chunks[:1], world.lanes)
        first = time.perf_counter() - t0
        wall, times, acc, twice = float("inf"), None, None, 0
        for _ in range(repeat):
            t0 = time.perf_counter()
            times_i, acc_i, twice_i = _pass(fn, params, key, chunks, world.lanes)
            wall_i = time.perf_counter() - t0
            if wall_i < wall:
                wall, times, acc, twice = wall_i, times_i, acc_i, twice_i
    return {"compile_s": compile_s, "held": compile_s == 0.0, "first_call_s": first, "wall_s": wall, "times": times,
            "sums": runner.merged(acc.total), "twice": twice, "n_chunks": len(chunks), "chunk": world.chunk_size}


def bench_throughput(labels, runs, chunk, seed=0, repeat=1):
    """Compile time and steady-state throughput for the given filters (none: the simulation alone,
    ``simulation_world``).

    compile_s: ``runner.program``'s seconds (tracing, lowering and compiling the program);
    throughput from the fastest full pass over all chunks with the compiled program.
    """
    from tracklab.worlds.tracking import scan

    chunk = min(chunk, runs)
    exp, structure, params = _restricted(labels, chunk)
    world = scan.world(structure) if labels else simulation_world(chunk)
    t = time_program(world, params, runs, seed, repeat)
    diverged = {lab: float(t["sums"][lab]["diverged"]) for lab in structure.labels}
    return {
        "labels": list(structure.labels),
        "runs": runs,
        "chunk": chunk,
        "repeat": repeat,
        "n_chunks": t["n_chunks"],
        "first_call_s": t["first_call_s"],
        "steady_chunk_s": statistics.median(t["times"]),
        "compile_s": t["compile_s"],
        "held": t["held"],
        "wall_s": t["wall_s"],
        "min_chunk_s": min(t["times"]),
        "max_chunk_s": max(t["times"]),
        "throughput": runs * exp.steps / t["wall_s"],
        "diverged": diverged,
        "twice": t["twice"],
    }


# ----------------------------------------------------------------------------- memory child


def _vmhwm_kib():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return -1


def child_memory(runs, chunk, labels=None):
    """Runs in a fresh process: the experiment (or its filters ``labels``) through the public API."""
    t0 = time.perf_counter()
    import jax

    import tracklab

    tracklab.configure()  # one CPU device per core, Eigen single-threaded, 64-bit mode

    exp = _load(labels)
    jax.block_until_ready(jax.numpy.zeros(1))  # backend initialised
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    import_s = time.perf_counter() - t0
    after_first = []

    def progress(done, total):
        if not after_first:  # peak after compile + first chunk
            after_first.append(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)

    res = exp.monte_carlo(runs=runs, seed=0, chunk=chunk, progress=progress)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({
        "runs": runs,
        "chunk": chunk,
        "baseline_kib": base,
        "after_first_chunk_kib": after_first[0],
        "peak_kib": peak,
        "vmhwm_kib": _vmhwm_kib(),  # cross-check: the same high-water mark, per address space
        "import_s": import_s,
        "wall_s": res.wall_s,  # the whole call, compile included
        "compile_s": res.compile_s,  # runner.program's tracing, lowering and compiling
        "diverged": {lab: float(res.sums[lab]["diverged"]) for lab in res.labels},
        "count_last": {lab: float(res.sums[lab]["count"][-1]) for lab in res.labels},
    }))


def bench_memory(runs, chunk, labels=None):
    t0 = time.perf_counter()
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child-memory", str(runs), str(chunk)]
    if labels:
        cmd += ["--labels", ",".join(labels)]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    total = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"memory child failed:\n{p.stderr}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["process_s"] = total
    return out


# ----------------------------------------------------------------------------- 10^6 runs, first result

MILLION_LABELS = ("CMKF", "EKF")  # the full set of six takes ~1 h for 10^6 runs on 2 cores


def million(out=None):
    """10^6 runs x 200 steps in chunks of 10 000, peak RSS of a fresh process (bound: 2 GiB)."""
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    m = bench_memory(1_000_000, 10_000, MILLION_LABELS)
    lines = [
        "## 10^6 runs x 200 steps (`python benchmarks/bench_lidar.py --million`)",
        "",
        f"Filters {', '.join(MILLION_LABELS)} of the lidar experiment, chunk 10 000, fresh process, "
        f"load average at start {load}.",
        "",
        "| Runs | Baseline (MiB) | Peak RSS (MiB) | VmHWM (MiB) | Wall (s) | Throughput (runs·steps/s) | Diverged |",
        "|---:|---:|---:|---:|---:|---:|---|",
        f"| {m['runs']} | {_mib(m['baseline_kib']):.0f} | {_mib(m['peak_kib']):.0f} | {_mib(m['vmhwm_kib']):.0f} | "
        f"{m['wall_s']:.0f} | {fmt_rate(m['runs'] * 200 / m['wall_s'])} | {m['diverged']} |",
        "",
    ]
    _emit(lines, out)
    assert m["peak_kib"] <= 2 * 1024 * 1024, "peak resident memory above 2 GiB"


def first_result(out=None):
    """`tracklab run` wall time, process start to exit: a cold compilation cache, then a warm one."""
    import shutil
    import tempfile

    from bench_rerun import first_line

    cache = Path(tempfile.mkdtemp(prefix="tracklab-cache-"))
    res_dir = Path(tempfile.mkdtemp(prefix="tracklab-out-"))
    cmd = [sys.executable, "-m", "tracklab.cli", "run", str(EXPERIMENT), "--runs", "1000", "--no-figures",
           "--out", str(res_dir / "r")]
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}  # it would take precedence
    env["TRACKLAB_CACHE_DIR"] = str(cache)
    rows = []
    for label in ("cold cache", "warm cache", "warm cache"):
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True, cwd=ROOT)
        rows.append((label, time.perf_counter() - t0, first_line(p.stdout)["compile_s"], load))
        shutil.rmtree(res_dir / "r", ignore_errors=True)
    shutil.rmtree(cache, ignore_errors=True)
    shutil.rmtree(res_dir, ignore_errors=True)
    lines = [
        "## First result (`python benchmarks/bench_lidar.py --first-result`)",
        "",
        "`tracklab run experiments/lidar_crossing.toml --runs 1000 --no-figures`, all six filters: wall time "
        "from process start to exit (import, tracing, compilation or cache load, the run, the results folder), "
        "and the seconds of it that `tracklab run` reports compiling or loading the program.",
        "",
        "| Compilation cache | Wall (s) | Of it compiling or loading (s) | Load average (1 min) |",
        "|---|---:|---:|---:|",
    ] + [f"| {lab} | {w:.1f} | {c:.1f} | {ld:.2f} |" for lab, w, c, ld in rows] + [""]
    _emit(lines, out)


def _emit(lines, out):
    md = "\n".join(lines)
    print(md)
    if out is not None:
        with open(out, "a") as f:
            f.write(md + "\n")


# ----------------------------------------------------------------------------- report


def machine_info():
    import jax

    model = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "date": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "nproc": os.cpu_count(),
        "cpu": model,
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": getattr(__import__("jaxlib"), "__version__", "?"),
        "backend": f"{jax.default_backend()} ({len(jax.devices())} device(s))",
        "loadavg": " ".join(f"{x:.2f}" for x in os.getloadavg()),
        "cache": jax.config.jax_compilation_cache_dir or "off",
    }


def _compile(r):
    """A compile time, or a note that the program was already held (runner.program returned 0)."""
    return "held" if r.get("held") else f"{r['compile_s']:.2f}"


def fmt_rate(x):
    return f"{x / 1e6:.2f} M" if x >= 1e6 else f"{x / 1e3:.0f} k"


def _mib(kib):
    return kib / 1024


def render(info, cmd, cfg, single, alls, sim, sweep, mems, total_s, load_end):
    L = []
    L.append("# Lidar benchmark (`experiments/lidar_crossing.toml`)")
    L.append("")
    L.append(f"- Date: {info['date']}")
    L.append(f"- Machine: nproc = {info['nproc']}, CPU = {info['cpu']} (model name from /proc/cpuinfo)")
    L.append(f"- Load average (1/5/15 min) at start: {info['loadavg']}; at end: {load_end}")
    L.append(f"- Python {info['python']}, jax {info['jax']}, jaxlib {info['jaxlib']}, backend {info['backend']}, float64")
    L.append(f"- Command: `{cmd}`")
    L.append(f"- Steps per run: {cfg['steps']}; chunk size {cfg['chunk']} unless stated "
             f"(`tracking.default_chunk` gives {cfg['default_chunk']} here: 1 000 per device)")
    L.append(f"- JAX persistent compilation cache in this process: {info['cache']}")
    L.append(f"- Total benchmark time: {total_s:.0f} s")
    L.append("")
    L.append(f"## Throughput and compile time ({cfg['runs']} runs, chunk {cfg['chunk']})")
    L.append("")
    L.append("Throughput = runs x steps / wall time of one full pass over all chunks with the compiled program "
             "(`runner.program`; simulate + filter + statistics, then transfer and host-side accumulation with "
             "`runner.Accumulator`, as `runner.run` does it); the fastest of "
             f"{cfg['repeat']} such pass(es) is kept. Compile = `runner.program`'s seconds (tracing, lowering, XLA "
             "compilation). 1st call = the compiled program's first call on one chunk, before the timed passes.")
    L.append("")
    L.append("| Filters | Throughput (runs·steps/s) | Wall (s) | Per chunk, median [min–max] (s) | Compile (s) | 1st call (s) | Wall / all-filters wall |")
    L.append("|---|---:|---:|---:|---:|---:|---:|")
    rows = list(single) + [alls] + [sim]
    for r in rows:
        name = ", ".join(r["labels"]) if len(r["labels"]) == 1 else f"**all {len(r['labels'])}**"
        if not r["labels"]:
            name = "(simulation alone, see below)"
        share = f"{100 * r['wall_s'] / alls['wall_s']:.0f} %"
        L.append(f"| {name} | {fmt_rate(r['throughput'])} | {r['wall_s']:.2f} | {r['steady_chunk_s']:.3f} "
                 f"[{r['min_chunk_s']:.3f}–{r['max_chunk_s']:.3f}] | {_compile(r)} | {r['first_call_s']:.2f} | {share} |")
    ssum = sum(r["wall_s"] for r in single)
    L.append("")
    L.append(f"Sum of the single-filter walls: {ssum:.2f} s (each includes the simulation, which alone "
             f"takes {sim['wall_s']:.2f} s); all in one program: {alls['wall_s']:.2f} s.")
    L.append("")
    L.append("Simulation alone: the tracking world cannot run with no filter (its chunk stacks one divergence "
             "row per filter), so this row is a world of the benchmark's own on the same runner "
             "(`bench_lidar.simulation_world`): each run's truth, measurements, prior mean and the PCRLB's "
             "expected information, from the run's key split as the tracking world splits it, summed over the "
             "runs. It draws each run whole; for these filters the tracking world draws the same numbers step "
             "by step inside its scan, so this is the simulation's cost measured apart, not exactly the part "
             "of the rows above that it stands for.")
    L.append("")
    L.append(f"## Chunk size (all filters, {cfg['runs']} runs)")
    L.append("")
    L.append("The last chunk is padded to full size (masked runs), so a chunk that does not divide the run "
             "count does some wasted work.")
    L.append("")
    L.append("| Chunk | Chunks | Throughput (runs·steps/s) | Wall (s) | Per chunk, median (s) | Compile (s) |")
    L.append("|---:|---:|---:|---:|---:|---:|")
    for r in sweep:
        L.append(f"| {r['chunk']} | {r['n_chunks']} | {fmt_rate(r['throughput'])} | {r['wall_s']:.2f} | "
                 f"{r['steady_chunk_s']:.3f} | {_compile(r)} |")
    L.append("")
    L.append("## Peak resident memory (all filters, fresh subprocess, `exp.monte_carlo`)")
    L.append("")
    L.append("`resource.getrusage(RUSAGE_SELF).ru_maxrss` in the child (KiB on Linux, shown in MiB): baseline after "
             "importing jax + tracklab, loading the experiment and initialising the backend; again after the first "
             "chunk (compile + run, via the progress callback); and at the end. VmHWM from /proc/self/status is the "
             "same high-water mark, as a cross-check. The child is started before the parent imports jax, because "
             "Linux carries the parent's peak RSS into a child's ru_maxrss across fork/exec (a child started from a "
             "parent that had run the throughput benchmarks reported a 916 MiB \"baseline\"). Wall = "
             "`MonteCarloResult.wall_s` (the whole call, compile included); compile = `MonteCarloResult.compile_s` "
             "(`runner.program`'s tracing, lowering and compiling; the child enables no persistent cache, so unless "
             "JAX_COMPILATION_CACHE_DIR is set this is a full compile).")
    L.append("")
    L.append("| Runs | Chunk | Baseline (MiB) | After 1st chunk (MiB) | Peak at end (MiB) | Increment (MiB) | VmHWM (MiB) | Wall (s) | Compile (s) | Throughput incl. compile (runs·steps/s) |")
    L.append("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for m in mems:
        b, f, p = _mib(m["baseline_kib"]), _mib(m["after_first_chunk_kib"]), _mib(m["peak_kib"])
        thr = m["runs"] * cfg["steps"] / m["wall_s"]
        L.append(f"| {m['runs']} | {m['chunk']} | {b:.0f} | {f:.0f} | {p:.0f} | {p - b:.0f} | {_mib(m['vmhwm_kib']):.0f} | "
                 f"{m['wall_s']:.1f} | {m['compile_s']:.1f} | {fmt_rate(thr)} |")
    L.append("")
    twice = sum(r["twice"] for r in rows + sweep)
    if twice:
        L.append(f"Chunks run a second time without their diverged runs (charged to the passes): {twice}.")
        L.append("")
    div = {k: v for r in rows + sweep for k, v in r["diverged"].items() if v}
    div.update({k: v for m in mems for k, v in m["diverged"].items() if v})
    L.append(f"Diverged runs: {div}" if div else "No diverged runs in any filter or configuration.")
    L.append("")
    return "\n".join(L)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke version: fewer runs, does not write lidar.md")
    ap.add_argument("--out", type=Path, default=None, help="Markdown output (default benchmarks/lidar.md; none with --quick)")
    ap.add_argument("--repeat", type=int, default=None,
                    help="timed passes per throughput measurement, fastest kept (default 2; 1 with --quick)")
    ap.add_argument("--million", action="store_true",
                    help="only the memory bound: 10^6 runs x 200 steps of the CMKF and the EKF in a fresh process")
    ap.add_argument("--first-result", action="store_true",
                    help="only the wall time of `tracklab run` (import included), cold and with a warm compilation cache")
    ap.add_argument("--child-memory", nargs=2, type=int, metavar=("RUNS", "CHUNK"), help=argparse.SUPPRESS)
    ap.add_argument("--labels", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()

    if a.child_memory:
        child_memory(*a.child_memory, labels=a.labels.split(",") if a.labels else None)
        return
    if a.million:
        million(a.out)
        return
    if a.first_result:
        first_result(a.out)
        return

    t_all = time.perf_counter()
    load_start = os.getloadavg()
    cmd = "python benchmarks/bench_lidar.py" + (" --quick" if a.quick else "")
    runs = 2000 if a.quick else 10_000
    mem_runs = 3000 if a.quick else 100_000
    chunk = DEFAULT_CHUNK
    repeat = a.repeat or (1 if a.quick else 2)
    if a.repeat:
        cmd += f" --repeat {a.repeat}"

    # Memory first, while this process has not imported jax (see render()).
    print(f"memory: {mem_runs} runs in a subprocess ...", flush=True)
    mems = [bench_memory(mem_runs, chunk)]
    m = mems[0]
    print(f"  baseline {_mib(m['baseline_kib']):.0f} MiB, after 1st chunk {_mib(m['after_first_chunk_kib']):.0f} MiB, "
          f"peak {_mib(m['peak_kib']):.0f} MiB, wall {m['wall_s']:.1f} s", flush=True)

    import tracklab

    tracklab.configure()  # one CPU device per core, Eigen single-threaded, 64-bit mode
    from tracklab.worlds.tracking.scan import default_chunk

    info = machine_info()
    info["loadavg"] = " ".join(f"{x:.2f}" for x in load_start)
    exp = _load()
    labels = [f.label for f in exp.filters]
    cfg = {"runs": runs, "chunk": chunk, "steps": exp.steps, "repeat": repeat,
           "default_chunk": default_chunk(exp.scenario, exp.sensor)}
    print(f"# {info}", flush=True)

    def log(r):
        print(f"  {r['labels'] or ['(sim only)']} runs={r['runs']} chunk={r['chunk']}: "
              f"{fmt_rate(r['throughput'])} runs*steps/s, wall {r['wall_s']:.2f} s, compile {_compile(r)} s, "
              f"1st call {r['first_call_s']:.2f} s", flush=True)

    single = []
    for lab in labels:
        single.append(bench_throughput([lab], runs, chunk, repeat=repeat))
        log(single[-1])
    sim = bench_throughput([], runs, chunk, repeat=repeat)
    log(sim)
    alls = bench_throughput(labels, runs, chunk, repeat=repeat)
    log(alls)

    sweep = []
    for c in (250, 1000, 4000):
        r = alls if c == chunk else bench_throughput(labels, runs, c, repeat=repeat)
        if c != chunk:
            log(r)
        sweep.append(r)

    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())
    md = render(info, cmd, cfg, single, alls, sim, sweep, mems, time.perf_counter() - t_all, load_end)
    print()
    print(md)
    out = a.out if a.out is not None else (None if a.quick else ROOT / "benchmarks" / "lidar.md")
    if out is not None:
        write_run(out, md, "bench_lidar.py")
        print(f"written {out}")


if __name__ == "__main__":
    main()
