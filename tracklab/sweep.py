"""Sweeps: a grid of values evaluated by one compiled program, on common random numbers.

Two kinds of axis (``--grid``):

* ``NAME=LO:HI:N`` with NAME a filter parameter its kind declares sweepable (``q``, ``r``,
  ``lam``, ``alpha``, …; ``SCALABLE``): N log-spaced *scale factors* from LO to HI, multiplying that
  parameter of every filter (of every tracker of an airborne file: q its Q, r its
  R; of every estimator of a servo file) — the noise-mismatch study of paper 001.
* ``PATH=LO:HI:N`` (evenly spaced) or ``PATH=LO:HI:N:log``: N *values* of any
  number of the file. PATH is ``section.field`` (``sensor.sigma_r``,
  ``scenario.speed``, ``engagement.turn_g``, ``servo.noise``) or, in an array of
  tables, ``section[LABEL].field`` with the entry's label (a sensor's name; or its
  1-based index): ``filter[EKF].accel_sigma``, ``tracker[joint EKF].q_scale``.

Each grid point is the file with those values, validated as the file itself is;
its numbers are a parameter set of the same compiled program (numbers are inputs:
a value that would change the program — a step count, a kind — is refused). The
parameter sets of a block of points are stacked along a leading axis and run on
the same runs (run i draws from ``fold_in(key, i)`` at every point), so
differences between points are the parameters', not the noise's. Grid points and
runs are processed in blocks so memory stays bounded.
"""

from __future__ import annotations

import copy
import csv
import io
import itertools
import time
from pathlib import Path

import jax
import numpy as np

from tracklab.config import parse_experiment
from tracklab.config.paths import Axis, set_value, table_of
from tracklab.errors import ConfigError
from tracklab.montecarlo import runner
from tracklab.output import atomic_folder
from tracklab.intervals import with_half_width
from tracklab.report import md_cell, write_json

def _path_of(exp, a: Axis):
    """The file's value at a PATH axis (None when the file leaves it to its default); ConfigError
    in one line for a PATH that names no number of the file."""
    try:
        table = table_of(copy.deepcopy(exp.raw), a.path, create=True)
    except ValueError as e:
        raise ConfigError(exp.path, "--grid", a.name, str(e)) from None
    v = table.get(a.path[2])
    if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
        kind = type(v).__name__.replace("str", "a string").replace("list", "a list").replace("dict", "a table")
        raise ConfigError(exp.path, "--grid", a.name, f"is not a number in the file (it is {kind}): only numbers "
                          "can be swept")
    return v


def grid_points(axes: list[Axis]) -> int:
    return int(np.prod([len(a.values) for a in axes], dtype=float))


