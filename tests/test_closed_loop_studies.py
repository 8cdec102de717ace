"""tune and sweep on the closed-loop worlds (airborne radar, servo), and sweeps over any number
of a file: a sweep point equals a run of its own with that value."""

import numpy as np
import pytest

from tracklab.config import load_experiment, parse_experiment
from tracklab.config.paths import parse_grid
from tracklab.studies.sweep import sweep

AIRBORNE = """
[experiment]
name = "airborne_tiny"
runs = 4
seed = 1
chunk = 4

[airborne]
duration = 1.0

[[tracker]]
label = "joint"
kind = "cd_ekf"
"""

SERVO = """
[experiment]
name = "servo_tiny"
runs = 4
seed = 2
chunk = 4

[servo]
frames = 300
settle = 1.0

[target]
kind = "sine"

[[estimator]]
label = "KF"
kind = "kf"
q = 0.01

[[case]]
mode = "on_axis"
estimator = "KF"
"""

TRACKING = """
[experiment]
name = "tracking_tiny"
runs = 16
dt = 0.5
steps = 30
chunk = 16

[scenario]
kind = "crossing"
speed = 200.0
offset = 3000.0
start_x = -3000.0

[sensor]
kind = "polar"
sigma_r = 50.0
sigma_angle = 0.004

[[filter]]
kind = "ekf"
label = "EKF"
"""


def _load(tmp_path, name, text):
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return load_experiment(path)


def _alone(exp, *settings):
    """The experiment with numbers set ((path, value) pairs), run on its own: its statistics document."""
    import copy

    from tracklab.config.paths import set_value as _set

    raw = copy.deepcopy(exp.raw)
    for path, value in settings:
        _set(raw, path, value)
    return parse_experiment(exp.path, raw).simulate()  # every world's run, as `tracklab run` makes it


def _agree(a, b, what):
    for k, v in b.items():
        if isinstance(v, (int, float)) and v is not None and k in a:
            np.testing.assert_allclose(a[k], v, rtol=1e-9, atol=1e-12, err_msg=f"{what}: {k}")


@pytest.mark.parametrize("world, grid, label", [
    ("tracking", "sensor.sigma_r=20:180:3", "EKF"),
    ("airborne", "engagement.target_speed=200:400:2", "joint"),
    ("servo", "servo.noise=5:20:2", "on_axis, KF"),
])
def test_a_sweep_point_equals_a_run_with_that_value(tmp_path, world, grid, label):
    text = {"tracking": TRACKING, "airborne": AIRBORNE, "servo": SERVO}[world]
    exp = _load(tmp_path, world, text)
    axis = parse_grid(grid)
    doc = sweep(exp, [axis], chunk=exp.chunk)
    assert [p["values"][axis.name] for p in doc["points"]] == list(axis.values)
    summaries = [p["stats"]["filters"][label]["summary"] for p in doc["points"]]
    assert summaries[0] != summaries[-1]  # the number reached the program
    for value, s in zip(axis.values, summaries):  # every grid value (each separate run reuses one program)
        _agree(s, _alone(exp, (axis.path, value))["filters"][label]["summary"], f"{grid} at {value}")


def test_airborne_q_r_mismatch_grid_in_one_sweep(tmp_path):
    """Paper 001's Q/R mismatch study as one call: scale factors on the joint EKF's Q and R."""
    exp = _load(tmp_path, "airborne", AIRBORNE)
    doc = sweep(exp, [parse_grid("q=0.1:10:2"), parse_grid("r=0.1:10:2")], chunk=4)
    assert len(doc["points"]) == 4
    nees = [p["stats"]["filters"]["joint"]["summary"]["nees"] for p in doc["points"]]
    assert len(set(nees)) == 4
    # the same as the file with q_scale / r_scale set (points: q major, r minor)
    assert doc["points"][2]["values"] == {"q": 10.0, "r": 0.1}
    alone = _alone(exp, (("tracker", "joint", "q_scale"), 10.0), (("tracker", "joint", "r_scale"), 0.1))
    _agree(doc["points"][2]["stats"]["filters"]["joint"]["summary"], alone["filters"]["joint"]["summary"], "q x10")


@pytest.mark.parametrize("world, params, loss", [("airborne", "q_scale,lam", "pointing"), ("servo", "q", "track_mse")])
def test_tune_runs_on_a_closed_loop_and_writes_a_file_run_accepts(tmp_path, world, params, loss):
    from tracklab.studies.files import check_tune, run_tune

    exp = _load(tmp_path, world, {"airborne": AIRBORNE, "servo": SERVO}[world])
    names = params.split(",")
    out = tmp_path / f"{world}_tuned.toml"
    check_tune(exp, names, None, out, 4, folder=tmp_path / "report")
    lines = []
    res = run_tune(exp, names, steps=2, lr=0.1, loss=loss, runs_per_step=4, labels=None, out_toml=out,
                   folder=tmp_path / "report", log=lines.append, eval_runs=4)
    assert not res.stopped and len(res.history) == 2
    # a gradient flows through the closed loop; each tuned lane has its own loss
    assert all(all(np.isfinite(v) for v in per.values()) and g > 0 for _, per, g in res.history)
    assert set(res.eval_tuned) == set(res.history[0][1]) and (tmp_path / "report" / "tune.json").exists()
    tuned = load_experiment(out)
    start = {n: float(v) for n, v in next(iter(res.initial.values())).items()}
    got = {n: float(v) for n, v in next(iter(res.params.values())).items()}
    assert got != start
    table = (tuned.raw["tracker"] if world == "airborne" else tuned.raw["estimator"])[0]
    for n, v in got.items():
        assert table[n] == pytest.approx(v)


def test_sweep_and_tune_refuse_in_one_line(tmp_path, capsys):
    """The new grid syntax's refusals: one line naming the file, exit 2."""
    from tracklab.cli import main

    path = tmp_path / "t.toml"
    path.write_text(TRACKING)
    cases = {
        "nosuch.sigma_r=1:2:2": "unknown section",
        "filter[KF].accel_sigma=1:2:2": "no [[filter]] entry is labelled 'KF'",
        "filter[EKF].kind=1:2:2": "not a number",
        "sensor.sigma_r=1:2:0": "N must be in",
        "sensor.sigma_r=5:1:3:log": "a log grid needs 0 < LO <= HI",
        "sensor.sigma_r=5:1:3": "needs LO <= HI",
        "sensor.sigma_r=-5:1:3": "sensor.sigma_r",  # an invalid file at a grid end
        "sensor.sigma_r=1:2:x": "N must be a whole number",
        "sensor.sigma_r=1:2:3:cubic": "spacing",
        "sensor..x=1:2:2": "PATH must be",
    }
    for grid, why in cases.items():
        code = main(["sweep", str(path), "--grid", grid, "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2, grid
        assert len(err) == 1 and why in err[0] and str(path) in err[0], (grid, err)
    assert not (tmp_path / "out").exists()
