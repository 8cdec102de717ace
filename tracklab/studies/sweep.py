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

Each grid point is the file with those values, validated as the file itself is, and run
as ``tracklab run`` runs it: its own runs, seed, level and precision (a runs axis is a
convergence study, a level axis recomputes the intervals at each level). Points whose
programs are alike are one compiled program: their parameter sets stacked along a leading
axis and run on the same runs (run i draws from ``fold_in(key, i)`` at every point), so
differences between points are the parameters', not the noise's. A value that changes the
program (a step count, a kind, a number a plug-in compiles in) runs one program per value;
points with different runs or seeds run on runs of their own. Refused in one line before
anything runs: a PATH that names no number, a [[study]] table's settings, a point that
trains an estimator first, and an axis none of whose values changes what runs or is
reported. Grid points and runs are processed in blocks so memory stays bounded.
"""

from __future__ import annotations

import copy
import itertools
import time

import jax
import numpy as np

from tracklab.config import parse_experiment
from tracklab.config.paths import Axis, set_value, table_of
from tracklab.scenarios import SCENARIOS
from tracklab.sensors import SENSORS
from tracklab.errors import ConfigError
from tracklab.memory import check
from tracklab.montecarlo import runner


def _table_of(exp, a: Axis, raw: dict) -> dict:
    """The table of ``raw`` (a copy of the file's) that a PATH axis's number lives in (the number
    may be absent: the file leaves it to its default); ConfigError in one line for a PATH that
    names no number of the file."""
    try:
        table = table_of(raw, a.path, create=True)
    except ValueError as e:
        raise ConfigError(exp.path, "--grid", a.name, str(e)) from None
    v = table.get(a.path[2])
    if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
        kind = type(v).__name__.replace("str", "a string").replace("list", "a list").replace("dict", "a table")
        raise ConfigError(exp.path, "--grid", a.name, f"is not a number in the file (it is {kind}): only numbers "
                          "can be swept")
    return table

def grid_points(axes: list[Axis]) -> int:
    return int(np.prod([len(a.values) for a in axes], dtype=float))

def _call_shape(exp, points, runs, chunk=None, block_points=None):
    """(runs, grid points) of one call: memory per call grows with grid points × runs × steps,
    kept near 10⁶ run-steps."""
    budget = 1_000_000
    steps = exp.samples_per_run
    chunk = int(min(chunk or exp.chunk or 1000, runs, max(1, budget // steps)))  # a sweep's own program
    return chunk, int(block_points or max(1, min(points, budget // (chunk * steps))))

def memory_bytes(exp, axes: list[Axis], runs=None) -> float:
    """A lower bound: every grid point's per-step statistics (kept until the sweep is written), and
    one call's runs."""
    P = grid_points(axes)
    chunk, block = _call_shape(exp, P, runs or exp.runs)
    return P * exp.statistics_bytes + block * chunk * exp.run_bytes


def check_sweep(exp, axes: list[Axis], runs=None, limit=None):
    """Refuse (ConfigError, one line) what a sweep cannot mean: an axis named twice, a scale factor
    of a parameter no filter has, a PATH that names no number, ``--runs`` beside an axis of the
    runs, an estimator trained before its run, or a grid too large to hold. Each grid point is
    checked as a file when the sweep reads it (``points``)."""
    names = [a.name for a in axes]
    if len(set(names)) != len(names):
        raise ConfigError(exp.path, "--grid", " ".join(names), "each parameter may appear once")
    raw, seen = copy.deepcopy(exp.raw), {}  # the number each PATH names: (its table, its field) -> the axis
    for a in axes:
        if a.path is None and not _scales(exp, a.name):
            raise ConfigError(exp.path, "--grid", a.name, f"no filter of this experiment declares a scalable "
                              f"parameter {a.name!r} (scalable here: {', '.join(exp.scalable()) or 'none'})")
        if a.path is not None and a.path[0] == "study":
            raise ConfigError(exp.path, "--grid", a.name, "a [[study]] table's numbers set how that study runs (tracklab "
                              "reproduce), not the experiment: sweep a number of the experiment's own tables")
        if a.path is not None:
            where = (id(_table_of(exp, a, raw)), a.path[2])
            if where in seen:  # by its label and by its index
                raise ConfigError(exp.path, "--grid", f"{seen[where]} {a.name}", "name the same number: each number "
                                  "may appear once")
            seen[where] = a.name
        if a.path == ("experiment", None, "runs") and runs is not None:
            raise ConfigError(exp.path, "--runs", runs, f"the grid sets each point's runs ({a.name}): give one of them")
    if exp.trained_first():
        raise ConfigError(exp.path, "--grid", " ".join(names), "an estimator trained before its run (train_steps > 0) "
                          "cannot be swept: set train_steps = 0, or sweep the trained weights through the Python API")
    check(exp.path, memory_bytes(exp, axes, runs), limit, f"a sweep of {grid_points(axes):.3g} grid points",
          "fewer grid points (N in NAME=LO:HI:N), or fewer experiment.steps")

def _scales(exp, name) -> bool:
    """Whether a scale-factor axis ``name`` scales something in this experiment."""
    return name in exp.scalable()


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

def _inputs(at, params) -> tuple:
    """What a grid point runs and reports with: equal for two points, equal statistics."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    numbers = tuple((np.shape(a), np.asarray(a).dtype.name, np.asarray(a).tobytes()) for a in leaves)
    return (at.structure(16, 16), treedef, numbers, at.runs, at.seed, at.precision, at.level, at.window, at.baseline,
            at.steps)


def check_points(exp, axes, values, made):
    """Refuse (ConfigError, one line) a grid whose point trains an estimator before its run, and an
    axis none of whose values changes what runs or is reported (its statistics would repeat
    under different labels)."""
    for (at, _), v in zip(made, values):
        if at.trained_first():
            what = ", ".join(f"{a.name} = {x:g}" for a, x in zip(axes, v))
            raise ConfigError(exp.path, "--grid", what, "trains an estimator before its run (train_steps > 0), which "
                              "a sweep cannot: sweep with train_steps = 0, or the trained weights through the Python API")
    inputs = [_inputs(at, params) for at, params in made]
    for i, a in enumerate(axes):
        if len(a.values) > 1 and not _changes(values, i, inputs):
            raise ConfigError(exp.path, "--grid", a.name, "no value of it changes what runs or what is reported, "
                              "given the file's other settings (e.g. a training setting of an estimator with "
                              "train_steps = 0): there is nothing to sweep")


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
    check_points(exp, axes, values, made)
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
    return {"axes": {a.name: a.values.tolist() for a in axes}, "titles": {a.name: _title(exp, a) for a in axes},
            "log": {a.name: a.log for a in axes}, "factors": [a.name for a in axes if a.path is None],
            "points": doc_points, "wall_s": wall, "compile_s": compile_s,
            "runs": each[0] if len(each) == 1 else each, "programs": len(programs), "structural": structural,
            "separate": separate,
            "units": list(exp.units), "nees_dof": exp.nees_dof,
            "metrics": [[k, t.format(pos=exp.units[0])] for k, t in exp.sweep_metrics]}

def _title(exp, a: Axis) -> str:
    """An axis in a figure: its field and unit — a declared number's from its declaration (a unit's,
    a sensor's or a scenario's), another's from the fields' table (``paths.UNITS``)."""
    if a.path is None:
        return a.title
    section, label, name = a.path
    kind = _kind_of(exp.raw.get(section), label)
    declared = (SENSORS.get(kind) if section == "sensor" else SCENARIOS.get(kind) if section == "scenario" else None)
    if declared is not None and name in declared.params:
        unit = declared.params[name].unit
        return f"{a.name} ({unit})" if unit else a.name
    if label is None:
        return a.title
    table, labels = exp.tables()
    if section == table:
        if label not in labels and label.isdigit() and 1 <= int(label) <= len(labels):
            label = labels[int(label) - 1]
        p = exp.declared().get(label, {}).get(name)
        if p is not None:
            return f"{a.name} ({p.unit})" if p.unit else a.name
    return a.title


def _kind_of(tables, label) -> str | None:
    """The kind of the table a PATH names (a section's table, or the entry of an array picked by label)."""
    try:
        t = table_of({"x": tables}, ("x", label, "")) if tables is not None else None
    except ValueError:
        return None
    return t.get("kind") if isinstance(t, dict) else None


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