def _call_shape(exp, points, runs, chunk=None, block_points=None):
    """(runs, grid points) of one call: memory per call grows with grid points × runs × steps,
    kept near 10⁶ run-steps."""
    budget = 1_000_000
    steps = getattr(exp, "ticks", exp.steps)
    chunk = int(min(chunk or exp.chunk or 1000, runs, max(1, budget // steps)))  # a sweep's own program
    return chunk, int(block_points or max(1, min(points, budget // (chunk * steps))))


def memory_bytes(exp, axes: list[Axis], runs=None) -> float:
    """A lower bound: every grid point's per-step statistics of every filter (kept until the
    sweep is written), and one call's per-step values."""
    P = grid_points(axes)
    chunk, block = _call_shape(exp, P, runs or exp.runs)
    lanes = len(exp.structure().labels)
    width = 2 * exp.dim + exp.sensor.m if hasattr(exp, "sensor") else 12
    per_point = exp.steps * (lanes * 64 + getattr(exp, "dim", 1) ** 2) * 8.0
    return P * per_point + block * chunk * getattr(exp, "ticks", exp.steps) * width * 4.0


def check_sweep(exp, axes: list[Axis], runs=None, limit=None):
    """Refuse (ConfigError, one line) what a sweep cannot mean: an axis named twice, a scale factor
    of a parameter no filter has, a PATH that names no number, ``--runs`` beside an axis of the
    runs, an estimator trained before its run, or a grid too large to hold. Each grid point is
    checked as a file when the sweep reads it (``points``)."""
    from tracklab.memory import check

    names = [a.name for a in axes]
    if len(set(names)) != len(names):
        raise ConfigError(exp.path, "--grid", " ".join(names), "each parameter may appear once")
    for a in axes:
        if a.path is None and not _scales(exp, a.name):
            raise ConfigError(exp.path, "--grid", a.name, f"no filter of this experiment declares a scalable "
                              f"parameter {a.name!r} (scalable here: {', '.join(_scalable(exp)) or 'none'})")
        if a.path is not None:
            _path_of(exp, a)
        if a.path == ("experiment", None, "runs") and runs is not None:
            raise ConfigError(exp.path, "--runs", runs, f"the grid sets each point's runs ({a.name}): give one of them")
    if getattr(exp, "trained_first", list)():
        raise ConfigError(exp.path, "--grid", " ".join(names), "an estimator trained before its run (train_steps > 0) "
                          "cannot be swept: set train_steps = 0, or sweep the trained weights through the Python API")
    check(exp.path, memory_bytes(exp, axes, runs), limit, f"a sweep of {grid_points(axes):.3g} grid points",
          "fewer grid points (N in NAME=LO:HI:N), or fewer experiment.steps")


def _scalable(exp) -> list[str]:
    """The parameter names a scale-factor axis may name in this experiment."""
    if hasattr(exp, "filters"):
        return list(dict.fromkeys(n for fc in exp.filters for n, p in exp.declared(fc).items() if p.sweep))
    if hasattr(exp, "trackers"):
        return ["q", "r"] if any(t.kind != "classical" for t in exp.trackers) else []
    return ["q", "r"] if getattr(exp, "estimators", ()) else []


def _scales(exp, name) -> bool:
    """Whether a scale-factor axis ``name`` scales something in this experiment."""
    return name in _scalable(exp)


def point(exp, axes: list[Axis], values):
    """One grid point: (the file with the PATH values set, validated as a file is; its params, scale
    factors applied). ConfigError in one line naming the point for a value the file refuses."""
    raw, factors = None, {}
    for a, v in zip(axes, values):
        if a.path is None:
            factors[a.name] = float(v)
        else:
            raw = raw if raw is not None else copy.deepcopy(exp.raw)
            set_value(raw, a.path, v)
    if raw is None:
        at = exp
    else:
        try:
            at = parse_experiment(exp.path, raw)
        except ConfigError as e:
            what = ", ".join(f"{a.name} = {v:g}" for a, v in zip(axes, values) if a.path is not None)
            raise ConfigError(exp.path, "--grid", what, f"gives an invalid file: {e.field} = {e.value!r}: {e.allowed}") from None
    params = at.params()
    return at, (at.scaled(params, factors) if factors else params)


def _shape(params):
    leaves, treedef = jax.tree_util.tree_flatten(params)
    return treedef, tuple((np.shape(a), np.asarray(a).dtype.name) for a in leaves)


def sweep(exp, axes: list[Axis], runs=None, seed=None, block_points=None, chunk=None, progress=None, max_memory=None,
          log=None):
    """Statistics of every filter at every grid point: {"points": [{"values", "stats"}], ...}.

    Each point is the file with its values (``point``), run as ``tracklab run`` would run it:
    its own runs, seed, precision, report level and baseline (``runs``: every point's runs
    instead). Points whose programs are alike — the same structure, params of the same shapes,
    the same runs and seed — are one program: their parameter sets stacked along a leading axis
    and run on the same runs (the runner's ``points``), a block at a time. A value that changes
    the program (a step count, a kind, a number a filter of one's own compiles in) makes the
    grid several programs, one per value; ``log`` is told which axes do."""
    check_sweep(exp, axes, runs, max_memory)
    values = list(itertools.product(*[a.values for a in axes]))
    names = [a.name for a in axes]
    P = len(values)
    made = [point(exp, axes, v) for v in values]  # every point checked before anything runs
    most = max(int(runs or at.runs) for at, _ in made)  # one chunk size for any runs a point asks
    groups: dict = {}
    for j, (at, params) in enumerate(made):
        c, block = _call_shape(at, P, most, chunk, block_points)
        program = (at.structure(c, most * block), _shape(params), at.precision, c, block)
        groups.setdefault((program, int(runs or at.runs), at.seed if seed is None else seed), []).append(j)
    keys = list(groups)
    programs = {k[0] for k in keys}
    of = _group_of(groups, P)
    structural = [a.name for i, a in enumerate(axes) if _changes(values, i, [k[0] for k in of])]
    separate = [a.name for i, a in enumerate(axes) if a.name not in structural and _changes(values, i, of)]
    if log and structural:
        log(f"{', '.join(structural)} {'changes' if len(structural) == 1 else 'change'} what is compiled: "
            f"{len(programs)} programs for the {P} grid points, one per value")
    if log and separate:
        log(f"{', '.join(separate)}: each value runs on runs of its own ({len(keys)} calls of "
            f"{'the same program' if len(programs) == 1 else 'the programs'})")
    total = sum(k[1] * -(-len(groups[k]) // k[0][4]) for k in keys)
    stats, compile_s, done = [None] * P, 0.0, 0
    t0 = time.perf_counter()
    for key in keys:
        (structure, _, precision, c, block), n_runs, n_seed = key
        world = made[groups[key][0]][0].world(structure)
        members = groups[key]
        for b0 in range(0, len(members), block):
            js = members[b0:b0 + block]
            sets = [made[j][1] for j in js]
            sets += sets[-1:] * (block - len(sets))  # the last block padded to the same program
            stacked = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *sets)
            tick = (lambda d, t, base=done: progress(base + d, total)) if progress else None
            out = runner.run(world, stacked, n_runs, n_seed, precision=precision, points=block, progress=tick)
            done += n_runs
            compile_s += out.compile_s
            for i, j in enumerate(js):
                stats[j] = made[j][0].summarise(structure, runner.pick(stacked, i), runner.pick(out.sums, i), out, i)
    wall = time.perf_counter() - t0
    doc_points = [{"values": dict(zip(names, map(float, v))), "stats": st} for v, st in zip(values, stats)]
    each = sorted({int(runs or at.runs) for at, _ in made})
    return {"axes": {a.name: a.values.tolist() for a in axes}, "titles": {a.name: a.title for a in axes},
            "log": {a.name: a.log for a in axes}, "points": doc_points, "wall_s": wall, "compile_s": compile_s,
            "runs": each[0] if len(each) == 1 else each, "programs": len(programs), "structural": structural,
            "units": list(exp.units), "nees_dof": getattr(exp, "nees_dof", None),
            "metrics": [[k, t.format(pos=exp.units[0])] for k, t in exp.sweep_metrics]}


def _group_of(groups: dict, P: int) -> list:
    """Each grid point's group key."""
    out = [None] * P
    for k, js in groups.items():
        for j in js:
            out[j] = k
    return out


def _changes(values, i, where) -> bool:
    """Whether axis ``i`` alone puts grid points into different groups (``where``: each point's)."""
    seen: dict = {}
    for v, w in zip(values, where):
        if seen.setdefault(v[:i] + v[i + 1:], w) != w:
            return True
    return False


def write_sweep(exp, doc, out, figures=True):
    """sweep.json, table.md, table.csv and heatmaps (1-D: curves) of RMSE and NEES per filter."""
    with atomic_folder(Path(out), exp.path) as tmp:
        return _write_sweep(exp, doc, tmp, figures)


def _csv(v):
    return v if v is not None and np.isfinite(v) else ""


_NOT_METRICS = ("runs", "diverged", "lost_lock", "healthy_runs")


def _metrics(summary: dict) -> list[str]:
    """The columns of a sweep's table: the headline statistics of the world's summaries."""
    if "pred_err_rms" in summary:  # open-loop tracking
        return (["rmse_pos", "rmse_vel", "pred_err_rms"] + [k for k in summary if k.startswith("pred_err_max[")]
                + ["nees", "nees_in_bounds"])
    return [k for k, v in summary.items() if k not in _NOT_METRICS and (v is None or isinstance(v, (int, float)))]


def _write_sweep(exp, doc, tmp, figures):
    names = list(doc["axes"])
    labels = list(doc["points"][0]["stats"]["filters"])
    metrics = _metrics(doc["points"][0]["stats"]["filters"][labels[0]]["summary"])
    rows, hws = [], []
    for p in doc["points"]:
        for l in labels:
            f = p["stats"]["filters"][l]
            s, hw = f["summary"], f.get("half_width", {})
            rows.append([*(p["values"][n] for n in names), l, *(s.get(m) for m in metrics), s.get("diverged", 0)])
            hws.append([hw.get(m) for m in metrics])
    with_hw = [m for j, m in enumerate(metrics) if any(h[j] is not None for h in hws)]
    heads = [n if "." in n else f"{n} x" for n in names]
    header = [*heads, "filter", *metrics, "diverged"]
    lines = ["| " + " | ".join(md_cell(h) for h in header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    for r, h in zip(rows, hws):
        cells = ([f"{v:.4g}" for v in r[:len(names)]] + [md_cell(r[len(names)])]
                 + [with_half_width(v, hw, "{:.4g}") for v, hw in zip(r[len(names) + 1:-1], h)] + [str(int(r[-1]))])
        lines.append("| " + " | ".join(cells) + " |")
    level = doc["points"][0]["stats"].get("level", 0.95)
    same = ("every point on the same runs" if doc.get("programs", 1) == 1 else
            f"the grid ran as {doc['programs']} programs, {', '.join(doc.get('structural')) or 'runs or seed'} changing "
            "what is compiled: the points of one program on the same runs")
    caption = (f"\n± : half-width of the {level:.0%} confidence interval over the {runs_text(doc['runs'])} runs at each "
               f"point ({same}).\n") if with_hw else ""
    (tmp / "table.md").write_text("\n".join(lines) + "\n" + caption)
    buf = io.StringIO()
    header_csv = header[:-1] + [f"{m}_hw" for m in with_hw] + header[-1:]
    csv.writer(buf).writerows([header_csv, *([*r[:len(names) + 1], *map(_csv, r[len(names) + 1:-1]),
                                              *(_csv(h[metrics.index(m)]) for m in with_hw), r[-1]]
                                             for r, h in zip(rows, hws))])
    (tmp / "table.csv").write_text(buf.getvalue())
    summary_only = {
        "name": exp.name, "runs": doc["runs"], "window": list(exp.window), "axes": doc["axes"],
        "titles": doc["titles"], "wall_s": doc["wall_s"], "compile_s": doc["compile_s"],
        "level": doc["points"][0]["stats"].get("level"),
        "points": [{"values": p["values"], "filters": {l: {"kind": f["kind"], "summary": f["summary"]}
                                                        | ({"half_width": f["half_width"]} if "half_width" in f else {})
                                                        for l, f in p["stats"]["filters"].items()}}
                   for p in doc["points"]],
        "experiment": exp.raw,
    }
    write_json(tmp / "sweep.json", summary_only)
    if figures and len(names) <= 2:
        _plot(doc, names, labels, tmp)
    return rows


def runs_text(runs) -> str:
    """A sweep's runs per point: one number, or the range a runs axis spans."""
    return str(runs) if isinstance(runs, int) else f"{min(runs)}–{max(runs)}"


def _log_edges(values):
    """Cell edges for values on a log axis: geometric midpoints, the end cells as wide as their
    neighbours (a single value: a factor 2 either side)."""
    v = np.log(np.asarray(values, float))
    if len(v) == 1:
        return np.exp(v[0] + np.array([-np.log(2), np.log(2)]))
    mid = 0.5 * (v[1:] + v[:-1])
    return np.exp(np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]]))


def _edges(values, log):
    """Cell edges that put each cell's centre on its grid value (on a log axis: in log)."""
    if log:
        return _log_edges(values)
    v = np.asarray(values, float)
    if len(v) == 1:
        half = 0.5 * abs(v[0]) or 0.5
        return np.array([v[0] - half, v[0] + half])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def _value_axis(ax, vals, positive):
    """A curve's value axis: logarithmic when its values span a decade or more; otherwise linear,
    at least ±10 % about their middle, so that a change of a fraction of a percent reads as flat
    (on a log axis auto-scaled to the data it would fill the panel)."""
    if vals.size == 0:
        return
    lo, hi = float(np.min(vals)), float(np.max(vals))
    if positive and hi >= 10 * lo:
        ax.set_yscale("log")
        return
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    half = max(half * 1.1, 0.1 * abs(mid), 1e-12)
    ax.set_ylim(mid - half, mid + half)
    ax.ticklabel_format(axis="y", style="plain", useOffset=False)


def _plot(doc, names, labels, folder):
    """Per metric one figure, a panel per filter laid out in a grid (at most three across): 1-D
    sweeps as curves with each point's confidence interval, 2-D sweeps as heatmaps with each
    cell centred on its grid values. The NEES's consistent value (its degrees of freedom) is a
    line on the curves and a white contour on the heatmaps."""
    from tracklab.figures import pyplot

    plt = pyplot()

    axes_vals = [np.asarray(doc["axes"][n]) for n in names]
    titles, log = doc["titles"], doc["log"]
    dof = doc.get("nees_dof")
    for metric, title in doc["metrics"]:
        # None (no healthy run at a point) -> NaN -> masked: left blank
        values = {l: np.ma.masked_invalid(np.array([p["stats"]["filters"][l]["summary"].get(metric)
                                                    for p in doc["points"]], float)) for l in labels}
        half = {l: np.array([p["stats"]["filters"][l].get("half_width", {}).get(metric, np.nan)
                             for p in doc["points"]], float) for l in labels}
        if all(v.mask.all() for v in values.values()):
            continue  # nothing to draw (e.g. no NEES in this world)
        if any(np.ma.is_masked(v) for v in values.values()):
            title += " — blank: no run without divergence"
        positive = all(bool(np.all(v.compressed() > 0)) for v in values.values())
        mark = dof if metric == "nees" and dof else None
        cols = min(len(labels), 3)
        rows = -(-len(labels) // cols)
        fig, axs = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.8 * rows), squeeze=False, layout="constrained")
        for ax, l in zip(axs.flat, labels):
            vals = values[l]
            if len(names) == 1:
                ax.errorbar(axes_vals[0], vals, yerr=np.where(np.isfinite(half[l]), half[l], 0.0), fmt="o-", ms=4,
                            capsize=2)
                ax.set_xscale("log" if log[names[0]] else "linear")
                _value_axis(ax, np.concatenate([vals.compressed()] + ([[mark]] if mark else [])), positive)
                if mark:
                    ax.axhline(mark, color="k", lw=0.8, ls="--", label=f"consistent ({mark})")
                    ax.legend(fontsize=7, loc="best")
                ax.set_xlabel(titles[names[0]])
                ax.set_ylabel(title, fontsize=8)
                ax.grid(True, which="both", alpha=0.3)
            else:
                grid = vals.reshape(len(axes_vals[0]), len(axes_vals[1]))
                shown = np.ma.log10(grid) if positive else grid
                im = ax.pcolormesh(_edges(axes_vals[1], log[names[1]]), _edges(axes_vals[0], log[names[0]]), shown)
                if mark and len(axes_vals[0]) > 1 and len(axes_vals[1]) > 1:
                    level = np.log10(mark) if positive else mark
                    if np.nanmin(shown) < level < np.nanmax(shown):
                        ax.contour(axes_vals[1], axes_vals[0], shown, levels=[level], colors="w", linewidths=1.5)
                ax.set_xscale("log" if log[names[1]] else "linear")
                ax.set_yscale("log" if log[names[0]] else "linear")
                ax.set_xticks(axes_vals[1], [f"{v:g}" for v in axes_vals[1]], fontsize=7)
                ax.set_yticks(axes_vals[0], [f"{v:g}" for v in axes_vals[0]], fontsize=7)
                ax.minorticks_off()
                ax.set_xlabel(titles[names[1]], fontsize=8)
                ax.set_ylabel(titles[names[0]], fontsize=8)
                cb = fig.colorbar(im, ax=ax, label=f"log10 {metric}" if positive else metric)
                if mark:
                    cb.ax.axhline(np.log10(mark) if positive else mark, color="w", lw=1.5)
            ax.set_title(l, fontsize=9)
        for ax in list(axs.flat)[len(labels):]:
            ax.axis("off")
        if mark and len(names) == 2:
            title += f" — white line: consistent NEES = {mark}"
        fig.suptitle(title, fontsize=10)
        fig.savefig(folder / f"sweep_{metric}.png", dpi=110)
        plt.close(fig)
