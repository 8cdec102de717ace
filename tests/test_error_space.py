"""Error-space estimator (paper 004): against a NumPy implementation of steps (1)-(5),
and exact one-step predictions where the guide error follows the error model."""

import numpy as np
import pytest

import tracklab
from tracklab.filters import build, noise_params
from tracklab.models import ca, cv
from tracklab.sensors import Sensor


def numpy_error_space(z, x0, P0, model, q, r, q_e, r_e, guide=None, r_guide=None, delay=0):
    """Steps (2)-(5) of paper 004 §2.3 with two plain Kalman filters (NaN = no observation).

    Returns the one-step predictions Ẑ(k, k−1) and the estimates L̂(k) + ê(k|k)
    (full states), in the order of the measurements.
    """
    F, n, m = model.F, model.n, model.dim
    H = np.zeros((m, n))
    H[np.arange(m), list(model.pos_idx)] = 1.0
    Q, Qe = np.asarray(model.Q(q)), np.asarray(model.Q(q_e))
    R, Re = np.diag(r), np.diag(r_e)
    Rg = R if guide is None else np.diag(r_guide)
    lag = 1 + delay
    Fi = np.linalg.inv(F)
    Lx, LP = np.linalg.matrix_power(Fi, lag - 1) @ x0, P0.copy()  # L̂(1)
    ex, eP = (np.eye(n) - np.linalg.matrix_power(Fi, lag)) @ x0, P0.copy()  # ê(0|0)
    guide_readings = z if guide is None else guide
    preds, ests = [], []

    def kf_update(x, P, y, Rm):
        ok = np.isfinite(y)
        if not ok.any():
            return x, P
        Hs, Rs = H[ok], Rm[np.ix_(ok, ok)]
        S = Hs @ P @ Hs.T + Rs
        K = P @ Hs.T @ np.linalg.inv(S)
        I_KH = np.eye(n) - K @ Hs
        return x + K @ (y[ok] - Hs @ x), I_KH @ P @ I_KH.T + K @ Rs @ K.T

    for k, zk in enumerate(z):
        # step (3) for e: predict ê(k|k−1); the synthesis (5) made at k−1 is Ẑ(k, k−1)
        ex, eP = F @ ex, F @ eP @ F.T + Qe
        preds.append(Lx + ex)
        # step (2): e(k) = Z(k) − L̂(k), then the error filter's update
        ex, eP = kf_update(ex, eP, zk - H @ Lx, Re)
        ests.append(Lx + ex)
        # step (4): L(k+1) = the guide's reading, filtered
        j = k - delay
        g = guide_readings[j] if j >= 0 else np.full(m, np.nan)
        Lx, LP = F @ Lx, F @ LP @ F.T + Q
        Lx, LP = kf_update(Lx, LP, g, Rg)
    return np.array(preds), np.array(ests)


def _track(T, dt, rng, sigma):
    t = dt * np.arange(1, T + 1)
    pos = np.stack([20.0 * np.sin(0.3 * t) + 0.5 * t, 10.0 + 3.0 * t - 0.02 * t**2], -1)
    return pos, pos + rng.normal(size=pos.shape) * sigma


def test_error_space_matches_numpy_with_the_previous_observation_as_guide():
    rng = np.random.default_rng(0)
    model = ca(2, 0.1)
    sigma = np.array([0.05, 0.08])
    _, z = _track(300, 0.1, rng, sigma)
    z[[10, 11, 150]] = np.nan
    z[200, 0] = np.nan
    p = dict(noise_params(0.01, sigma**2), q_e=0.002, r_e=sigma**2 * 2)
    x0, P0 = np.array([0.0, 10.0, 0.0, 10.0, 3.0, 0.0]), np.eye(6)
    got = tracklab.run_filter(build("error_space", model, Sensor("cartesian", 2, tuple(sigma)), p), z, x0=x0, P0=P0, dt=0.1)
    preds, ests = numpy_error_space(z, x0, P0, model, 0.01, sigma**2, 0.002, sigma**2 * 2)
    np.testing.assert_allclose(got.x_pred, preds, rtol=1e-9, atol=1e-9 * np.abs(preds).max())
    np.testing.assert_allclose(got.x, ests, rtol=1e-9, atol=1e-9 * np.abs(ests).max())


