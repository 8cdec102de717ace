"""A tuned experiment file is the user's own file with only the tuned numbers changed.

For every bundled experiment, and for files that together with them use every scenario,
sensor, filter, tracker and estimator kind and kinds of one's own (a filter, a truth and a
sensor from a module found through ``pythonpath``), tuned values of every parameter a file
can hold are written back into a copy in another folder. The copy must keep every comment
of the original, parse to the same experiment except for the tuned numbers (and the names
that say it is tuned), reach the same trajectory and modules from its own folder, and run.
"""

import dataclasses
import os
import re
import shutil
import tomllib
from pathlib import Path

import jax
import numpy as np
import pytest

import tracklab
from tracklab.cli import main
from tracklab.config import load_experiment
from tracklab.config.writeback import tuned_text
from tracklab.filters.registry import KINDS
from tracklab.output import TUNED_HEADER
from tracklab.studies.tune import decode, encode, unwritable
from tracklab.worlds.tracking.experiment import Experiment
from tracklab.worlds.tracking.lanes import FilterSpec

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = sorted((ROOT / "experiments").glob("*.toml"))

PLUGINS = '''
import jax
import jax.numpy as jnp
import numpy as np

from tracklab.scenarios import ConstantVelocity
from tracklab.sensors import CustomSensor


def truth(context, speed=200.0):
    """A constant-velocity pass drawn afresh in every run (its heading is random)."""
    def draw(key):
        a = jax.random.uniform(key, (), minval=0.0, maxval=2 * jnp.pi)
        k = jnp.arange(context.steps + 1) * context.dt
        x, y = 5000.0 + speed * jnp.cos(a) * k, 3000.0 + speed * jnp.sin(a) * k
        return jnp.stack([x, jnp.full_like(k, speed * jnp.cos(a)), y, jnp.full_like(k, speed * jnp.sin(a))], -1)
    return draw


def radar(context, sigma_r=20.0, sigma_b=0.002):
    """Range and bearing with a full noise covariance."""
    h = lambda p: jnp.stack([jnp.hypot(p[0], p[1]), jnp.arctan2(p[1], p[0])])
    return CustomSensor(h, np.array([[sigma_r**2, 0.0], [0.0, sigma_b**2]]), angles=(False, True), dim=2)
'''

