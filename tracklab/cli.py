"""The ``tracklab`` command."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tracklab.errors import ConfigError
from tracklab.interrupts import raise_if_interrupted


def writes() -> bool:
    """``tracklab.processes.writes``, imported when first called: the command's module imports
    nothing before ``main`` has installed its SIGINT handler but what that needs."""
    from tracklab.processes import writes

    return writes()


def _formats(s):
    """--format: comma-separated figure formats (png, pdf, svg)."""
    from tracklab.report.figures import FORMATS

    given = tuple(f.strip().lower() for f in s.split(",") if f.strip())
    if not given or any(f not in FORMATS for f in given):
        raise argparse.ArgumentTypeError(f"{s!r}: figure formats from {', '.join(FORMATS)} (comma-separated)")
    return given


def _figures(args):
    """What the figures are written as: none (--no-figures), or the --format list (default PNG)."""
    return False if args.no_figures else args.format


def _positive_int(s):
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v} must be >= 1")
    return v


def _seconds(s):
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number of seconds") from None
    if not 0 < v < 1e6:
        raise argparse.ArgumentTypeError(f"{v:g} must be positive (and under 10⁶ s)")
    return v


def _seed(s):
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not an integer") from None
    if not 0 <= v < 2**32:
        raise argparse.ArgumentTypeError(f"{v} must be in [0, 2**32)")
    return v


def _size(s):
    from tracklab.memory import parse_size

    try:
        return parse_size(s)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{s!r} {e}") from None


def _fraction(s):
    try:
        v = float(s)
    except ValueError:
        v = float("nan")
    if not 0 < v < 1:
        raise argparse.ArgumentTypeError(f"{s!r} must be a relative half-width in (0, 1), e.g. 0.005")
    return v


def cmd_run(args) -> int:
    from tracklab.config import MAX_RUNS, load_experiment
    from tracklab.output import check_results_folder
    from tracklab.intervals import percent
    from tracklab.progress import Phases, wanted
    from tracklab.report.tables import terminal_table

    exp = load_experiment(args.experiment)
    per_run = exp.samples_per_run  # steps; closed loops: radar samples or servo ticks
    if args.runs is not None and (args.runs > MAX_RUNS or args.runs * per_run > 10**12):
        raise ConfigError(args.experiment, "--runs", args.runs, f"must be <= {MAX_RUNS} and runs x steps <= 1e12")
    target = args.precision
    if target is not None and args.runs is None and exp.target_precision is None:
        from tracklab.config.fields import AUTO_MAX_RUNS

        runs = max(2, min(AUTO_MAX_RUNS, 10**12 // per_run))  # the most --precision alone may take
    else:
        runs = args.runs or exp.runs
    out = Path(args.out) if args.out else Path("results") / exp.name
    check_results_folder(out, args.experiment)  # refused as --out (exp.run names its argument out)
    phases = Phases(exp.name, writes() and wanted(args.quiet))
    figures = _figures(args)

    progress = phases.callback(f"drawing the figures and writing {out}/" if figures else f"writing {out}/")
    extra = {"target_precision": target} if target is not None else {}
    for line in exp.before_runs():  # minutes without a line otherwise (a DEKF trained first): said in a log too
        if writes() and not args.quiet:
            print(f"{exp.name}: {line}", file=sys.stderr, flush=True)
    phases.phase("compiling the program (or loading it, compiled before)")
    doc = exp.run(runs=runs, seed=args.seed, out=out, progress=progress, figures=figures,
                  precision="float32" if args.float32 else None, max_memory=args.max_memory, **extra)
    if doc is None:  # a process other than 0 of a multi-process run: process 0 writes and prints
        return 0
    phases.done("done")
    print(f"# {exp.name}: {doc['runs']} runs x {exp.steps} steps, window {exp.window[0]}-{exp.window[1]}, "
          f"{doc['wall_s']:.1f} s wall, {doc['compile_s']:.1f} s of it compiling or loading the program")
    for label, info in (doc.get("training") or {}).items():  # before the runs, not in their wall time
        print(f"# {label}: trained first, {info['steps']} Adam steps in {info['wall_s']:.1f} s; held-out loss "
              f"{info['heldout_before']:.4g} -> {info['heldout_after']:.4g}")
    print(terminal_table(doc), end="")
    base = next((f["paired"]["baseline"] for f in doc["filters"].values() if "paired" in f), None)
    print(f"± : {percent(doc.get('level', 0.95))} interval over the runs" + (f"; Δ: paired difference to {base} on the "
          "same runs" if base else "") + f". Every column, with its caption: {out}/table.md (and table.csv)")
    print(f"results written to {out}/")
    return 0


def cmd_list(args) -> int:
    from tracklab.config.factories import kinds_of_ones_own, structural_keywords
    from tracklab.filters.factory import declared
    from tracklab.worlds.airborne.registry import TRACKERS
    from tracklab.worlds.servo.experiment import TARGET_KINDS
    from tracklab.worlds.servo.registry import ESTIMATORS
    from tracklab.filters.registry import KINDS
    from tracklab.scenarios import SCENARIOS
    from tracklab.sensors import SENSORS

    if args.markdown:  # the documentation's reference of the kinds
        from tracklab.config.reference import kinds_markdown

        sys.stdout.write(kinds_markdown())
        return 0
    folder = Path(args.dir or "experiments")
    if args.dir is not None and not folder.is_dir():
        raise ConfigError("tracklab list", "--dir", str(folder), "must be a folder (of experiment files)")
    print(f"experiments ({folder}/):")
    files = sorted(folder.glob("*.toml")) if folder.is_dir() else []
    for p in files:
        print(f"  {p}")
        for field, spec, factory in kinds_of_ones_own(p):  # the numbers a kind of one's own declares
            if isinstance(factory, ConfigError):
                print(f"  {'':<4}{spec} ({field}): {factory.allowed}")
                continue
            params = declared(factory)
            shown = ", ".join(q.describe(n, with_doc=True) for n, q in params.items()) if params else "declares no numbers"
            rest = structural_keywords(factory)
            print(f"  {'':<4}{spec} ({field}): {shown}" + (f"; structure: {', '.join(rest)}" if rest else ""))
    if not files:
        print("  (none)")
    print("filter kinds ([[filter]] of a file; parameters [unit] = default; * tunable (tracklab tune --params), "
          "× a sweep's scale factor (--grid NAME=LO:HI:N); any number sweeps by its path):")
    for k in KINDS.values():
        print(f"  {k.name:<16} {k.doc} [sensors: {', '.join(k.accepts)}]")
        print(f"  {'':<16}   {', '.join(p.describe(n) for n, p in k.params.items())}")
    own = '"package.module:factory"'
    print(f"  {own:<16} your own: factory(context, **the table's other keys) -> Filter (docs/own-filter.md)")
    print("sensors:")
    for k in SENSORS.values():
        print(f"  {k.name:<16} {k.doc}")
        print(f"  {'':<16}   {', '.join(p.describe(n) for n, p in k.params.items())}; p_detect, period [s], offset [s]")
    print(f"  {'':<16} every sensor, in clutter: clutter_density [per unit measurement volume], clutter_window or "
          "clutter_coverage [its units], max_returns = 16, snr [dB] (docs/clutter.md)")
    print(f"  {own:<16} your own: factory(Context(dt, steps, dim), **keys) -> CustomSensor(h, R, angles=...)")
    print("scenarios:")
    for k in SCENARIOS.values():
        print(f"  {k.name:<16} {k.doc}")
        if k.params:
            print(f"  {'':<16}   {', '.join(p.describe(n) for n, p in k.params.items())}")
    print(f"  {own:<16} your own: factory(Context(dt, steps, dim), **keys) -> a scenario, or truth(key)")
    print("airborne-radar trackers ([[tracker]] of an [airborne] file, paper 001):")
    for k in TRACKERS.values():
        print(f"  {k.name:<16} {k.doc}")
        fields = [p.describe(n) for n, p in k.params.items()] + [f"{n} = {c[0]} ({' | '.join(c)})"
                                                                  for n, c in k.choices.items()]
        if fields:
            print(f"  {'':<16}   {', '.join(fields)}")
    print("servo estimators ([[estimator]] of a [servo] file, paper 003):")
    for k in ESTIMATORS.values():
        print(f"  {k.name:<16} {k.doc}")
        print(f"  {'':<16}   {', '.join([p.describe(n) for n, p in k.params.items()] + [o.describe(n) for n, o in k.options.items()])}")
    print("servo modes ([[case]] of a [servo] file, paper 003): double_loop, velocity_lag, on_axis")
    print("servo targets ([target] of a [servo] file):")
    for k, desc in TARGET_KINDS.items():
        print(f"  {k:<16} {desc}")
    return 0


def cmd_tune(args) -> int:
    import math

    from tracklab.config import load_experiment
    from tracklab.studies.files import check_tune, run_tune

    exp = load_experiment(args.experiment)
    names = [n.strip() for n in args.params.split(",") if n.strip()]
    declared = exp.declared()
    tunable = list(dict.fromkeys(n for d in declared.values() for n, p in d.items() if p.tune))
    bad = [n for n in names if n not in tunable]
    if not names or bad:
        raise ConfigError(args.experiment, "--params", args.params, f"must name parameters among "
                          f"{', '.join(tunable) or '(none: no filter here declares a tunable number)'}")
    losses = list(exp.tune_losses)
    args.loss = args.loss or losses[0]
    if args.loss not in losses:
        raise ConfigError(args.experiment, "--loss", args.loss, f"must be one of {', '.join(losses)}")
    if not (args.lr > 0 and math.isfinite(args.lr)):
        raise ConfigError(args.experiment, "--lr", args.lr, "must be a finite number > 0")
    labels = [l.strip() for l in args.filters.split(",")] if args.filters else None
    known = exp.tables()[1]
    if labels is not None and (not labels or any(l not in known for l in labels)):
        raise ConfigError(args.experiment, "--filters", args.filters, f"must name filter labels from: {', '.join(known)}")
    folder = Path(args.results) if args.results else Path("results") / f"{exp.name}_tune"
    out = Path(args.out) if args.out else folder.with_name(f"{exp.name}_tuned.toml")  # beside the results
    check_tune(exp, names, labels, out, args.runs_per_step, args.max_memory, folder=folder)

    if writes():
        from tracklab.progress import Phases, wanted

        Phases(exp.name, wanted(False)).phase(f"compiling the tuning program ({', '.join(names)}; {args.loss}), then "
                                              f"a line every {args.every} steps")
    run_tune(exp, names, steps=args.steps, lr=args.lr, loss=args.loss, runs_per_step=args.runs_per_step,
             labels=labels, out_toml=out, folder=folder,
             log=lambda line: (raise_if_interrupted(), writes() and print(line, flush=True)), every=args.every,
             figures=_figures(args))
    return 0


def cmd_sweep(args) -> int:
    from tracklab.config import MAX_RUNS, load_experiment
    from tracklab.output import check_results_folder
    from tracklab.config.paths import parse_grid
    from tracklab.studies.sweep import grid_points, sweep
    from tracklab.progress import Phases, wanted
    from tracklab.report.sweep import no_figures, runs_text, write_sweep

    exp = load_experiment(args.experiment)
    axes = []
    for g in args.grid:
        try:
            axes.append(parse_grid(g))
        except ValueError as e:
            raise ConfigError(args.experiment, "--grid", g, str(e)) from None
    if args.runs is not None and args.runs > MAX_RUNS:
        raise ConfigError(args.experiment, "--runs", args.runs, f"must be <= {MAX_RUNS}")
    out = Path(args.out) if args.out else Path("results") / f"{exp.name}_sweep"
    check_results_folder(out, args.experiment)

    phases = Phases(f"{exp.name} sweep", writes() and wanted(args.quiet), unit="runs (all grid points)")

    progress = phases.callback()
    phases.phase("compiling the grid's programs (or loading them, compiled before)")
    doc = sweep(exp, axes, runs=args.runs, progress=progress, max_memory=args.max_memory,  # checks grid and memory first
                log=lambda line: writes() and print(f"{exp.name} sweep: {line}", file=sys.stderr, flush=True))
    phases.phase(f"drawing the figures and writing {out}/" if _figures(args) else f"writing {out}/")
    if not writes():  # process 0 of a multi-process run writes and prints
        return 0
    n = grid_points(axes)
    print(f"# {exp.name}: {n} grid points x {runs_text(doc['runs'])} runs, {doc['wall_s']:.1f} s wall, "
          f"{doc['compile_s']:.1f} s of it compiling or loading the program")
    write_sweep(exp, doc, out, figures=_figures(args))
    phases.done("done")
    print((out / "table.md").read_text(), end="")
    if not args.no_figures and no_figures(doc):
        print(no_figures(doc))
    print(f"sweep written to {out}/")
    return 0


def cmd_table(args) -> int:
    from tracklab.reproduce import METRICS, combined_table, read_stats

    metrics = tuple(m.strip() for m in args.metrics.split(",")) if args.metrics else tuple(METRICS)
    bad = [m for m in metrics if m not in METRICS]
    if bad:
        raise ConfigError("tracklab table", "--metrics", ",".join(bad), f"must be among {', '.join(METRICS)}")
    docs = [read_stats(d) for d in args.results]  # each checked: one line for a bad one
    print(combined_table(args.results, args.format, metrics, docs), end="")
    return 0


def cmd_reproduce(args) -> int:
    import tempfile

    from tracklab.progress import Phases, wanted
    from tracklab.reproduce import reproduce

    out = args.out or (tempfile.mkdtemp(prefix="tracklab-quick-") if args.quick else "results")
    phases = Phases("reproduce", wanted(args.quiet))  # each experiment's runs: a bar on a terminal
    folders = reproduce(args.experiments, out, quick=args.quick, max_memory=args.max_memory,
                        figures=_figures(args), progress=phases.callback())
    print(f"{len(folders)} results folders and {Path(out) / 'README.md'} (combined table) rebuilt")
    return 0


def cmd_plot(args) -> int:
    from tracklab.report.redraw import redraw

    kinds = None if args.figures is None else tuple(k.strip() for k in args.figures.split(",") if k.strip())
    for folder in args.folders:
        written = redraw(folder, args.format, None if kinds is None else _figure_kinds(kinds))
        print(f"{folder}: {', '.join(written) if written else 'no figure to draw'}")
    return 0


def _figure_kinds(kinds):
    from tracklab.report.figures import FIGURE_KINDS

    if kinds == ("all",):
        return FIGURE_KINDS
    bad = [k for k in kinds if k not in FIGURE_KINDS]
    if bad or not kinds:
        raise ConfigError("tracklab plot", "--figures", ",".join(bad), f"must be all or among {', '.join(FIGURE_KINDS)}")
    return kinds


class _Parser(argparse.ArgumentParser):
    """argparse with a bad argument refused in one line (exit 2), like every other bad input."""

    def error(self, message):
        print(f"error: {self.prog}: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def build_parser():
    """The command's parser. It imports nothing heavy (no JAX, no registry of kinds), so that
    ``--help`` and a bad argument answer at once; ``tracklab list`` names the kinds and numbers."""
    p = _Parser(prog="tracklab", description="Monte-Carlo evaluation of tracking filters. `tracklab list` describes "
                "every filter, scenario and sensor kind and the numbers each declares")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    many = _Parser(add_help=False)  # several processes (jax.distributed): run, sweep and tune
    g = many.add_argument_group("several processes (one per host or GPU; docs/devices.md)")
    g.add_argument("--coordinator", metavar="HOST:PORT", help="process 0's address (or TRACKLAB_COORDINATOR)")
    g.add_argument("--processes", type=_positive_int, metavar="N", help="process count (or TRACKLAB_PROCESSES)")
    g.add_argument("--process-id", type=int, metavar="I", help="this process, 0 … N-1 (or TRACKLAB_PROCESS_ID)")
    g.add_argument("--process-timeout", type=_seconds, metavar="S",
                   help="seconds to wait for the other processes at the start and at the end "
                        "(default 60; or TRACKLAB_PROCESS_TIMEOUT)")
    r = sub.add_parser("run", help="run an experiment file and write its results folder", parents=[many])
    r.add_argument("experiment")
    r.add_argument("--runs", type=_positive_int, help="Monte-Carlo runs (default: the file's)")
    r.add_argument("--seed", type=_seed, help="random seed (default: the file's)")
    r.add_argument("--out", help="results folder (default: results/<name>/)")
    r.add_argument("--no-figures", action="store_true", help="skip the figures")
    r.add_argument("--quiet", action="store_true", help="no phases or progress bar on stderr (none either when "
                                                        "stderr is not a terminal)")
    r.add_argument("--format", type=_formats, default=("png",), metavar="FMT",
                   help="figure formats, comma-separated: png (150 dpi), pdf, svg (vector, for papers); default png")
    r.add_argument("--float32", action="store_true", help="single precision (as precision = \"float32\")")
    r.add_argument("--precision", type=_fraction, metavar="REL",
                   help="run until every filter's position-RMSE interval is within ± REL of it (e.g. 0.005; "
                        "--runs is then the most it may take)")
    r.add_argument("--max-memory", type=_size, help="refuse an experiment needing more (e.g. 8G; default: this machine's memory)")
    r.set_defaults(func=cmd_run)
    tu = sub.add_parser("tune", help="tune filter parameters by gradient descent through the Monte-Carlo runs",
                        parents=[many])
    tu.add_argument("experiment")
    tu.add_argument("--params", required=True, help="comma-separated names of the numbers to tune (q, r, lam, …; "
                                                      "tracklab list marks the tunable ones)")
    tu.add_argument("--steps", type=_positive_int, default=200)
    tu.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (unconstrained coordinates)")
    tu.add_argument("--loss", help="mse_pos (default) | pred_mse | nll; airborne: pointing (default) | los_rate; "
                                   "servo: track_mse (default) | rate_mse")
    tu.add_argument("--runs-per-step", type=_positive_int, default=None, help="fresh runs per step (default 256)")
    tu.add_argument("--filters", default=None, help="comma-separated labels (default: every filter with the parameters)")
    tu.add_argument("--every", type=_positive_int, default=10, help="progress line every N steps")
    tu.add_argument("--results", help="results folder: tune.json, table.md, loss.png, tune.log "
                                      "(default: results/<name>_tune/)")
    tu.add_argument("--out", help="tuned experiment file (default: <name>_tuned.toml beside the results folder)")
    tu.add_argument("--max-memory", type=_size, help="refuse a tuning needing more (default: this machine's memory)")
    tu.add_argument("--no-figures", action="store_true", help="skip loss.png")
    tu.add_argument("--format", type=_formats, default=("png",), metavar="FMT", help="figure formats: png, pdf, svg")
    tu.set_defaults(func=cmd_tune)
    sw = sub.add_parser("sweep", help="evaluate every filter on a grid of values of any numbers of the file, or of "
                                      "filter-parameter scale factors", parents=[many])
    sw.add_argument("experiment")
    sw.add_argument("--grid", action="append", required=True, help="PATH=LO:HI:N (evenly spaced) or PATH=LO:HI:N:log values of a number of the file (sensor.sigma_r, "
                         "scenario.speed, filter[EKF].accel_sigma, tracker[joint EKF].q_scale); or NAME=LO:HI:N, "
                         "log-spaced scale factors of a filter parameter (q, r, …; tracklab list marks the sweepable "
                         "ones). Repeat for a 2-D grid")
    sw.add_argument("--runs", type=_positive_int, help="Monte-Carlo runs per grid point (default: the file's)")
    sw.add_argument("--out", help="folder (default: results/<name>_sweep/)")
    sw.add_argument("--no-figures", action="store_true")
    sw.add_argument("--quiet", action="store_true", help="no phases or progress bar on stderr")
    sw.add_argument("--format", type=_formats, default=("png",), metavar="FMT", help="figure formats: png, pdf, svg")
    sw.add_argument("--max-memory", type=_size, help="refuse a sweep needing more (default: this machine's memory)")
    sw.set_defaults(func=cmd_sweep)
    tb = sub.add_parser("table", help="one error-statistics table from several results folders")
    tb.add_argument("results", nargs="+")
    tb.add_argument("--format", choices=("md", "csv", "latex"), default="md")
    tb.add_argument("--metrics", help="comma-separated summary keys (default: all)")
    tb.set_defaults(func=cmd_table)
    rp = sub.add_parser("reproduce", help="run every experiment and rebuild results/")
    rp.add_argument("--quick", action="store_true", help="20 runs each, into a temporary folder (a smoke check)")
    rp.add_argument("--experiments", default="experiments")
    rp.add_argument("--out", help="results folder (default results/, or a temporary one with --quick)")
    rp.add_argument("--max-memory", type=_size, help="refuse experiments needing more (default: this machine's memory)")
    rp.add_argument("--no-figures", action="store_true", help="skip the figures (the numbers alone)")
    rp.add_argument("--format", type=_formats, default=("png",), metavar="FMT", help="figure formats: png, pdf, svg")
    rp.add_argument("--quiet", action="store_true", help="no progress bars on stderr")
    rp.set_defaults(func=cmd_reproduce)
    pl = sub.add_parser("plot", help="draw a results folder's figures again from its statistics (other formats, other "
                                     "figure kinds), running nothing")
    pl.add_argument("folders", nargs="+", metavar="FOLDER", help="a run's results folder (tracklab run, reproduce)")
    pl.add_argument("--format", type=_formats, default=("png",), metavar="FMT", help="figure formats: png, pdf, svg")
    pl.add_argument("--figures", metavar="KINDS", help="comma-separated figure kinds of a tracking run, or all "
                                                        "(default: those the experiment file names, else all)")
    pl.set_defaults(func=cmd_plot)
    ls = sub.add_parser("list", help="experiment files, filter kinds (with their sensors and parameters), sensors and scenarios")
    ls.add_argument("--dir", default=None, help="folder of experiment files (default: experiments/, if there is one)")
    ls.add_argument("--markdown", action="store_true", help="the kinds and their numbers as the documentation's "
                                                             "Markdown reference (docs/kinds.md)")
    ls.set_defaults(func=cmd_list)
    return p


def _compilation_cache():
    """Keep compiled programs between invocations: JAX's persistent cache, and beside it the
    runner's own store (``montecarlo.programs``), which a new process finds before tracing.

    TRACKLAB_CACHE_DIR chooses the folder (JAX's cache in it, the store in its ``programs``
    folder); an empty value turns both off. JAX's own JAX_COMPILATION_CACHE_DIR, when set,
    takes precedence for JAX's cache.
    """
    import os

    folder = os.environ.get("TRACKLAB_CACHE_DIR", str(Path.home() / ".cache" / "tracklab" / "jax"))
    if not folder:
        return
    from tracklab.montecarlo import programs

    programs.keep_in(Path(folder) / "programs")
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def _interrupted_exit():
    import contextlib
    import os

    from tracklab.interrupts import hold_interrupts, written

    hold_interrupts()  # a second Ctrl-C cannot cut this line short
    done = written()
    what = f"{', '.join(map(str, done))} written in full before it" if done else "previous results left untouched"
    end_progress = "\n" if sys.stderr.isatty() else ""  # a progress line drawn with \r is ended first
    with contextlib.suppress(OSError, ValueError):  # a closed pipe
        sys.stdout.flush()
    with contextlib.suppress(OSError, ValueError):
        print(f"{end_progress}interrupted: {what}", file=sys.stderr, flush=True)
    # the temporary folder is already gone; skip interpreter teardown, which can crash
    # while XLA's worker threads are still inside a computation
    os._exit(130)


def _what_runs(args) -> dict:
    """What a process of several runs, compared between them before they start: the command, its
    options (not the process's own, nor where process 0 writes) and the experiment file's contents."""
    own = {"coordinator", "processes", "process_id", "process_timeout", "func", "out", "results", "experiment"}
    what = {k: v for k, v in vars(args).items() if k not in own}
    try:
        what["experiment file contents"] = Path(args.experiment).read_bytes()
    except OSError:  # the command refuses it in its own words
        what["experiment file"] = args.experiment
    return what


def _end_processes(meeting, code):
    """Meet the other processes at the end; one of them gone: one line, and this process ends now."""
    import os

    from tracklab import processes

    end = processes.finish(meeting, code)
    if end is None:
        return
    status, line = end
    sys.stdout.flush()
    if line:
        print(line, file=sys.stderr, flush=True)
    os._exit(status)


class _Reader:
    """Standard output for a reader that may stop reading (``tracklab run … | head``): once the
    pipe is closed, what is printed is dropped and the command goes on (its results are written
    all the same); every other error is the stream's own."""

    def __init__(self, stream):
        self.stream = stream

    def _closed(self):
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self.stream.fileno())  # the C-level writes and the last flush too
        os.close(devnull)

    def write(self, text):
        try:
            return self.stream.write(text)
        except BrokenPipeError:
            self._closed()
            return len(text)

    def flush(self):
        try:
            self.stream.flush()
        except BrokenPipeError:
            self._closed()

    def __getattr__(self, name):  # isatty, fileno, encoding, …: the stream's
        return getattr(self.stream, name)


