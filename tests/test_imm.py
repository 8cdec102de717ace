"""Interacting multiple models: one model is that model's filter; the modes follow a switching target."""

import numpy as np
import pytest

import tracklab
from tracklab.filters import build, imm_params, noise_params
from tracklab.filters.imm import transition
from tracklab.models import ca, cv
from tracklab.sensors import Sensor


@pytest.mark.parametrize("kind", ["cv", "ca"])
def test_imm_with_one_model_is_that_models_kalman_filter(kind):
    rng = np.random.default_rng(0)
    dt, T = 0.5, 150
    sensor = Sensor("cartesian", 2, (20.0, 30.0))
    t = dt * np.arange(1, T + 1)
    z = np.stack([100 * t + 3 * t**2, -50 * t], -1) + rng.normal(size=(T, 2)) * [20.0, 30.0]
    z[[10, 60, 61]] = np.nan
    z[90, 1] = np.nan
    q, r = (4.0 if kind == "cv" else 0.3), np.array([400.0, 900.0])
    model = cv(2, dt) if kind == "cv" else ca(2, dt)
    x0_ca = np.array([0.0, 100.0, 6.0, 0.0, -50.0, 0.0])
    P0_ca = np.diag([400.0, 100.0, 10.0, 400.0, 100.0, 10.0])
    imm = build("imm", ca(2, dt), sensor, imm_params([kind], [q], 1e-4, r), {"models": (kind,)})
    got = tracklab.run_filter(imm, z, x0=x0_ca, P0=P0_ca, dt=dt)
    if kind == "cv":  # the CV model's prediction drops the prior's acceleration: the same as a CV prior
        idx = [0, 1, 3, 4]
        x0, P0 = x0_ca[idx], P0_ca[np.ix_(idx, idx)]
    else:
        idx = list(range(6))
        x0, P0 = x0_ca, P0_ca
    ref = tracklab.run_filter(build("kf", model, sensor, noise_params(q, r)), z, x0=x0, P0=P0, dt=dt)
    np.testing.assert_allclose(np.asarray(got.aux["mode_probabilities"]), 1.0)
    np.testing.assert_allclose(got.x[:, idx], ref.x, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(got.P[:, np.array(idx)[:, None], np.array(idx)[None, :]], ref.P, rtol=1e-9, atol=1e-6)


def test_coordinated_turn_transition_matches_the_circle():
    """ct: a target on a circle of radius v/ω is moved exactly along it (and ω = 0 is a straight line)."""
    import jax.numpy as jnp

    f = transition("ct", 2, 0.7)
    w, v = 0.2, 150.0
    x = jnp.array([v / w, 0.0, 0.0, 0.0, v, 0.0, w])  # on a circle about the origin, moving anticlockwise
    y = np.asarray(f(x))
    ang = w * 0.7
    np.testing.assert_allclose(y[[0, 3]], v / w * np.array([np.cos(ang), np.sin(ang)]), rtol=1e-12)
    np.testing.assert_allclose(y[[1, 4]], v * np.array([-np.sin(ang), np.cos(ang)]), rtol=1e-12)
    np.testing.assert_allclose(y[[2, 5]], -w * v * np.array([np.cos(ang), np.sin(ang)]), rtol=1e-12)
    straight = np.asarray(f(x.at[-1].set(0.0)))
    np.testing.assert_allclose(straight[[0, 3]], [v / w, v * 0.7], rtol=1e-12)


def _turning_track(rng, dt=1.0):
    """Straight 60 s, a 3°/s turn for 40 s, straight 60 s; polar measurements."""
    x, y, vx, vy = -8000.0, 6000.0, 200.0, 0.0
    pos, phase = [], []
    for k in range(160):
        w = np.radians(3.0) if 60 <= k < 100 else 0.0
        if w:
            c, s = np.cos(w * dt), np.sin(w * dt)
            x, y = x + (np.sin(w * dt) * vx - (1 - c) * vy) / w, y + ((1 - c) * vx + np.sin(w * dt) * vy) / w
            vx, vy = c * vx - s * vy, s * vx + c * vy
        else:
            x, y = x + vx * dt, y + vy * dt
        pos.append((x, y))
        phase.append(1 if w else 0)
    pos = np.array(pos)
    sig = np.array([20.0, 0.002])
    z = np.stack([np.hypot(pos[:, 0], pos[:, 1]), np.arctan2(pos[:, 1], pos[:, 0])], -1) + rng.normal(size=(160, 2)) * sig
    return pos, np.array(phase), z, sig


def test_mode_probabilities_follow_a_target_that_turns():
    rng = np.random.default_rng(3)
    pos, phase, z, sig = _turning_track(rng)
    sensor = Sensor("polar", 2, tuple(sig))
    p = imm_params(("cv", "ct"), [0.25, 0.25], (0.002) ** 2, sig**2, p_stay=0.95)
    imm = build("imm", ca(2, 1.0), sensor, p, {"models": ("cv", "ct")})
    x0 = np.array([-8000.0, 200.0, 0.0, 6000.0, 0.0, 0.0])
    P0 = np.diag([400.0, 100.0, 1.0, 400.0, 100.0, 1.0])
    out = tracklab.run_filter(imm, z, x0=x0, P0=P0)
    mu_ct = np.asarray(out.aux["mode_probabilities"])[:, 1]
    assert mu_ct[75:100].mean() > 0.8  # inside the turn, once it is recognised
    assert mu_ct[20:60].mean() < 0.3 and mu_ct[120:].mean() < 0.3  # straight flight
    err_imm = np.hypot(*(out.x[:, [0, 3]] - pos).T)[65:100]
    kf_cv = tracklab.run_filter(build("ekf", cv(2, 1.0), sensor, noise_params(0.25, sig**2)), z,
                                x0=x0[[0, 1, 3, 4]], P0=P0[np.ix_([0, 1, 3, 4], [0, 1, 3, 4])])
    err_cv = np.hypot(*(kf_cv.x[:, [0, 2]] - pos).T)[65:100]
    assert np.sqrt(np.mean(err_imm**2)) < 0.2 * np.sqrt(np.mean(err_cv**2))


@pytest.mark.parametrize("sensor", ["spherical"])
def test_imm_in_an_experiment_with_2d_and_3d_sensors(tmp_path, sensor):
    """On the CV crossing the IMM pays a little for its other models (RMSE within 30 % of the
    CV EKF's) and is never overconfident; mixing in the CA and CT spreads makes it conservative."""
    from tracklab.config import load_experiment
    from tracklab.montecarlo.statistics import statistics

    spec = {"polar": 'kind = "polar"\nsigma_r = 50.0\nsigma_angle = 0.002',
            "spherical": 'kind = "spherical"\nsigma_r = 50.0\nsigma_az = 0.002\nsigma_el = 0.002'}[sensor]
    alt = "altitude = 3000.0" if sensor == "spherical" else ""
    (tmp_path / "e.toml").write_text(f"""
[experiment]
name = "imm"
runs = 300
dt = 1.0
steps = 60

[scenario]
kind = "crossing"
speed = 200.0
offset = 10000.0
start_x = -6000.0
accel_sigma = 0.5
{alt}

[sensor]
{spec}

[prior]
pos_sigma = 50.0
vel_sigma = 20.0
acc_sigma = 0.5

[[filter]]
kind = "ekf"
label = "EKF"
accel_sigma = 0.5

[[filter]]
kind = "imm"
label = "IMM"
q = [0.25, 0.01, 0.25]
p_stay = 0.97

[report]
window = [10, 60]
""")
    exp = load_experiment(tmp_path / "e.toml")
    st = statistics(exp.monte_carlo(), exp.window)["filters"]
    dim = 3 if sensor == "spherical" else 2
    assert st["IMM"]["summary"]["diverged"] == 0
    assert st["IMM"]["summary"]["rmse_pos"] < 1.3 * st["EKF"]["summary"]["rmse_pos"]
    assert 0.4 * 2 * dim < st["IMM"]["summary"]["nees"] < 1.2 * 2 * dim