EXTRA = {
    # a manoeuvre with turns beside a filter of one's own imported through pythonpath (inline tables)
    "manoeuvre_own_filter.toml": '''
# a 5 g turn between straight legs, tracked by an EKF and a converted-measurement KF of one's own
[experiment]
name = "manoeuvre_own_filter"   # the results folder
runs = 4
dt = 1.0
steps = 60
pythonpath = ["plugins"]        # own_filter.py lives there

[scenario]
kind = "manoeuvre"
initial = [-8000.0, 250.0, 12000.0, 0.0]
segments = [{duration = 20.0}, {duration = 15.0, turn_g = 5.0}, {duration = 10.0, accel = -8.0}]

[sensor]
kind = "polar"
sigma_r = 30.0
sigma_angle = 0.002

[[filter]]
kind = "ekf"
label = "EKF"
accel_sigma = 20.0              # m/s^2: room for the turn

[[filter]]
kind = "own_filter:converted_kf"
label = "mine"
accel_var = 400.0               # (m/s^2)^2

[report]
baseline = "EKF"
''',
    # the same manoeuvre written with arrays of tables inside a table (the form a hand-written
    # writer loses), and the 1-D sine with the CA KF, the DEKF and the alpha-beta-gamma filter
    "sine_kinds.toml": '''
[experiment]
name = "sine_kinds"
runs = 4
dt = 0.01
steps = 400

[scenario]
kind = "sine"
amplitude = 83.33   # deg
omega = 0.6

[sensor]
kind = "cartesian"
sigma = 0.0028

[prior]
pos_sigma = 0.01
vel_sigma = 1.0
acc_sigma = 1.0

[[filter]]
kind = "kf"
label = "KF"
model = "ca"
q = 1.0

[[filter]]
kind = "dekf"
label = "DEKF"
q = 1.0
forget = 0.999
scale = [80.0, 50.0, 30.0]

[[filter]]
kind = "alpha_beta_gamma"
label = "abg"
gains = "explicit"
alpha = 0.5
beta = 0.2
gamma = 0.02

[[study]]
kind = "sweep"
grid = ["q=0.1:10:3"]
runs = 4
out = "mismatch/sine"
''',
    "nested_manoeuvre.toml": '''
[experiment]
name = "nested_manoeuvre"
runs = 4
dt = 1.0
steps = 50

[scenario]
kind = "manoeuvre"
initial = [-8000.0, 250.0, 12000.0, 0.0]

  [[scenario.segments]]   # straight
  duration = 20.0

  [[scenario.segments]]   # a 4 g turn left
  duration = 15.0
  turn_g = 4.0

[sensor]
kind = "polar"
sigma_r = 30.0
sigma_angle = 0.002

[[filter]]
kind = "ukf"
label = "UKF"
sigma_r = 30.0       # the truth's

[[filter]]
kind = "cmkf"
label = "CMKF "
''',
    # a truth and a sensor of one's own
    "own_truth_and_sensor.toml": '''
[experiment]
name = "own_truth_and_sensor"
runs = 4
dt = 1.0
steps = 30
pythonpath = ["plugins"]

[scenario]
kind = "mine:truth"
speed = 150.0

[sensor]
kind = "mine:radar"
sigma_r = 25.0

[[filter]]
kind = "ekf"
label = "EKF"
r = [625.0, 4e-6]
''',
}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The bundled experiment files and the extra ones (in a folder with their modules)."""
    folder = tmp_path_factory.mktemp("own")
    plugins = folder / "plugins"
    plugins.mkdir()
    shutil.copy(ROOT / "experiments" / "own_filter.py", plugins)
    (plugins / "mine.py").write_text(PLUGINS)
    extra = []
    for name, text in EXTRA.items():
        (folder / name).write_text(text.lstrip())
        extra.append(folder / name)
    return BUNDLED + extra


def tuned_values(exp) -> dict:
    """A tuned value, inside its constraint and away from the file's, for every declared number of
    every unit (filter, tracker, estimator) that a file can hold: {label: {name: value}}."""
    declared, values = exp.declared(), exp.values(exp.params())
    out = {}
    for label, d in declared.items():
        names = [n for n, p in d.items() if p.tune and p.write is not None
                 and unwritable(exp, {label: {n: p.constraint}}) is None]  # r of several sensors: no field for it
        if names:
            theta = jax.tree_util.tree_map(lambda u: u + 0.3, encode({n: d[n].constraint for n in names}, values[label]))
            out[label] = {n: np.asarray(v) for n, v in decode({n: d[n].constraint for n in names}, theta).items()}
    return out


def relabelled(structure, renamed):
    """A world's structure with its lanes' labels renamed (its first field: the lanes)."""
    lanes = dataclasses.fields(structure)[0].name
    items = tuple(dataclasses.replace(x, label=renamed.get(x.label, x.label)) if dataclasses.is_dataclass(x)
                  else x for x in getattr(structure, lanes))
    return dataclasses.replace(structure, **{lanes: items})


def expected_params(exp, values):
    """The original's params with the tuned numbers put in."""
    return exp.with_values(exp.params(), values)


def comments(text) -> list[tuple]:
    """(table, key, comment) of each comment of a TOML text outside its [[study]] tables (which a
    tuned file leaves out): the table as (dotted name, which of its array entries), the key the
    comment's line assigns (None for a comment line or a header)."""
    out, table, seen = [], ((), 0), {}
    for line in text.splitlines():
        head = line.split("#", 1)[0].strip()
        if head.startswith("["):
            name = tuple(head.strip("[]").strip().split("."))
            seen[name] = seen.get(name, -1) + 1
            table = (name, seen[name])
        if "#" in line and table[0] != ("study",):
            key = head.split("=", 1)[0].strip() if "=" in head else None
            out.append((table, key, line[line.index("#"):].strip()))
    return out


def has_key(raw, table, key) -> bool:
    """Whether a parsed file's ``table`` (as ``comments`` names it) still has ``key``."""
    (name, index), t = table, raw
    for part in name:
        t = t.get(part.strip('"'), {})
    if isinstance(t, list):
        t = t[index] if index < len(t) else {}
    return key in t


