"""A filter, scenario and sensor of one's own, from Python and from experiment files.

The bundled example (experiments/own_filter.py: a converted-measurement KF written with
jax.numpy on the state [x, y, ẋ, ẏ]) has the built-in CMKF's maths, so every statistic of
it must equal the built-in one's — from Python and through ``kind = "module:factory"``.
"""

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tracklab
from tracklab.report.document import read_results
from tracklab import FilterSpec, Out
from tracklab.cli import main
from tracklab.montecarlo.statistics import statistics

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ROOT / "experiments"
OWN_FILTER_PAGE = ROOT / "docs" / "own-filter.md"


def _example_module():
    spec = importlib.util.spec_from_file_location("own_filter_under_test", EXPERIMENTS / "own_filter.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def x_and_P_only(flt):
    """The same filter, reporting nothing but x and P."""

    def step(params, state, meas):
        state, out = flt.step(params, state, meas)
        return state, Out(out.x, out.P)

    return flt._replace(step=step)


@pytest.fixture(scope="module")
def compared():
    """The file's two filters (built-in CMKF, the factory's), the example from Python and an
    x/P-only copy of it: one experiment, one program, 300 runs."""
    base = tracklab.load_experiment(EXPERIMENTS / "own_filter.toml")
    own = _example_module().converted_kf(tracklab.filter_context(base.scenario, base.sensor))
    exp = tracklab.experiment(base.scenario, base.sensor,
                              base.filters + [FilterSpec("own, from Python", own), FilterSpec("x and P only", x_and_P_only(own))],
                              name="own_filter_test", runs=300, prior=base.prior, window=base.window)
    res = exp.monte_carlo()
    return exp, res, statistics(res, exp.window, exp.pred_windows)


def _close(a: dict, b: dict, rtol, keys=None):
    keys = keys or [k for k, v in a.items() if isinstance(v, float) and np.isfinite(v)]
    assert keys
    for k in keys:
        np.testing.assert_allclose(b[k], a[k], rtol=rtol, atol=1e-12 * max(1.0, abs(a[k])), err_msg=k)


def test_own_cmkf_equals_the_built_in_one_from_python_and_from_the_file(compared):
    exp, res, st = compared
    assert [f.kind for f in exp.filters[:2]] == ["cmkf", "own_filter:converted_kf"]
    ref = st["filters"]["CMKF"]
    for label in ("CMKF (own code)", "own, from Python"):
        _close(ref["summary"], st["filters"][label]["summary"], 1e-9)
        for name in ("rmse_pos", "rmse_vel", "nees", "nis", "pred_rmse_x"):
            np.testing.assert_allclose(st["filters"][label]["series"][name], ref["series"][name], rtol=1e-9,
                                       err_msg=f"{label}: {name}")
    # the comparison is not vacuous: the filter is good and consistent
    s = ref["summary"]
    assert 30 < s["rmse_pos"] < 40 and abs(s["nees"] - 4.0) < 0.3 and abs(s["nis"] - 2.0) < 0.1, s


def test_a_filter_giving_only_x_and_P_runs_with_empty_NIS_and_prediction_columns(compared, tmp_path):
    exp, res, st = compared
    mine, ref = st["filters"]["x and P only"]["summary"], st["filters"]["CMKF"]["summary"]
    _close(ref, mine, 1e-9, ["rmse_pos", "rmse_vel", "nees", "max_err_pos", "mean_err_x"])
    for k in ("nis", "nis_in_bounds", "pred_err_rms", "pred_err_max", "pred_err_rms_x"):
        assert not np.isfinite(mine[k]) and np.isfinite(ref[k]), k
    doc = exp.run(out=tmp_path / "out", figures=False)  # the same program: nothing compiles again
    stats = read_results(tmp_path / "out")
    assert stats["filters"]["x and P only"]["summary"]["nis"] is None
    assert stats["filters"]["own, from Python"]["params"] == {"accel_var": 1.0, "r": [1e4, 9e-6]}
    assert stats["filters"]["CMKF"]["params"]["q"] == 1.0
    row = next(r for r in (tmp_path / "out" / "table.md").read_text().splitlines() if r.startswith("| x and P only"))
    header = next(r for r in (tmp_path / "out" / "table.md").read_text().splitlines() if r.startswith("| filter"))
    cells = dict(zip([c.strip() for c in header.split("|")], [c.strip() for c in row.split("|")]))
    assert cells["NIS"] == "—" and cells["pred err RMS (m)"] == "—" and cells["RMSE pos (m)"] != "—"
    assert doc["filters"]["x and P only"]["kind"] == "user"


def test_recorded_data_give_the_statistics_of_the_simulation(compared, tmp_path):
    """run_filter over the simulated runs' measurements, judged against their truth by
    ``evaluate``, gives the simulation's statistics (the same code computes both)."""
    from tracklab.worlds.tracking.scan import simulate_runs

    exp, res, st = compared
    with jax.enable_x64(True):
        truth, z, prior = simulate_runs(exp.scenario, exp.sensor, jnp.asarray(exp.prior_covariance()),
                                        jax.random.key(exp.seed), jnp.arange(exp.runs, dtype=jnp.uint32))
    results = {}
    for spec in exp.filter_specs()[1:4:2]:  # the factory's filter and the x/P-only one
        layout = spec.report_layout(2)
        x0, P0 = layout.embed(prior, jnp.asarray(exp.prior_covariance()))
        results[spec.label] = tracklab.run_filter(spec.filter, z, x0=x0, P0=P0, dt=exp.dt)
    doc = tracklab.evaluate(results, np.asarray(truth)[:, 1:], dt=exp.dt, window=exp.window,
                            out=tmp_path / "flight", figures=False)
    assert (tmp_path / "flight" / "table.md").is_file()
    for label in results:
        want = st["filters"][label]["summary"]
        got = doc["filters"][label]["summary"]
        keys = [k for k, v in want.items() if isinstance(v, float) and np.isfinite(v) and "pcrlb" not in k]
        _close(want, got, 1e-9, keys)
        assert np.isfinite(got["nis"]) == (label != "x and P only")
    with pytest.raises(ValueError, match=r"run_filter: z has shape \(200,\)"):
        tracklab.run_filter(exp.filter_specs()[1].filter, np.zeros(200), x0=x0[0], P0=P0)
    with pytest.raises(ValueError, match=r"run_filter: z = a \(200, 3\) array: has m = 3 components per measurement, "
                                         r"the filter takes 2 "):
        tracklab.run_filter(exp.filter_specs()[1].filter, np.zeros((200, 3)), x0=x0[0], P0=P0)
    # one recording is one run
    one = tracklab.evaluate(tracklab.run_filter(exp.filter_specs()[1].filter, z[0], x0=x0[0], P0=P0),
                            np.asarray(truth)[0, 1:], dt=exp.dt)
    assert one["runs"] == 1 and np.isfinite(one["filters"]["filter"]["summary"]["rmse_pos"])


def test_tuning_a_parameter_of_ones_own_by_its_own_name(tmp_path):
    from tracklab.scenarios import Crossing
    from tracklab.sensors import Sensor

    scenario = Crossing(dt=0.5, steps=60, accel_sigma=1.0)
    sensor = Sensor("polar", 2, (100.0, 0.003))
    own = _example_module().converted_kf(tracklab.filter_context(scenario, [sensor]), accel_var=400.0)
    exp = tracklab.experiment(scenario, sensor, [FilterSpec("mine", own)], runs=500, prior={"vel_sigma": 50.0})
    for names, why in (({"mine": {"accel_vr": "positive"}}, "has no parameter 'accel_vr'"),
                       ({"mine": ["spare"]}, "declares no tunable 'spare'"),
                       ({"yours": {"accel_var": "positive"}}, "no filter labelled 'yours'"),
                       ({"mine": {"accel_var": "posit"}}, "constraint 'posit'"),
                       ({"mine": {"accel_var": (0.0, 10.0)}}, "outside its constraint (0, 10)")):
        with pytest.raises(ValueError, match=re.escape(why)) as e:
            tracklab.tune(exp, names, steps=1)
        assert "\n" not in str(e.value)
    r = tracklab.tune(exp, {"mine": {"accel_var": "positive"}}, steps=25, lr=0.3, runs_per_step=64, eval_runs=500)
    assert not r.stopped
    assert r.params["mine"]["accel_var"] < 100.0  # the truth's is 1 (m/s²)²
    assert r.eval_tuned["mine"] < 0.9 * r.eval_initial["mine"]


def test_a_parameter_the_loss_does_not_see_is_refused():
    from tracklab.scenarios import Crossing
    from tracklab.sensors import Sensor

    scenario = Crossing(dt=0.5, steps=20, accel_sigma=1.0)
    sensor = Sensor("polar", 2, (100.0, 0.003))
    own = _example_module().converted_kf(tracklab.filter_context(scenario, [sensor]))
    unused = own._replace(params={**own.params, "spare": jnp.asarray(3.0)})
    exp = tracklab.experiment(scenario, sensor, [FilterSpec("mine", unused)], runs=64)
    with pytest.raises(ValueError, match="does not depend on mine: spare"):
        tracklab.tune(exp, {"mine": {"spare": "positive"}}, steps=2, runs_per_step=16, eval_runs=16)


def test_import_leaves_jax_as_it_was(tmp_path, xla_flags):
    """``import tracklab`` sets no XLA flag, no device count, no 64-bit mode; the runner still
    computes in float64 (the same numbers as with ``configure()``)."""
    code = """
import json, os, sys
import jax
before = [os.environ.get("XLA_FLAGS"), jax.config.jax_enable_x64]
import tracklab
from tracklab.scenarios import ConstantVelocity
from tracklab.sensors import Sensor
after = [os.environ.get("XLA_FLAGS"), jax.config.jax_enable_x64]
devices = jax.device_count()
sc = ConstantVelocity(dt=1.0, steps=20, initial=(1.0e4, 30.0, 2.0e4, -10.0), accel_sigma=0.5)
exp = tracklab.experiment(sc, Sensor("cartesian", 2, (20.0, 20.0)), [{"kind": "kf"}], runs=64, chunk=64)
sums = exp.monte_carlo().sums["kf"]
print(json.dumps({"before": before, "after": after, "devices": devices, "mode": jax.config.jax_enable_x64,
                  "sumsq": sums["sumsq_pos"].tolist()}))
"""
    env = dict(os.environ, XLA_FLAGS=xla_flags())  # the suite's compile flags, no device count
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert doc["after"] == doc["before"] == [xla_flags(), False]
    assert doc["devices"] == 1 and doc["mode"] is False
    from tracklab.scenarios import ConstantVelocity
    from tracklab.sensors import Sensor

    sc = ConstantVelocity(dt=1.0, steps=20, initial=(1.0e4, 30.0, 2.0e4, -10.0), accel_sigma=0.5)
    exp = tracklab.experiment(sc, Sensor("cartesian", 2, (20.0, 20.0)), [{"kind": "kf"}], runs=64, chunk=64)
    np.testing.assert_allclose(doc["sumsq"], exp.monte_carlo().sums["kf"]["sumsq_pos"], rtol=1e-12)


def test_configure_sets_the_cpu_devices_and_keeps_given_flags():
    """A flag the user's XLA_FLAGS name is kept; one ``configure`` added gives way to a world's own
    compiler option (the airborne world's fusion emitters), one the user named does not, and one
    this XLA does not have is left out (not an error at compile time)."""
    code = """
import json, os
import tracklab
tracklab.configure()
import jax
from tracklab.montecarlo import runner
world = runner.World(None, None, 1, 1, (("xla_cpu_use_fusion_emitters", True), ("xla_force_host_platform_device_count", 7),
                                        ("xla_cpu_no_such_option", "")))
print(json.dumps([os.environ["XLA_FLAGS"], jax.device_count(), jax.config.jax_enable_x64,
                  runner.world_compiler_options(world)]))
"""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=3")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    flags, devices, x64, options = json.loads(out.stdout.strip().splitlines()[-1])
    assert devices == 3 and x64 is True
    assert "--xla_cpu_multi_thread_eigen=false" in flags and flags.count("device_count") == 1
    assert "--xla_cpu_use_fusion_emitters=false" in flags
    assert options == {"xla_cpu_use_fusion_emitters": True}


# ------------------------------------------------------------------- experiment files

BASE = """
[experiment]
name = "refusal"
runs = 2
dt = 0.5
steps = 10

[scenario]
{scenario}

[sensor]
{sensor}

[[filter]]
{filter}
"""
SCENARIO = 'kind = "crossing"'
SENSOR = 'kind = "polar"\nsigma_r = 100.0\nsigma_angle = 0.003'
FILTER = 'kind = "ekf"'

MODULE = """
import jax, jax.numpy as jnp, numpy as np
import tracklab
from tracklab import Filter, Out
from tracklab.sensors import CustomSensor

def ok_filter(context, **kw):
    def init(params, prior):
        return prior.x, prior.P
    def step(params, state, meas):
        return state, Out(*state)
    return Filter(init, step, {{}})

def wrong_shape(context):
    def init(params, prior):
        return prior.x, prior.P
    def step(params, state, meas):
        return state, Out(state[0][:2], state[1])
    return Filter(init, step, {{}})

def raises(context, gain=1.0):
    raise RuntimeError("no gain " + str(gain))

def not_a_filter(context):
    return {{"init": None}}

def takes_nothing():
    return None

def bad_truth(context):
    return lambda key: jnp.zeros((3, 4))

def not_a_sensor(context):
    return "radar"

def singular_sensor(context):
    return CustomSensor(lambda p: p, np.zeros((2, 2)), dim=2)

NOT_CALLABLE = 3
{extra}
"""


@pytest.mark.parametrize("case, table, module_extra, why", [
    ("no module", ("filter", 'kind = "no_such_module_xyz:f"'), "", "module 'no_such_module_xyz' is not found"),
    ("import fails", ("filter", 'kind = "{mod}:ok_filter"'), "raise ImportError('broken install')",
     "importing '{mod}' failed: ImportError: broken install"),
    ("no factory", ("filter", 'kind = "{mod}:missing"'), "", "has no 'missing'"),
    ("not callable", ("filter", 'kind = "{mod}:NOT_CALLABLE"'), "", "is a int, not a callable"),
    ("bad form", ("filter", 'kind = "{mod}:a:b"'), "", 'must be "package.module:factory"'),
    ("factory raises", ("filter", 'kind = "{mod}:raises"\ngain = 2.0'), "", "the factory raised RuntimeError: no gain 2.0"),
    ("import exits", ("filter", 'kind = "{mod}:ok_filter"'), "import sys\nsys.exit(0)",
     "filter[1].kind = '{mod}:ok_filter': importing '{mod}' failed: its import called sys.exit(0)"),
    ("import exits with a message", ("sensor", 'kind = "{mod}:singular_sensor"'), "raise SystemExit('bye')",
     "sensor.kind = '{mod}:singular_sensor': importing '{mod}' failed: its import called sys.exit('bye')"),
    ("import raises a BaseException", ("scenario", 'kind = "{mod}:bad_truth"'),
     "class Stop(BaseException):\n    pass\nraise Stop('halt')", "importing '{mod}' failed: Stop: halt"),
    ("factory exits", ("filter", 'kind = "{mod}:exits"'), "def exits(context):\n    import sys\n    sys.exit(0)",
     "filter[1].kind = '{mod}:exits': the factory called sys.exit(0)"),
    ("truth exits", ("scenario", 'kind = "{mod}:exiting_truth"'),
     "def exiting_truth(context):\n    import sys\n    return lambda key: sys.exit()",
     "the factory's truth(key) fails: it called sys.exit()"),
    ("wrong keyword", ("filter", 'kind = "{mod}:raises"\ngian = 2.0'), "", "unexpected keyword argument 'gian'"),
    ("not a filter", ("filter", 'kind = "{mod}:not_a_filter"'), "", "the factory returned dict"),
    ("no context", ("filter", 'kind = "{mod}:takes_nothing"'), "", "takes 0 positional arguments"),
    ("wrong shapes", ("filter", 'kind = "{mod}:wrong_shape"'), "", "gives x (2,) and P (4, 4)"),
    ("bad truth", ("scenario", 'kind = "{mod}:bad_truth"'), "", "gives (3, 4) float64: expected floats of shape (11, 4)"),
    ("not a sensor", ("sensor", 'kind = "{mod}:not_a_sensor"'), "", "the factory returned str"),
    ("singular R", ("sensor", 'kind = "{mod}:singular_sensor"'), "", "R must be positive definite"),
])
def test_every_factory_refusal_is_one_line_and_exit_2(tmp_path, capsys, case, table, module_extra, why):
    mod = "own_" + re.sub(r"\W", "_", case)  # a module name of its own per case (imports are cached)
    (tmp_path / f"{mod}.py").write_text(MODULE.format(extra=module_extra))
    parts = {"scenario": SCENARIO, "sensor": SENSOR, "filter": FILTER}
    section, text = table
    parts[section] = text.format(mod=mod)
    path = tmp_path / "exp.toml"
    path.write_text(BASE.format(**parts))
    code = main(["run", str(path), "--out", str(tmp_path / "out"), "--no-figures"])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert str(path) in err and why.format(mod=mod) in err, err
    assert not (tmp_path / "out").exists()


def test_a_truth_and_a_sensor_of_ones_own_from_a_file(tmp_path):
    """A scenario factory (a truth function of each run's key) and a sensor factory (h and a
    full R): the EKF built in sees the custom sensor with R's diagonal and stays consistent."""
    (tmp_path / "own_world.py").write_text('''
import jax, jax.numpy as jnp, numpy as np
from tracklab.sensors import CustomSensor

def weaving(context, speed=250.0, amplitude=300.0):
    t = context.dt * jnp.arange(context.steps + 1)
    def truth(key):  # a random phase per run
        phase = jax.random.uniform(key, (), minval=0.0, maxval=2 * jnp.pi)
        w = 2 * jnp.pi / 40.0
        x, vx = -5000.0 + speed * t, speed + 0 * t
        y, vy = 15000.0 + amplitude * jnp.sin(w * t + phase), amplitude * w * jnp.cos(w * t + phase)
        return jnp.stack([x, vx, y, vy], axis=-1)
    return truth

def range_bearing(context, sigma_r=50.0, sigma_b=0.002):
    h = lambda p: jnp.stack([jnp.hypot(p[0], p[1]), jnp.arctan2(p[1], p[0])])
    return CustomSensor(h, np.diag([sigma_r**2, sigma_b**2]), angles=(False, True), dim=context.dim)
''')
    path = tmp_path / "own_world.toml"
    path.write_text('''
[experiment]
name = "own_world"
runs = 400
dt = 0.5
steps = 120

[scenario]
kind = "own_world:weaving"
amplitude = 200.0

[sensor]
kind = "own_world:range_bearing"
name = "radar"
sigma_r = 40.0

[[filter]]
kind = "ekf"
accel_sigma = 8.0
''')
    exp = tracklab.load_experiment(path)
    assert exp.sensor.sensors[0].name == "radar" and exp.sensor.sensors[0].kind == "custom"
    assert exp.filters[0].params["r"] == pytest.approx((40.0**2, 0.002**2))
    st = statistics(exp.monte_carlo(), (20, 120))["filters"]["ekf"]["summary"]
    assert 1.8 < st["nis"] < 2.2, st  # the measurement noise the filter assumes is the sensor's
    assert 20 < st["rmse_pos"] < 60 and "rmse_pos_over_pcrlb" not in st, st  # no PCRLB for this truth


def test_a_custom_sensor_measures_as_the_built_in_one_it_copies():
    """CustomSensor(polar h, diag(σ²)) makes the built-in polar sensor's measurements: an EKF
    gives the same statistics on either."""
    from tracklab.scenarios import Crossing
    from tracklab.sensors import CustomSensor, Sensor, polar_h

    scenario = Crossing(dt=0.5, steps=80, accel_sigma=1.0)
    stats = []
    for sensor in (Sensor("polar", 2, (100.0, 0.003)),
                   CustomSensor(polar_h, np.diag([100.0**2, 0.003**2]), angles=(False, True), dim=2, name="polar")):
        exp = tracklab.experiment(scenario, sensor, [{"kind": "ekf"}, {"kind": "ukf"}], runs=200,
                                  prior={"vel_sigma": 50.0})
        res = exp.monte_carlo()
        stats.append(statistics(res, exp.window)["filters"])
        pcrlb = res.pcrlb
    for kind in ("ekf", "ukf"):  # the UKF evaluates h on all its sigma points at once
        _close(stats[0][kind]["summary"], stats[1][kind]["summary"], 1e-9)
    assert np.isfinite(pcrlb).all()
    with pytest.raises(ValueError, match="a polar sensor needs 2 noise standard deviations"):
        tracklab.experiment(scenario, Sensor("polar", 2, (100.0,)), [{"kind": "ekf"}])
    with pytest.raises(ValueError, match="R has shape"):
        tracklab.experiment(scenario, CustomSensor(polar_h, np.ones(2), dim=2), [{"kind": "ekf"}])


def test_the_documented_example_runs_as_written(tmp_path):
    code = re.findall(r"```python\n(.*?)```", OWN_FILTER_PAGE.read_text(), re.S)[0]
    # its filter is the bundled file's, word for word
    bundled = (EXPERIMENTS / "own_filter.py").read_text()
    assert bundled[bundled.index("def converted_kf"):].strip() in code
    (tmp_path / "experiments").symlink_to(EXPERIMENTS)
    (tmp_path / "example.py").write_text(code)
    out = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "| mine | user |" in out.stdout
    tuned = float(re.search(r"'accel_var': ([0-9.e+-]+)", out.stdout).group(1))
    before, after = map(float, re.search(r"held-out loss (\S+) -> (\S+) m²", out.stdout).groups())
    assert tuned < 25.0 and after < before
    assert (tmp_path / "my_results" / "own_filter" / "rmse.png").is_file()


MANOEUVRE = """
[experiment]
name = "manoeuvre"
runs = 300
dt = 1.0
steps = 100

[scenario]
kind = "manoeuvre"
initial = [-8000.0, 250.0, 12000.0, 0.0]
segments = {segments}

[sensor]
kind = "polar"
sigma_r = 30.0
sigma_angle = 0.002

[prior]
pos_sigma = 50.0
vel_sigma = 20.0

[[filter]]
kind = "ekf"
accel_sigma = 20.0
"""


def test_the_manoeuvre_scenario_and_its_bound(tmp_path):
    """Straight legs only: the bound of the deterministic path (its motion's Jacobians) equals
    the constant-velocity model's with no process noise. With a 4 g turn and a deceleration the
    filters stay above it at every step, and a bad segment is refused in one line."""
    from tracklab.scenarios import ConstantVelocity

    path = tmp_path / "straight.toml"
    path.write_text(MANOEUVRE.format(segments="[{duration = 40.0}]"))
    straight = tracklab.load_experiment(path)
    cv = tracklab.experiment(ConstantVelocity(dt=1.0, steps=100, initial=(-8000.0, 250.0, 12000.0, 0.0)),
                             straight.sensor, straight.filters, runs=300, prior=straight.prior)
    np.testing.assert_allclose(straight.monte_carlo(runs=20).pcrlb, cv.monte_carlo(runs=20).pcrlb, rtol=1e-9)

    path.write_text(MANOEUVRE.format(segments="[{duration = 30.0}, {duration = 25.0, turn_g = 4.0}, "
                                              "{duration = 10.0, accel = -8.0}]"))
    turning = tracklab.load_experiment(path)
    res = turning.monte_carlo()
    st = statistics(res, turning.window)["filters"]["ekf"]
    rmse = np.asarray(st["series"]["rmse_pos"])
    bound = np.sqrt(np.trace(res.pcrlb[:, 0::2, 0::2], axis1=1, axis2=2))
    assert np.all(np.isfinite(bound)) and np.all(rmse > 0.85 * bound)  # 300 runs: the sample RMSE is within ~10 %
    heading = np.degrees(np.arctan2(res.example["truth"][-1, 3], res.example["truth"][-1, 1]))
    speed = np.hypot(res.example["truth"][-1, 1], res.example["truth"][-1, 3])
    # 4 g for 25 s at 250 m/s: ω = 4 g / v, heading turned by 4·9.80665·25/250 rad
    turned = np.degrees(4 * 9.80665 * 25 / 250.0)  # 224.75°
    assert abs((heading - turned + 180.0) % 360.0 - 180.0) < 0.2, (heading, turned)
    np.testing.assert_allclose(speed, 250.0 - 80.0, rtol=1e-9)

    path.write_text(MANOEUVRE.format(segments="[{duration = 30.0, accel = -9.0}]"))
    assert main(["run", str(path), "--out", str(tmp_path / "o")]) == 2
    from tracklab.scenarios import Manoeuvre

    for segments, why in ((((10.0, 2.0),), r"expected \(duration_s > 0, turn_g, accel\)"),
                          (((30.0, 0.0, -9.0),), "brings the speed to zero")):
        with pytest.raises(ValueError, match=why):
            tracklab.experiment(Manoeuvre(dt=1.0, steps=50, initial=(0.0, 250.0, 1e4, 0.0), segments=segments),
                                straight.sensor, straight.filters)
