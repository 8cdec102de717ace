"""Strong tracking filter: against a NumPy implementation of docs/mathematics.md §3, and
its reduction to the Kalman filter when the fading factor stays at 1."""

import numpy as np
import pytest

import tracklab
from tracklab.filters import build, noise_params, strong_tracking
from tracklab.models import ca, cv
from tracklab.sensors import Sensor


def numpy_stf(z, x0, P0, F, Q, R, rho, b, h, jac_h, angle=None):
    """Straight from the reference steps, with the full matrix V (NaN = component absent)."""
    x, P = np.array(x0, float), np.array(P0, float)
    m = R.shape[0]
    V, started = np.zeros((m, m)), np.zeros(m, bool)
    xs, Ps, lams = [], [], []
    for zk in z:
        pres = np.isfinite(zk)
        xp = F @ x
        FPF = F @ P @ F.T
        H = jac_h(xp)
        g = np.where(pres, zk, 0.0) - h(xp)
        if angle is not None:
            g[angle] = (g[angle] + np.pi) % (2 * np.pi) - np.pi
        g = np.where(pres, g, 0.0)
        lam = 1.0
        if pres.any():
            both = np.outer(pres, pres)
            new = np.where(np.outer(started, started), (rho * V + np.outer(g, g)) / (1 + rho), np.outer(g, g))
            V = np.where(both, new, V)
            started |= pres
            N = V - H @ Q @ H.T - b * R
            M = H @ FPF @ H.T
            idx = np.flatnonzero(pres)
            lam = max(1.0, np.trace(N[np.ix_(idx, idx)]) / np.trace(M[np.ix_(idx, idx)]))
        Pp = lam * FPF + Q
        if pres.any():
            idx = np.flatnonzero(pres)
            Hs, Rs = H[idx], R[np.ix_(idx, idx)]
            S = Hs @ Pp @ Hs.T + Rs
            K = Pp @ Hs.T @ np.linalg.inv(S)
            x = xp + K @ g[idx]
            I_KH = np.eye(len(x)) - K @ Hs
            P = I_KH @ Pp @ I_KH.T + K @ Rs @ K.T
        else:
            x, P = xp, Pp
        xs.append(x)
        Ps.append(P)
        lams.append(lam)
    return np.array(xs), np.array(Ps), np.array(lams)


def manoeuvring_measurements(rng, T, dt, sigma):
    """A target that turns halfway: the kind of input the fading factor reacts to."""
    t = dt * np.arange(1, T + 1)
    turn = np.clip(t - 0.5 * t[-1], 0, None)
    pos = np.stack([30.0 * t + 2.0 * turn**2, 10.0 * t - 1.5 * turn**2], -1)
    return pos + rng.normal(size=pos.shape) * sigma


def test_linear_stf_matches_numpy():
    rng = np.random.default_rng(1)
    model = ca(2, 0.5)
    sigma = np.array([3.0, 5.0])
    z = manoeuvring_measurements(rng, 160, 0.5, sigma)
    z[[7, 40, 41]] = np.nan
    z[90, 1] = np.nan  # a partial measurement
    sensor = Sensor("cartesian", 2, tuple(sigma))
    p = dict(noise_params(0.05, sigma**2), rho=0.9, b=1.5)
    x0, P0 = np.zeros(6), np.eye(6) * 100.0
    got = tracklab.run_filter(build("stf", model, sensor, p), z, x0=x0, P0=P0, dt=0.5)
    H = np.zeros((2, 6))
    H[[0, 1], [0, 3]] = 1.0
    xs, Ps, lams = numpy_stf(z, x0, P0, model.F, np.asarray(model.Q(0.05)), np.diag(sigma**2), 0.9, 1.5,
                             lambda x: H @ x, lambda x: H)
    assert (lams > 1).sum() > 10  # the test exercises the fading
    np.testing.assert_allclose(got.aux["fading"], lams, rtol=1e-9)
    np.testing.assert_allclose(got.x, xs, rtol=1e-9, atol=1e-9 * np.abs(xs).max())
    np.testing.assert_allclose(got.P, Ps, rtol=1e-9, atol=1e-9 * np.abs(Ps).max())


def test_extended_stf_on_polar_measurements_matches_numpy():
    rng = np.random.default_rng(2)
    model = cv(2, 1.0)
    t = np.arange(1, 121, dtype=float)
    pos = np.stack([-6000.0 + 100.0 * t, 600.0 - 20.0 * t + 0.3 * np.clip(t - 70, 0, None) ** 2], -1)  # crosses ±π
    sig = np.array([10.0, 0.002])
    z = np.stack([np.hypot(pos[:, 0], pos[:, 1]), np.arctan2(pos[:, 1], pos[:, 0])], -1) + rng.normal(size=(120, 2)) * sig
    z[:, 1] = (z[:, 1] + np.pi) % (2 * np.pi) - np.pi
    z[33] = np.nan
    sensor = Sensor("polar", 2, tuple(sig))
    p = dict(noise_params(1.0, sig**2), rho=0.95, b=1.0)
    x0 = np.array([-6000.0, 100.0, 600.0, -20.0])
    P0 = np.diag([400.0, 100.0, 400.0, 100.0])
    got = tracklab.run_filter(build("stf", model, sensor, p), z, x0=x0, P0=P0)

    def h(x):
        return np.array([np.hypot(x[0], x[2]), np.arctan2(x[2], x[0])])

    def jac(x):
        r2 = x[0] ** 2 + x[2] ** 2
        r = np.sqrt(r2)
        return np.array([[x[0] / r, 0, x[2] / r, 0], [-x[2] / r2, 0, x[0] / r2, 0]])

    xs, Ps, lams = numpy_stf(z, x0, P0, model.F, np.asarray(model.Q(1.0)), np.diag(sig**2), 0.95, 1.0, h, jac, angle=1)
    assert np.ptp(z[np.isfinite(z[:, 1]), 1]) > 5.0  # the bearing wraps through ±π
    np.testing.assert_allclose(got.aux["fading"], lams, rtol=1e-9)
    np.testing.assert_allclose(got.x, xs, rtol=1e-9, atol=1e-9 * np.abs(xs).max())
    np.testing.assert_allclose(got.P, Ps, rtol=1e-9, atol=1e-9 * np.abs(Ps).max())