def _main(argv) -> int:
    from tracklab.interrupts import interrupted

    from tracklab.runtime import configure

    if argv is None and not isinstance(sys.stdout, _Reader):
        sys.stdout = _Reader(sys.stdout)
    args = build_parser().parse_args(argv)
    raise_if_interrupted()  # one that came while JAX and the registries were imported
    configure()  # one CPU device per core, single-threaded Eigen, 64-bit mode (before JAX starts)
    meeting = None
    if hasattr(args, "processes"):
        from tracklab import processes

        try:
            several = processes.settings(args.coordinator, args.processes, args.process_id, args.process_timeout)
            if several is not None or processes.cluster_size() > 1:
                processes.quiet_runtime_logs()
            meeting = processes.start(several, _what_runs(args))
        except ValueError as e:
            print(f"error: tracklab {args.command}: {e}", file=sys.stderr)
            return 2
        except processes.ProcessError as e:
            print(f"error: tracklab {args.command}: {e}", file=sys.stderr)
            return e.exit_status
    _compilation_cache()
    try:
        code = args.func(args)
    except ConfigError as e:
        code = 2
        if not interrupted():
            print(f"error: {e}", file=sys.stderr)
    except KeyboardInterrupt:
        _interrupted_exit()
    except MemoryError:
        code = 1
        print("error: out of memory (previous results left untouched): set a smaller chunk, fewer steps or "
              "runs, or --max-memory to be refused before starting", file=sys.stderr)
    except OSError as e:  # a write that failed after the checks (a full disk): nothing half-written is left
        code = 1
        where = f" ({e.filename})" if e.filename else ""
        print(f"error: cannot write{where}: {e.strerror or e} (previous results left untouched)", file=sys.stderr)
    except Exception as e:  # several processes: an exchange of sums that failed (a process gone)
        if meeting is None:
            raise
        code = 1
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:300]
        print(f"error: tracklab {args.command}: process {meeting.settings.process_id} of {meeting.settings.processes} "
              f"stops (nothing written): {first}", file=sys.stderr)
    if meeting is not None:
        _end_processes(meeting, code)
    if interrupted():  # a Ctrl-C whose KeyboardInterrupt was swallowed (e.g. inside a callback)
        _interrupted_exit()
    return code


