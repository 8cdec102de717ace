"""Monte-Carlo engine: consistency, bounds, chunking, devices, divergence."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.config import load_experiment
from tracklab.worlds.tracking.lanes import FilterSpec
from tracklab.worlds.tracking.outcome import monte_carlo
from tracklab.filters import Filter, build, noise_params
from tracklab.montecarlo.statistics import average_chi2_interval, chi2_quantile, statistics
from tracklab.models import cv

LINEAR = """
[experiment]
name = "linear"
runs = 10000
dt = 1.0
steps = 100

[scenario]
kind = "crossing"
speed = 100.0
offset = 2000.0
start_x = -5000.0
accel_sigma = 2.0

[sensor]
kind = "cartesian"
sigma = [30.0, 60.0]

[prior]
pos_sigma = 50.0
vel_sigma = 10.0

[[filter]]
kind = "kf"
label = "KF"
accel_sigma = 2.0

[[filter]]
kind = "ekf"
label = "EKF"
accel_sigma = 2.0

[report]
window = [1, 100]
"""

POLAR = """
[experiment]
name = "polar"
runs = 301
dt = 0.5
steps = 40

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003
p_detect = 0.9

[[filter]]
kind = "ekf"

[[filter]]
kind = "sequential_ekf"
"""


def write(tmp_path, text, name="exp.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def test_chi2_quantiles():
    # known values: chi2(1) 97.5 % = 5.0239, chi2(4) 2.5 % = 0.4844, chi2(100) 95 % = 124.342
    np.testing.assert_allclose(chi2_quantile(0.975, 1), 5.023886, rtol=1e-5)
    np.testing.assert_allclose(chi2_quantile(0.025, 4), 0.484419, rtol=1e-5)
    np.testing.assert_allclose(chi2_quantile(0.95, 100), 124.3421, rtol=1e-5)
    lo, hi = average_chi2_interval(4, 10000)
    assert lo < 4 < hi and hi - lo < 0.25
    # a series with repeated (p, dof) pairs: each element as if asked alone
    p = np.array([0.025, 0.975, 0.025, 0.5, 0.975])
    dof = np.array([4.0, 1.0, 4.0, 7.0, 1.0])
    np.testing.assert_allclose(chi2_quantile(p, dof), [chi2_quantile(a, b) for a, b in zip(p, dof)], rtol=1e-12)
    np.testing.assert_allclose(chi2_quantile(0.5, 7.0), 6.345811, rtol=1e-5)


def test_linear_gaussian_nees_and_pcrlb(tmp_path):
    """True model and noise: NEES inside its 95 % band and RMSE at the PCRLB."""
    exp = load_experiment(write(tmp_path, LINEAR))
    res = exp.monte_carlo()
    st = statistics(res, exp.window)
    bound = st["bounds"]["pcrlb_pos"]
    for label in ("KF", "EKF"):
        f = st["filters"][label]
        s, ser = f["summary"], f["series"]
        assert s["diverged"] == 0
        assert s["nees_in_bounds"] >= 0.85, s
        assert abs(s["nees"] - 4.0) < 0.1, s
        assert abs(s["nis"] - 2.0) < 0.05, s
        assert abs(s["rmse_pos_over_pcrlb"] - 1.0) < 0.02, s
        ratio = ser["rmse_pos"] / bound
        assert np.all(np.abs(ratio - 1.0) < 0.05), ratio
    # the linear KF and the EKF of a linear model are the same filter
    np.testing.assert_allclose(st["filters"]["KF"]["series"]["rmse_pos"], st["filters"]["EKF"]["series"]["rmse_pos"], rtol=1e-9)


def test_wrong_noise_leaves_the_nees_band(tmp_path):
    """The NEES test is not vacuous: a filter that assumes 10x too little noise fails it."""
    text = LINEAR.replace("runs = 10000", "runs = 500").replace('label = "EKF"\naccel_sigma = 2.0', 'label = "EKF"\naccel_sigma = 2.0\nsigma = 5.0')
    exp = load_experiment(write(tmp_path, text))
    st = statistics(exp.monte_carlo(), exp.window)
    assert st["filters"]["KF"]["summary"]["nees_in_bounds"] > 0.8
    assert st["filters"]["EKF"]["summary"]["nees_in_bounds"] < 0.05
    assert st["filters"]["EKF"]["summary"]["nees"] > 20


def _flat(res):
    return {f"{lab}/{k}": np.asarray(v) for lab, d in res.sums.items() for k, v in d.items()}


def test_chunking_does_not_change_statistics(tmp_path):
    exp = load_experiment(write(tmp_path, POLAR))
    ref = _flat(exp.monte_carlo(chunk=301))
    for chunk in (64, 100):
        got = _flat(exp.monte_carlo(chunk=chunk))
        for k in ref:  # equal up to the order of floating-point sums (and FMA contraction)
            np.testing.assert_allclose(got[k], ref[k], rtol=1e-12, atol=1e-9, err_msg=k)


DEVICE_SCRIPT = """
import json, sys
import tracklab
tracklab.configure()  # as the command does (the device count from XLA_FLAGS)
import jax, numpy as np
from tracklab.config import load_experiment
exp = load_experiment(sys.argv[1])
res = exp.monte_carlo(chunk=int(sys.argv[2]))
print(json.dumps({"devices": jax.device_count(),
                  "sums": {f"{l}/{k}": np.asarray(v).tolist() for l, d in res.sums.items() for k, v in d.items()}}))