def _linear_gaussian_run(b, T=3000, seed=3):
    """CV truth with the filter's own q and R: a correctly specified model."""
    rng = np.random.default_rng(seed)
    model = cv(2, 1.0)
    q, sig = 0.5, np.array([20.0, 20.0])
    F, G = model.F, model.G
    x = np.array([0.0, 10.0, 0.0, -5.0])
    zs = []
    for _ in range(T):
        x = F @ x + G @ (np.sqrt(q) * rng.normal(size=2))
        zs.append(x[[0, 2]] + sig * rng.normal(size=2))
    sensor = Sensor("cartesian", 2, tuple(sig))
    prior = dict(x0=np.array([0.0, 10.0, 0.0, -5.0]), P0=np.diag([400.0, 25.0, 400.0, 25.0]))
    p = noise_params(q, sig**2)
    stf = tracklab.run_filter(build("stf", model, sensor, dict(p, rho=0.95, b=b)), np.array(zs), **prior)
    kf_flt = build("kf", model, sensor, p)
    return np.array(zs), stf, kf_flt, prior


def test_stf_with_b1_in_steady_state_is_the_kalman_filter_where_fading_is_1():
    """b = 1, true model: λ = 1 on most steps, and there the STF's step is the KF's step."""
    z, stf, kf_flt, prior = _linear_gaussian_run(b=1.0)
    lam = np.asarray(stf.aux["fading"])[500:]  # steady state
    assert np.mean(lam == 1.0) > 0.5
    # a KF step from the STF's own previous posterior gives the STF's posterior wherever λ = 1
    steps = np.flatnonzero(np.asarray(stf.aux["fading"]) == 1.0)
    steps = steps[steps > 500][:200]
    for k in steps:
        one = tracklab.run_filter(kf_flt, z[k:k + 1], x0=stf.x[k - 1], P0=stf.P[k - 1])
        np.testing.assert_allclose(one.x[0], stf.x[k], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(one.P[0], stf.P[k], rtol=1e-12, atol=1e-9)


def test_stf_with_a_large_weakening_factor_is_the_kalman_filter():
    z, stf, kf_flt, prior = _linear_gaussian_run(b=10.0, T=1500)
    assert np.all(np.asarray(stf.aux["fading"]) == 1.0)
    kf_out = tracklab.run_filter(kf_flt, z, **prior)
    np.testing.assert_allclose(stf.x, kf_out.x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(stf.P, kf_out.P, rtol=1e-12, atol=1e-9)


def test_public_constructor_on_a_scalar_random_walk():
    """strong_tracking(f, h, Q, R): a level jump makes λ > 1 and the filter catches up faster than the KF."""
    z = np.concatenate([np.zeros(100), 50.0 * np.ones(30)])[:, None] + np.random.default_rng(4).normal(size=(130, 1))
    f = lambda x: x
    h = lambda x: x
    stf = tracklab.run_filter(strong_tracking(f, h, [[0.01]], [[1.0]]), z, x0=[0.0], P0=[[1.0]])
    kf_out = tracklab.run_filter(tracklab.filters.kf([[1.0]], [[1.0]], [[0.01]], [[1.0]]), z, x0=[0.0], P0=[[1.0]])
    assert stf.aux["fading"][100] > 10.0
    assert abs(stf.x[105, 0] - 50.0) < 0.2 * abs(kf_out.x[105, 0] - 50.0)


@pytest.mark.parametrize("name", ["rho", "b"])
def test_stf_gradient_with_respect_to_rho_and_b_matches_finite_differences(name):
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(5)
    model = ca(2, 0.5)
    sigma = np.array([3.0, 5.0])
    z = manoeuvring_measurements(rng, 120, 0.5, sigma)
    truth_free = manoeuvring_measurements(np.random.default_rng(5), 120, 0.5, 0 * sigma)
    flt = build("stf", model, Sensor("cartesian", 2, tuple(sigma)), dict(noise_params(0.05, sigma**2), rho=0.9, b=1.5))
    x0, P0 = np.zeros(6), np.eye(6) * 100.0

    def loss(v):
        p = dict(flt.params, **{name: v})
        out = tracklab.run_filter(flt, z, x0=x0, P0=P0, params=p, dt=0.5)
        return jnp.mean((out.x[:, jnp.array([0, 3])] - truth_free) ** 2)

    v0 = float(flt.params[name])
    g = float(jax.grad(loss)(jnp.asarray(v0)))
    eps = 1e-6
    fd = (float(loss(jnp.asarray(v0 + eps))) - float(loss(jnp.asarray(v0 - eps)))) / (2 * eps)
    assert abs(g) > 0
    np.testing.assert_allclose(g, fd, rtol=1e-4)