@pytest.mark.parametrize("delay", [0, 3])
def test_error_space_matches_numpy_with_an_external_delayed_guide(delay):
    rng = np.random.default_rng(1)
    model = ca(2, 0.1)
    sigma, sigma_g = np.array([0.05, 0.05]), np.array([0.3, 0.4])
    pos, z = _track(250, 0.1, rng, sigma)
    zg = pos + rng.normal(size=pos.shape) * sigma_g
    zg[[5, 6, 7, 100]] = np.nan  # the guide drops out
    z[[50, 51]] = np.nan
    p = dict(noise_params(0.01, sigma**2), q_e=0.003, r_e=sigma**2, r_guide=sigma_g**2)
    suite = tracklab.sensors.SensorSuite((Sensor("cartesian", 2, tuple(sigma), name="a"),
                                          Sensor("cartesian", 2, tuple(sigma_g), name="g")))
    flt = build("error_space", model, suite, p, {"guide": "g", "guide_delay": delay})
    x0, P0 = np.array([0.0, 10.0, 0.0, 10.0, 3.0, 0.0]), np.eye(6)
    got = tracklab.run_filter(flt, np.concatenate([z, zg], -1), x0=x0, P0=P0, dt=0.1)
    preds, ests = numpy_error_space(z, x0, P0, model, 0.01, sigma**2, 0.003, sigma**2, guide=zg,
                                    r_guide=sigma_g**2, delay=delay)
    np.testing.assert_allclose(got.x_pred, preds, rtol=1e-9, atol=1e-9 * np.abs(preds).max())
    np.testing.assert_allclose(got.x, ests, rtol=1e-9, atol=1e-9 * np.abs(ests).max())


def _polynomial_target(coef, dt, T):
    """Noise-free positions and the CA state [x, ẋ, ẍ, y, ẏ, ÿ] at t = 0 of a polynomial path."""

    def state(t):
        return np.array([np.polyval(np.polyder(coef[::-1, a], d), t) if d else np.polyval(coef[::-1, a], t)
                         for a in range(2) for d in range(3)])

    t = dt * np.arange(1, T + 1)
    return np.stack([state(tk)[[0, 3]] for tk in t]), state(0.0)


def _es_and_kf(truth, x0, dt):
    model = ca(2, dt)
    sensor = Sensor("cartesian", 2, (1e-3, 1e-3))
    r = np.array([1e-6, 1e-6])
    p = dict(noise_params(1e-6, r), q_e=1e-6, r_e=r)
    P0 = np.eye(6) * 1e-2
    es = tracklab.run_filter(build("error_space", model, sensor, p), truth, x0=x0, P0=P0, dt=dt)
    kf_out = tracklab.run_filter(build("kf", model, sensor, noise_params(1e-6, r)), truth, x0=x0, P0=P0, dt=dt)
    return es.x_pred[:, [0, 3]], kf_out.x_pred[:, [0, 3]]


def test_prediction_is_exact_when_the_guide_error_is_constant_velocity():
    """Z(t) quadratic: the guide error e(k) = Z(k) − Z(k−1) is exactly CV.

    With noise-free observations and the exact prior every residual is zero, so
    Ẑ(k+1, k) = L̂(k+1) + ê(k+1, k) is the analytic one-step prediction Z(k+1).
    Synthesising with L̂(k) or with ê(k|k) instead would be off by a whole step.
    """
    coef = np.array([[0.3, -2.0], [1.5, 0.7], [-0.2, 0.05]])  # rows: powers of t
    truth, x0 = _polynomial_target(coef, 0.04, 400)
    es, _ = _es_and_kf(truth, x0, 0.04)
    np.testing.assert_allclose(es, truth, rtol=0, atol=1e-10 * np.abs(truth).max())


def test_on_a_jerking_target_the_error_space_prediction_beats_the_ca_kalman_filter():
    """Z(t) cubic: the CA model is wrong for both methods; the guide error absorbs most of the lag."""
    coef = np.array([[0.3, -2.0], [1.5, 0.7], [-0.2, 0.05], [0.01, -0.004]])
    truth, x0 = _polynomial_target(coef, 0.04, 400)
    es, kf_pred = _es_and_kf(truth, x0, 0.04)
    err_es = np.abs(es - truth)[200:].max()
    err_kf = np.abs(kf_pred - truth)[200:].max()
    assert err_es < 0.01 * err_kf


def test_error_space_reports_the_guide_plus_the_error_state():
    """x̂(k|k) = L̂(k) + ê(k|k): on a CV target with CV models both filters' rates add up to the target's."""
    rng = np.random.default_rng(2)
    model = cv(1, 1.0)
    T = 400
    truth = 5.0 + 2.0 * np.arange(1, T + 1)
    z = (truth + rng.normal(size=T))[:, None]
    p = dict(noise_params(1e-4, np.array([1.0])), q_e=1e-4, r_e=np.array([1.0]))
    out = tracklab.run_filter(build("error_space", model, Sensor("cartesian", 1, (1.0,)), p), z,
                              x0=np.array([5.0, 2.0]), P0=np.eye(2))
    assert abs(out.x[-50:, 1].mean() - 2.0) < 0.05
    assert np.sqrt(np.mean((out.x[-100:, 0] - truth[-100:]) ** 2)) < 1.0