def test_a_tuned_file_is_the_file_with_only_the_tuned_numbers_changed(files, tmp_path):
    kinds = {"scenario": set(), "sensor": set(), "filter": set(), "tracker": set(), "estimator": set()}
    for path in files:
        exp = load_experiment(path)
        raw = tomllib.loads(path.read_text())
        for section, seen in kinds.items():
            tables = raw.get(section, [])
            seen.update(t["kind"] for t in (tables if isinstance(tables, list) else [tables]))
        values = tuned_values(exp)
        out = tmp_path / "elsewhere" / f"{path.stem}_tuned.toml"  # another folder: paths must follow
        out.parent.mkdir(exist_ok=True)
        text = tuned_text(exp, values, out)
        out.write_text(text)
        assert text.startswith(TUNED_HEADER + "\n")

        # every comment is kept, but that of a field the tuned value replaces (a tuned tracking index
        # in the place of the sigma_w it was computed from: the comment described that field)
        now = tomllib.loads(text)
        lost = [c for t, k, c in comments(path.read_text()) if c not in text and (k is None or has_key(now, t, k))]
        assert not lost, f"{path.name}: comments lost: {lost}"
        tuned = load_experiment(out)
        assert tuned.name == f"{exp.name}_tuned" and not getattr(tuned, "studies", [])
        renamed = {l: f"{l}, tuned" for l in values} if exp.relabel_tuned else {}
        assert tuned.baseline == renamed.get(exp.baseline, exp.baseline)
        # the same experiment: what it is compiled for, and every number, but the tuned ones
        a, b = tuned.structure(), relabelled(exp.structure(), renamed)
        if isinstance(exp, Experiment):  # the same filter of one's own, traced anew: its code
            a = dataclasses.replace(a, filters=tuple((f.label, f.kind, f.sensors) if isinstance(f, FilterSpec) else f
                                                     for f in a.filters))
            b = dataclasses.replace(b, filters=tuple((f.label, f.kind, f.sensors) if isinstance(f, FilterSpec) else f
                                                     for f in b.filters))
        assert a == b, path.name
        got, want = tuned.params(), expected_params(exp, values)
        shape = lambda t: re.sub(r" at 0x[0-9a-f]+", "", str(jax.tree_util.tree_structure(t)))  # a module's
        assert shape(got) == shape(want), path.name  # functions are new objects in every parse
        for (where, x), y in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree_util.tree_leaves(want)):
            np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), rtol=1e-12, atol=0,
                                       err_msg=f"{path.name}: {jax.tree_util.keystr(where)}")
        if values:  # and not vacuously: the tuned numbers moved
            assert any(not np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
                       zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(exp.params()))), path.name
    from tracklab.worlds.airborne.registry import TRACKERS
    from tracklab.worlds.servo.registry import ESTIMATORS
    from tracklab.scenarios import SCENARIOS
    from tracklab.sensors import SENSORS

    own = {k for seen in kinds.values() for k in seen if ":" in k}
    assert kinds["scenario"] >= set(SCENARIOS) and kinds["sensor"] >= set(SENSORS)
    assert kinds["filter"] >= set(KINDS) and kinds["tracker"] >= set(TRACKERS) and kinds["estimator"] >= set(ESTIMATORS)
    assert {"own_filter:converted_kf", "mine:truth", "mine:radar"} <= own


def test_the_tuned_manoeuvre_with_a_filter_of_ones_own_runs_from_another_folder(files, tmp_path):
    """Written under results/ (not beside its module), the tuned copy finds the module and keeps the
    turn: its EKF's error peaks in the turn as the original's does, on the same runs."""
    path = next(f for f in files if f.name == "manoeuvre_own_filter.toml")
    exp = load_experiment(path)
    out = tmp_path / "results" / "manoeuvre_own_filter_tuned.toml"
    out.parent.mkdir()
    out.write_text(tuned_text(exp, {"EKF": {"q": 100.0}, "mine": {"accel_var": 100.0}}, out))
    text = out.read_text()
    here = os.path.relpath(path.parent, out.parent)
    assert 'turn_g = 5.0' in text and f'pythonpath = ["{here}", "{here}/plugins"]' in text, text
    assert re.search(r"^accel_sigma = 10\.0 +# m/s\^2: room for the turn$", text, re.M), text
    assert main(["run", str(out), "--runs", "4", "--no-figures", "--out", str(tmp_path / "tuned")]) == 0
    stats = tracklab.load_experiment(out)
    assert stats.scenario.segments == exp.scenario.segments and [f.label for f in stats.filters] == ["EKF, tuned", "mine, tuned"]


def test_a_manoeuvre_without_segments_and_labels_equal_once_trimmed_are_refused(files, tmp_path, capsys):
    text = EXTRA["manoeuvre_own_filter.toml"]
    path = next(f for f in files if f.name == "manoeuvre_own_filter.toml").with_name("bad.toml")  # beside plugins/
    for bad, field in ((re.sub(r"^segments = .*$", "", text, flags=re.M), "scenario.segments"),
                       (text.replace("segments = [", "segments = [] #"), "scenario.segments"),
                       (text.replace('label = "mine"', 'label = "EKF "'), "filter[2].label")):
        path.write_text(bad)
        assert main(["run", str(path), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and field in err[0], err
