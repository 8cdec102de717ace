"""Unscented Kalman filter: exact on linear-Gaussian models, consistent on polar ones."""

import textwrap

import numpy as np
import pytest

import tracklab
from polar_pass import SIGMA, wrapping_pass
from tracklab.config import load_experiment
from tracklab.filters import build, noise_params
from tracklab.montecarlo.statistics import statistics
from tracklab.models import ca, cv
from tracklab.sensors import Sensor


@pytest.mark.parametrize("model", [cv(2, 1.0), ca(2, 0.5)], ids=["cv", "ca"])
def test_ukf_equals_kf_on_a_linear_gaussian_model(model):
    rng = np.random.default_rng(0)
    sensor = Sensor("cartesian", 2, (30.0, 60.0))
    p = noise_params(4.0, np.array([900.0, 3600.0]))
    z = rng.normal(size=(120, 2)).cumsum(0) * 30
    z[[5, 50, 51]] = np.nan
    z[20, 0] = np.nan  # a partial measurement: only y
    x0 = np.zeros(model.n)
    P0 = np.eye(model.n) * 400.0
    u = tracklab.run_filter(build("ukf", model, sensor, p), z, x0=x0, P0=P0)
    k = tracklab.run_filter(build("kf", model, sensor, p), z, x0=x0, P0=P0)
    np.testing.assert_allclose(u.x, k.x, rtol=1e-9, atol=1e-9 * np.abs(k.x).max())
    np.testing.assert_allclose(u.P, k.P, rtol=1e-9, atol=1e-9 * np.abs(k.P).max())
    np.testing.assert_array_equal(u.valid, k.valid)


POLAR = """
[experiment]
name = "ukf"
runs = 2000
dt = 0.5
steps = 100

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003

[prior]
pos_sigma = 100.0
vel_sigma = 50.0

[[filter]]
kind = "ukf"
label = "UKF"

[[filter]]
kind = "ekf"
label = "EKF"

[report]
window = [10, 100]
"""


def test_ukf_is_consistent_and_at_the_bound_on_the_lidar_crossing(tmp_path):
    path = tmp_path / "exp.toml"
    path.write_text(textwrap.dedent(POLAR))
    exp = load_experiment(path)
    st = statistics(exp.monte_carlo(), exp.window)
    u, e = st["filters"]["UKF"]["summary"], st["filters"]["EKF"]["summary"]
    assert u["diverged"] == 0
    assert abs(u["nees"] - 4.0) < 0.15 and u["nees_in_bounds"] > 0.8, u
    assert abs(u["rmse_pos_over_pcrlb"] - 1.0) < 0.02, u
    assert abs(u["rmse_pos"] / e["rmse_pos"] - 1.0) < 0.01


def test_ukf_wraps_angles_across_pi():
    """A target crossing the negative x axis: azimuth jumps from +π to −π; the track must not."""
    m, truth, z = wrapping_pass()
    sig = SIGMA
    flt = build("ukf", m, Sensor("polar", 2, tuple(sig)), noise_params(0.01, sig**2))
    res = tracklab.run_filter(flt, z, x0=np.linalg.solve(m.F, truth[0]), P0=np.diag([50.0, 5.0, 50.0, 5.0]) ** 2)
    err = np.hypot(res.x[:, 0] - truth[:, 0], res.x[:, 2] - truth[:, 2])
    assert np.all(err < 60.0), err.max()
