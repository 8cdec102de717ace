"""Every number of every bundled experiment file, swept through a two-point grid, means what it
says: the sweep refuses it in one line naming the axis, or each grid point is exactly the file
with that value — the same compiled structure, the same parameter set, the same runs, seed,
level, window and precision as a plain run of the edited file — and the two points differ in
something the run or its statistics use (a number that reaches nothing is refused, not shown
beside identical statistics). Sweep points run the world of their program's first point on
these inputs (``sweep``), so equal inputs mean equal statistics; tests/test_sweep.py and
tests/test_closed_loop_studies.py run points against plain runs in every world."""

import copy
from pathlib import Path

import jax
import numpy as np
import pytest

from tracklab.config import load_experiment, parse_experiment
from tracklab.config.paths import parse_grid, set_value
from tracklab.errors import ConfigError
from tracklab.studies.sweep import check_points, check_sweep, point

EXPERIMENTS = sorted((Path(__file__).parent.parent / "experiments").glob("*.toml"))
SAME = ("runs", "seed", "precision", "level", "window", "baseline", "steps", "chunk")  # a plain run's inputs


def _numbers(raw: dict):
    """(PATH, value) of every number in the file's tables and arrays of tables (by label)."""
    for section, v in raw.items():
        if isinstance(v, dict):
            entries = [(None, v)]
        elif isinstance(v, list) and v and all(isinstance(e, dict) for e in v):
            entries = [(str(e["label"]) if "label" in e else str(i + 1), e) for i, e in enumerate(v)]
        else:
            continue
        for label, table in entries:
            for field, x in table.items():
                if isinstance(x, (int, float)) and not isinstance(x, bool):
                    yield (f"{section}.{field}" if label is None else f"{section}[{label}].{field}"), x


def _pairs(x):
    """Two-point grids holding the file's value and a neighbour (the first the file accepts is swept)."""
    if isinstance(x, int):
        return [(x, x + 1), (x - 1, x), tuple(sorted((x, 2 * x))), (-abs(x), abs(x))]
    if x == 0:
        return [(0.0, 0.5), (-0.5, 0.0)]
    return [tuple(sorted((x, y))) for y in (x * 1.25, x * 0.8, x * 2, x / 2)] + [(-abs(x), abs(x))]


def _grid(path, lo, hi):
    return parse_grid(f"{path}={lo!r}:{hi!r}:2")


def _equal_trees(a, b) -> bool:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(np.shape(x) == np.shape(y) and np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
                            for x, y in zip(la, lb))


def _inputs(exp, params):
    return exp.structure(16, 16), params, tuple(getattr(exp, k) for k in SAME)


def _untrained(exp):
    """The file with every estimator trained before its run made an untrained one (train_steps = 0):
    what a sweep of its numbers asks for."""
    raw = copy.deepcopy(exp.raw)
    for table in raw.get("estimator", []):
        if table.get("train_steps"):
            table["train_steps"] = 0
    return parse_experiment(exp.path, raw)


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda p: p.stem)
def test_every_number_of_a_bundled_file_sweeps_honestly(path):
    exp = load_experiment(path)
    if exp.trained_first():
        axis = _grid("experiment.seed", 0, 1)
        with pytest.raises(ConfigError, match="trained before its run"):
            check_sweep(exp, [axis])
        exp = _untrained(exp)
    refused, problems = {}, []
    for name, x in _numbers(exp.raw):
        outcome = None
        for lo, hi in _pairs(x):
            axis = _grid(name, lo, hi)
            try:
                check_sweep(exp, [axis])
                made = [point(exp, [axis], (v,)) for v in axis.values]
                check_points(exp, [axis], [(v,) for v in axis.values], made)
            except ConfigError as e:
                assert "\n" not in str(e) and e.field == "--grid" and name.split("[")[0] in str(e.value), str(e)
                outcome = ("refused", str(e.allowed))  # the last grid's reason
                continue
            outcome = ("swept", axis, made)
            break
        if outcome[0] == "refused":
            refused[name] = outcome[1]
            continue
        _, axis, made = outcome
        inputs = []
        for v, (at, params) in zip(axis.values, made):
            raw = copy.deepcopy(exp.raw)
            set_value(raw, axis.path, v)
            plain = parse_experiment(path, raw)
            got, want = _inputs(at, params), _inputs(plain, plain.params())
            if got[0] != want[0] or not _equal_trees(got[1], want[1]) or got[2] != want[2]:
                problems.append(f"{name} = {v:g}: the grid point is not the file with that value")
            inputs.append(got)
        a, b = inputs
        if a[0] == b[0] and _equal_trees(a[1], b[1]) and a[2] == b[2]:
            problems.append(f"{name}: both grid points ({axis.values[0]:g}, {axis.values[1]:g}) run the same inputs")
    assert not problems, "\n".join(problems)
    # what may be refused: a study's own settings (no part of the run), and a number whose neighbours the
    # file's own rules refuse (the last step of a recorded flight, a step count its report window ends at)
    unexpected = {k: why for k, why in refused.items()
                  if not (k.startswith("study") or why.startswith("gives an invalid file") or
                          (".train_" in k and (why.startswith("no value of it") or "trains an estimator" in why)))}
    assert not unexpected, unexpected


def test_a_number_named_twice_is_refused_whichever_way_it_is_named():
    exp = load_experiment(Path(__file__).parent.parent / "experiments" / "lidar_real_flight.toml")
    with pytest.raises(ConfigError, match="each number may appear once"):
        check_sweep(exp, [_grid("filter[EKF].accel_sigma", 1, 2), _grid("filter[2].accel_sigma", 1, 2)])
    check_sweep(exp, [_grid("filter[EKF].accel_sigma", 1, 2), _grid("filter[1].accel_sigma", 1, 2)])