def _guarded(argv) -> int:
    """``_main``; an exception of any kind after a SIGINT (the interrupt itself, or what it turned
    into inside a library) ends the command in one line, exit 130."""
    from tracklab.interrupts import interrupted

    try:
        code = _main(argv)
    except BaseException as e:
        if interrupted() or isinstance(e, KeyboardInterrupt):
            _interrupted_exit()
        raise
    if interrupted():
        _interrupted_exit()
    return code


def _end(code):
    """End the command's process with ``code``, or with exit 130 and one line if a SIGINT came
    at any moment before: SIGINT is only recorded from here on, the exit functions run (JAX's,
    the processes'), then SIGINT is blocked and the record and the pending signals are read
    last, and the process exits without the interpreter's teardown."""
    import atexit
    import contextlib
    import os
    import signal

    from tracklab.interrupts import hold_interrupts, interrupted

    hold_interrupts()
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message")
        print(code, file=sys.stderr)
        code = 1
    try:
        sys.stdout.flush()
    except (OSError, ValueError):  # a closed pipe (| head): as Python's own exit, 120
        code = code or 120
    with contextlib.suppress(OSError, ValueError):
        sys.stderr.flush()
    atexit._run_exitfuncs()
    pending = False
    if hasattr(signal, "pthread_sigmask") and hasattr(signal, "sigpending"):
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        pending = signal.SIGINT in signal.sigpending()
    if interrupted() or pending:
        _interrupted_exit()
    for stream in (sys.stdout, sys.stderr):  # what the exit functions printed
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


def main(argv=None) -> int:
    """The ``tracklab`` command; ``argv``: its arguments (default: the command line's).

    Ctrl-C: the SIGINT handler is installed first (``tracklab.interrupts``), before anything
    heavy is imported, and a SIGINT at any moment ends the command with one line on stderr
    ("interrupted: …") and exit 130: never a traceback, never a finished run with exit 0.
    Without ``argv`` (the console script, ``python -m tracklab.cli``) ``main`` ends the process
    itself, so that a SIGINT that arrives while it exits counts too; with ``argv`` it returns the
    exit status (argparse's refusals raise SystemExit)."""
    try:
        from tracklab.interrupts import catch_interrupts

        put_back = catch_interrupts()
        if argv is not None:
            try:
                return _guarded(argv)
            finally:
                put_back()  # inside another program (a test): its own SIGINT handling again
        try:
            code = _guarded(None)
        except SystemExit as e:  # argparse: --help, a bad argument
            code = e.code
    except KeyboardInterrupt:  # Python's own handler's, before catch_interrupts replaced it
        _interrupted_exit()
    _end(code)


if __name__ == "__main__":
    sys.exit(main())