"""


def test_statistics_do_not_depend_on_device_count(tmp_path, xla_flags):
    """Runs split over 4 (forced host) devices give the statistics of one device: 301 runs in one
    chunk, padded with dead runs to fill the 4. Two devices, every world:
    test_runner.test_statistics_do_not_depend_on_the_device_count; one device at other chunk
    sizes: test_chunking_does_not_change_statistics."""
    path = write(tmp_path, POLAR)
    script = tmp_path / "dev.py"
    script.write_text(DEVICE_SCRIPT)
    ref = _flat(load_experiment(path).monte_carlo(chunk=301))
    assert jax.device_count() == 1
    env = dict(os.environ, XLA_FLAGS=xla_flags(4))
    out = subprocess.run([sys.executable, str(script), str(path), "301"], env=env, capture_output=True, text=True,
                         check=True)
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert doc["devices"] == 4
    for k, v in doc["sums"].items():
        np.testing.assert_allclose(np.asarray(v, float), ref[k], rtol=1e-12, atol=1e-9, err_msg=k)


def test_diverging_runs_are_counted_and_excluded():
    """A filter that blows up in some runs: counted, excluded, the batch survives."""
    dt, steps = 1.0, 30
    from tracklab.scenarios import Crossing
    from tracklab.sensors import Sensor

    sc = Crossing(dt=dt, steps=steps, speed=100.0, offset=1000.0, start_x=-2000.0, accel_sigma=1.0)
    sensor = Sensor("cartesian", 2, (10.0, 10.0))
    m = cv(2, dt)
    good = build("kf", m, sensor, noise_params(1.0, np.array([100.0, 100.0])))

    def step(p, s, meas):  # NaN state once a measurement lands far in the tail
        s, out = good.step(p, s, meas)
        boom = jnp.abs(meas.z[0] - out.x_pred[0]) > 28.0
        s = jax.tree_util.tree_map(lambda a: jnp.where(boom, jnp.nan, a), s)
        return s, out._replace(x=jnp.where(boom, jnp.nan, out.x))

    bad = Filter(good.init, step, good.params)
    specs = [FilterSpec("good", good, "kf", layout=m), FilterSpec("bad", bad, "kf", layout=m)]
    P0 = np.diag([30.0, 5.0, 30.0, 5.0]) ** 2
    res = monte_carlo(sc, sensor, specs, 400, jax.random.key(3), P0, chunk=128)
    n_bad = float(res.sums["bad"]["diverged"])
    assert 0 < n_bad < 400
    assert res.sums["good"]["diverged"] == 0
    np.testing.assert_allclose(res.sums["bad"]["count"], 400 - n_bad)
    st = statistics(res, (1, steps))
    assert np.isfinite(st["filters"]["bad"]["summary"]["rmse_pos"])
    assert st["filters"]["bad"]["summary"]["diverged"] == n_bad


def test_missed_detections_keep_consistency(tmp_path):
    """p_detect < 1 on the linear-Gaussian case: misses are predict-only, NEES stays in band."""
    text = LINEAR.replace("runs = 10000", "runs = 3000").replace('sigma = [30.0, 60.0]', 'sigma = [30.0, 60.0]\np_detect = 0.7')
    exp = load_experiment(write(tmp_path, text))
    st = statistics(exp.monte_carlo(), exp.window)
    s = st["filters"]["KF"]["summary"]
    assert s["nees_in_bounds"] >= 0.8 and abs(s["nees"] - 4.0) < 0.15, s
    # with random misses the bound (expected information, Pd-scaled) is a lower bound, not tight
    assert 0.98 < s["rmse_pos_over_pcrlb"] < 1.1, s
