"""KF and EKF against an independent NumPy implementation on identical measurements."""

import numpy as np
import pytest

import tracklab
from polar_pass import SIGMA, wrapping_pass
from tracklab.filters import build, ekf, kf, noise_params
from tracklab.models import ca, cv
from tracklab.sensors import Sensor

RTOL = 1e-9


def np_kf(F, H, Q, R, z, x0, P0):
    """Textbook KF (standard-form covariance update); NaN rows are predict-only."""
    x, P = x0.copy(), P0.copy()
    xs, Ps = [], []
    for zk in z:
        x = F @ x
        P = F @ P @ F.T + Q
        if np.all(np.isfinite(zk)):
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ (zk - H @ x)
            P = (np.eye(len(x)) - K @ H) @ P
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


def np_polar_ekf(F, Q, R, z, x0, P0):
    """EKF with the analytic polar Jacobian of paper 000 eq. (21)."""
    x, P = x0.copy(), P0.copy()
    xs, Ps = [], []
    for zk in z:
        x = F @ x
        P = F @ P @ F.T + Q
        if np.all(np.isfinite(zk)):
            px, py = x[0], x[2]
            r = np.hypot(px, py)
            b = np.arctan2(py, px)
            H = np.array([[np.cos(b), 0, np.sin(b), 0], [-np.sin(b) / r, 0, np.cos(b) / r, 0]])
            nu = zk - np.array([r, b])
            nu[1] = (nu[1] + np.pi) % (2 * np.pi) - np.pi
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ nu
            P = (np.eye(4) - K @ H) @ P
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


def crossing_truth(rng, T, dt, dim=2):
    m = cv(dim, dt)
    s = np.array([-20000.0, 400.0, 20000.0, 0.0] + ([3000.0, 0.0] if dim == 3 else []))
    out = []
    for _ in range(T):
        s = m.F @ s + m.G @ rng.normal(size=dim)
        out.append(s)
    return np.array(out)


def test_kf_matches_numpy_with_missed_detections():
    rng = np.random.default_rng(1)
    dt, T = 0.5, 120
    m = cv(2, dt)
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    Q = np.asarray(m.Q(1.0))
    R = np.diag([50.0**2, 80.0**2])
    truth = crossing_truth(rng, T, dt)
    z = truth[:, [0, 2]] + rng.normal(size=(T, 2)) * [50.0, 80.0]
    z[[3, 40, 41, 90]] = np.nan
    x0 = np.array([-20000.0, 390.0, 20050.0, 5.0])
    P0 = np.diag([100.0, 20.0, 100.0, 20.0]) ** 2
    res = tracklab.run_filter(kf(m.F, H, Q, R), z, x0=x0, P0=P0)
    xr, Pr = np_kf(m.F, H, Q, R, z, x0, P0)
    np.testing.assert_allclose(res.x, xr, rtol=RTOL, atol=1e-9 * np.abs(xr).max())
    np.testing.assert_allclose(res.P, Pr, rtol=RTOL, atol=1e-12 * np.abs(Pr).max())
    assert not bool(res.valid[40]) and bool(res.valid[39])


def test_batched_run_filter_equals_single_runs():
    rng = np.random.default_rng(2)
    m = cv(1, 1.0)
    flt = kf(m.F, np.array([[1.0, 0.0]]), np.asarray(m.Q(0.5)), np.array([[4.0]]))
    z = rng.normal(size=(3, 50, 1)).cumsum(axis=1)
    x0, P0 = np.zeros(2), np.eye(2) * 10
    batch = tracklab.run_filter(flt, z, x0=x0, P0=P0)
    for i in range(3):
        one = tracklab.run_filter(flt, z[i], x0=x0, P0=P0)
        np.testing.assert_allclose(batch.x[i], one.x, rtol=1e-12)
        np.testing.assert_allclose(batch.P[i], one.P, rtol=1e-12)


@pytest.mark.parametrize("public", [True, False], ids=["tracklab.filters.ekf", "experiment-ekf"])
def test_polar_ekf_matches_numpy(public):
    rng = np.random.default_rng(3)
    dt, T = 0.5, 200
    m = cv(2, dt)
    sig = np.array([100.0, 0.003])
    truth = crossing_truth(rng, T, dt)
    r = np.hypot(truth[:, 0], truth[:, 2])
    b = np.arctan2(truth[:, 2], truth[:, 0])
    z = np.stack([r, b], 1) + rng.normal(size=(T, 2)) * sig
    z[[10, 11, 150]] = np.nan
    Q = np.asarray(m.Q(1.0))
    R = np.diag(sig**2)
    x0 = np.array([-19900.0, 420.0, 20100.0, -30.0])
    P0 = np.diag([100.0, 50.0, 100.0, 50.0]) ** 2
    if public:
        import jax.numpy as jnp

        h = lambda x: jnp.stack([jnp.hypot(x[0], x[2]), jnp.arctan2(x[2], x[0])])
        flt = ekf(lambda x: jnp.asarray(m.F) @ x, h, Q, R, angle_mask=(False, True))
    else:
        flt = build("ekf", m, Sensor("polar", 2, tuple(sig)), noise_params(1.0, sig**2))
    res = tracklab.run_filter(flt, z, x0=x0, P0=P0)
    xr, Pr = np_polar_ekf(m.F, Q, R, z, x0, P0)
    np.testing.assert_allclose(res.x, xr, rtol=RTOL, atol=1e-9 * np.abs(xr).max())
    np.testing.assert_allclose(res.P, Pr, rtol=RTOL, atol=1e-9 * np.abs(Pr).max())


def test_angle_innovation_is_wrapped_across_pi():
    """A target near β = ±π: the measured angle jumps by 2π, the estimate must not."""
    m, truth, z = wrapping_pass()
    sig = SIGMA
    flt = build("ekf", m, Sensor("polar", 2, tuple(sig)), noise_params(0.01, sig**2))
    x0, P0 = np.linalg.solve(m.F, truth[0]), np.diag([50.0, 5.0, 50.0, 5.0]) ** 2
    res = tracklab.run_filter(flt, z, x0=x0, P0=P0)
    err = np.hypot(res.x[:, 0] - truth[:, 0], res.x[:, 2] - truth[:, 2])
    assert np.all(err < 60.0)
    xr, _ = np_polar_ekf(m.F, np.asarray(m.Q(0.01)), np.diag(sig**2), z, x0, P0)
    np.testing.assert_allclose(res.x, xr, rtol=RTOL, atol=1e-6)


def test_ca_model_kf_matches_numpy():
    rng = np.random.default_rng(5)
    dt, T = 0.1, 100
    m = ca(2, dt)
    sensor = Sensor("cartesian", 2, (3.0, 3.0))
    flt = build("kf", m, sensor, noise_params(0.2, np.array([9.0, 9.0])))
    z = rng.normal(size=(T, 2)).cumsum(0) * 3
    H = np.zeros((2, 6))
    H[0, 0] = H[1, 3] = 1.0
    x0, P0 = np.zeros(6), np.eye(6) * 25.0
    res = tracklab.run_filter(flt, z, x0=x0, P0=P0)
    xr, Pr = np_kf(m.F, H, np.asarray(m.Q(0.2)), np.diag([9.0, 9.0]), z, x0, P0)
    np.testing.assert_allclose(res.x, xr, rtol=RTOL, atol=1e-9 * np.abs(xr).max())
    np.testing.assert_allclose(res.P, Pr, rtol=RTOL, atol=1e-9 * np.abs(Pr).max())
