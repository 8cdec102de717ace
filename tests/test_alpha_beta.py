"""α-β / α-β-γ filters: gains, least-squares equivalence, steady state, gradients.

References: docs/mathematics.md §2; paper 002 eqs. 1–9. Conventions of the library:
K = [α, β/T] (α-β, DWNA model) and K = [α, β/T, γ/(2T²)] (α-β-γ, DWPA model),
tracking index λ = σ_v T²/σ_w.

Every gain check reads the gain the *filter* actually applied, from its own
outputs (x = x_pred + K ν), not only the closed-form helper functions, so the
tests fail if the helpers are right but the filter scales or schedules them wrongly.
"""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tracklab
from tracklab.filters import (
    growing_memory_alpha_beta,
    growing_memory_alpha_beta_gamma,
    kalata_alpha_beta,
    kalata_alpha_beta_gamma,
    model_alpha_beta,
)
from tracklab.filters.alphabeta import ABState
from tracklab.filters.core import Meas, Prior
from tracklab.montecarlo.statistics import statistics
from tracklab.models import ca, cv
from tracklab.sensors import Sensor

LAMBDAS = [1e-3, 3e-3, 1e-2, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0]
PERIODS = [0.1, 1.0, 2.5]


# ---------------------------------------------------------------- helpers


def model_matrices(order, T):
    """Per-axis F, Γ of the DWNA (order 2) or DWPA (order 3) model, written out by hand."""
    if order == 2:
        return np.array([[1.0, T], [0.0, 1.0]]), np.array([T**2 / 2, T])
    F = np.array([[1.0, T, T**2 / 2], [0.0, 1.0, T], [0.0, 0.0, 1.0]])
    return F, np.array([T**2 / 2, T, 1.0])


def riccati_gain(F, Gam, sigma_v, sigma_w, max_iter=200_000):
    """Steady-state Kalman gain by iterating the discrete Riccati recursion to convergence."""
    n = F.shape[0]
    H = np.zeros((1, n))
    H[0, 0] = 1.0
    Q = sigma_v**2 * np.outer(Gam, Gam)
    M = Q + np.eye(n) * sigma_w**2  # any positive-definite start converges
    K_old = np.full(n, np.inf)
    for _ in range(max_iter):
        S = M[0, 0] + sigma_w**2
        K = M[:, 0] / S
        P = M - np.outer(K, M[0, :])
        P = 0.5 * (P + P.T)
        M = F @ P @ F.T + Q
        if np.max(np.abs(K - K_old) / np.abs(K)) < 1e-15:
            return K
        K_old = K
    raise AssertionError("Riccati iteration did not converge")


def applied_gain(flt, params, n, dt):
    """The gain the filter applies in one update: prior mean 0 (so x_pred = 0) and z = 1 give x = K."""
    s = flt.init(params, Prior(jnp.zeros(n), jnp.eye(n)))
    s, out = flt.step(params, s, Meas(jnp.ones(1), jnp.asarray(dt), jnp.asarray(True)))
    np.testing.assert_array_equal(np.asarray(out.x_pred), 0.0)
    return np.asarray(out.x)


def cartesian_1d(sigma_w):
    return Sensor("cartesian", 1, (float(sigma_w),))


def gain_vector(gains, T):
    """[α, β/T(, γ/(2T²))] from the library's dimensionless gains."""
    scale = np.array([1.0, 1.0 / T, 1.0 / (2 * T**2)])[: len(gains)]
    return np.asarray([float(g) for g in gains]) * scale


# ---------------------------------------------------------------- 1. Kalata = steady-state Kalman gain


@pytest.mark.parametrize("T", PERIODS)
def test_kalata_alpha_beta_is_steady_state_kalman_gain(T):
    sigma_w = 7.0
    F, Gam = model_matrices(2, T)
    for lam in LAMBDAS:
        sigma_v = lam * sigma_w / T**2
        K_ss = riccati_gain(F, Gam, sigma_v, sigma_w)
        a, b = kalata_alpha_beta(jnp.asarray(lam))
        np.testing.assert_allclose(gain_vector((a, b), T), K_ss, rtol=1e-8, err_msg=f"lambda={lam}")
        # the paper's side relations (docs/mathematics.md §2)
        np.testing.assert_allclose(float(b), 2 * (2 - float(a)) - 4 * np.sqrt(1 - float(a)), rtol=1e-8, atol=1e-14)
        np.testing.assert_allclose(lam**2, float(b) ** 2 / (1 - float(a)), rtol=1e-8)
        # and the filter applies exactly that gain, in the [α, β/T] layout
        m = cv(1, T)
        params = {"q": jnp.asarray(sigma_v**2), "r": jnp.asarray([sigma_w**2]), "lam": jnp.asarray([lam])}
        flt = model_alpha_beta(m, cartesian_1d(sigma_w), params, gains="kalata")
        np.testing.assert_allclose(applied_gain(flt, params, 2, T), K_ss, rtol=1e-8, err_msg=f"lambda={lam}")


# λ ≤ 12√3 ≈ 20.78: the cubic s³ + (λ/2 − 3)s² + (λ/2 + 3)s − 1 has one real root (Cardano's
# formula); above it three, and the trigonometric form must pick the one in (0, 1).
LAMBDAS_ABG = [lam for lam in LAMBDAS if lam < 12 * np.sqrt(3)] + [20.0, 20.78]


def _check_kalata_abg(T, lambdas):
    sigma_w = 7.0
    F, Gam = model_matrices(3, T)
    for lam in lambdas:
        sigma_v = lam * sigma_w / T**2
        K_ss = riccati_gain(F, Gam, sigma_v, sigma_w)
        a, b, g = kalata_alpha_beta_gamma(jnp.asarray(lam))
        np.testing.assert_allclose(gain_vector((a, b, g), T), K_ss, rtol=1e-8, err_msg=f"lambda={lam}")
        a, b, g = float(a), float(b), float(g)
        np.testing.assert_allclose(b, 2 * (2 - a) - 4 * np.sqrt(1 - a), rtol=1e-8, atol=1e-14)
        np.testing.assert_allclose(g, b**2 / a, rtol=1e-8)
        np.testing.assert_allclose(lam**2, g**2 / (4 * (1 - a)), rtol=1e-8)
        m = ca(1, T)
        params = {"q": jnp.asarray(sigma_v**2), "r": jnp.asarray([sigma_w**2]), "lam": jnp.asarray([lam])}
        flt = model_alpha_beta(m, cartesian_1d(sigma_w), params, gains="kalata")
        np.testing.assert_allclose(applied_gain(flt, params, 3, T), K_ss, rtol=1e-8, err_msg=f"lambda={lam}")


@pytest.mark.parametrize("T", PERIODS)
def test_kalata_alpha_beta_gamma_is_steady_state_kalman_gain(T):
    _check_kalata_abg(T, LAMBDAS_ABG)


@pytest.mark.parametrize("lam", [21.0, 30.0, 100.0])
def test_kalata_alpha_beta_gamma_large_tracking_index(lam):
    _check_kalata_abg(1.0, [lam])


@pytest.mark.parametrize("lam,T", [(0.03, 1.0), (0.5, 0.25), (5.0, 2.0)])
def test_kalata_filter_covariance_converges_to_closed_form(lam, T):
    """The filter's own propagated P (Joseph form with its fixed gain) ends at docs/mathematics.md §2's P(k|k)."""
    sigma_w = 100.0
    sigma_v = lam * sigma_w / T**2
    params = {"q": jnp.asarray(sigma_v**2), "r": jnp.asarray([sigma_w**2]), "lam": jnp.asarray([lam])}
    z = np.zeros((3000, 1))  # P does not depend on the data

    flt = model_alpha_beta(cv(1, T), cartesian_1d(sigma_w), params, gains="kalata")
    P = np.asarray(tracklab.run_filter(flt, z, x0=np.zeros(2), P0=np.eye(2) * 1e4, dt=T).P[-1])
    a, b = (float(v) for v in kalata_alpha_beta(jnp.asarray(lam)))
    closed = sigma_w**2 * np.array([[a, b / T], [b / T, b * (2 * a - b) / (2 * (1 - a) * T**2)]])
    np.testing.assert_allclose(P, closed, rtol=1e-8)

    flt3 = model_alpha_beta(ca(1, T), cartesian_1d(sigma_w), params, gains="kalata")
    P3 = np.asarray(tracklab.run_filter(flt3, z, x0=np.zeros(3), P0=np.eye(3) * 1e4, dt=T).P[-1])
    a, b, g = (float(v) for v in kalata_alpha_beta_gamma(jnp.asarray(lam)))
    closed3 = sigma_w**2 * np.array(
        [
            [a, b / T, g / (2 * T**2)],
            [b / T, (8 * a * b + g * (b - 2 * a - 4)) / (8 * (1 - a) * T**2), b * (2 * b - g) / (4 * (1 - a) * T**3)],
            [g / (2 * T**2), b * (2 * b - g) / (4 * (1 - a) * T**3), g * (2 * b - g) / (4 * (1 - a) * T**4)],
        ]
    )
    np.testing.assert_allclose(P3, closed3, rtol=1e-8)


# ---------------------------------------------------------------- 2. growing memory = least squares


def _ls_fit(t, z, k, deg):
    """Least-squares polynomial fit of z_1..z_k, evaluated at t_k: [value, 1st, (2nd) derivative]."""
    s = t[:k] - t[k - 1]  # centred time: well conditioned
    c = np.polyfit(s, z[:k], deg)[::-1]  # c0 + c1 s + c2 s²
    return np.array([c[0], c[1]] + ([2 * c[2]] if deg == 2 else []))


@pytest.mark.parametrize("T", [0.5, 1.0, 3.0])
@pytest.mark.parametrize("order", [2, 3])
def test_growing_memory_gains_equal_least_squares_fit(order, T):
    rng = np.random.default_rng(1 + order)
    N = 60
    t = T * np.arange(1, N + 1)
    z = 250.0 - 4.0 * t + 0.3 * t**2 + 20.0 * rng.standard_normal(N)  # arbitrary data, not a polynomial
    m = cv(1, T) if order == 2 else ca(1, T)
    params = {"q": jnp.asarray(1.0), "r": jnp.asarray([400.0])}
    flt = model_alpha_beta(m, cartesian_1d(20.0), params, gains="growing_memory")
    deg = order - 1
    first = order  # k >= 2 (line), k >= 3 (parabola)
    for x0 in (np.zeros(order), np.array([-1e4, 300.0, -7.0][:order])):  # any prior
        x = np.asarray(tracklab.run_filter(flt, z[:, None], x0=x0, P0=np.eye(order) * 1e6, dt=T).x)
        for k in range(first, N + 1):
            ref = _ls_fit(t, z, k, deg)
            scale = np.array([np.max(np.abs(z)), np.max(np.abs(z)) / T, np.max(np.abs(z)) / T**2])[:order]
            err = np.abs(x[k - 1] - ref)
            assert np.all(err <= 1e-9 * (np.abs(ref) + scale)), (k, x0.tolist(), x[k - 1], ref)


def test_growing_memory_gain_formulas():
    k = np.arange(1, 40, dtype=float)
    a, b = (np.asarray(v) for v in growing_memory_alpha_beta(jnp.asarray(k)))
    np.testing.assert_allclose(a, 2 * (2 * k - 1) / (k * (k + 1)), rtol=1e-14)
    np.testing.assert_allclose(b, 6 / (k * (k + 1)), rtol=1e-14)
    a, b, g = (np.asarray(v) for v in growing_memory_alpha_beta_gamma(jnp.asarray(k)))
    den = k * (k + 1) * (k + 2)
    np.testing.assert_allclose(a, 3 * (3 * k**2 - 3 * k + 2) / den, rtol=1e-14)
    np.testing.assert_allclose(b, 18 * (2 * k - 1) / den, rtol=1e-14)
    np.testing.assert_allclose(g / 2, 60 / den, rtol=1e-14)  # acceleration gain 60/den /T² in the γ/(2T²) layout


# ---------------------------------------------------------------- 3. Monte-Carlo steady-state covariance


def _window_se(A, P, i, W, N):
    """Relative MC standard error of the window-averaged MSE of component i.

    Stationary errors e_k of the fixed-gain filter obey e_{k+1} = A e_k + (indep. noise),
    A = (I − K H) F, so Cov(e_{k+j}, e_k) = A^j P. For Gaussian errors
    Cov(e_j², e_k²) = 2 Cov(e_j, e_k)², so the mean over W steps and N runs of e²
    has variance (2 / (N W²)) Σ_{j,k} C_{|j−k|}².
    """
    c = np.array([(np.linalg.matrix_power(A, j) @ P)[i, i] for j in range(W)])
    tot = W * c[0] ** 2 + 2 * sum((W - j) * c[j] ** 2 for j in range(1, W))
    return np.sqrt(2 * tot / (N * W**2)) / P[i, i]


def test_monte_carlo_steady_state_covariance_matches_closed_form(tmp_path):
    """α-β only: the constant_velocity truth has DWNA noise, which is the α-β (not the α-β-γ) model."""
    sigma_v, sigma_w, T, runs, steps = 3.0, 100.0, 1.0, 4000, 200  # paper 002 §3: variances 9 and 10 000
    path = tmp_path / "ab_mc.toml"
    path.write_text(
        textwrap.dedent(
            f"""
            [experiment]
            name = "ab-steady-state"
            runs = {runs}
            seed = 11
            dt = {T}
            steps = {steps}

            [scenario]
            kind = "constant_velocity"
            initial = [10.0, 88.0]
            accel_sigma = {sigma_v}

            [sensor]
            kind = "cartesian"
            sigma = {sigma_w}

            [[filter]]
            kind = "alpha_beta"
            label = "ab"
            accel_sigma = {sigma_v}
            """
        )
    )
    exp = tracklab.load_experiment(path)
    res = exp.monte_carlo()
    stats = statistics(res, (100, 200))
    series = stats["filters"]["ab"]["series"]
    assert np.all(series["healthy_runs"] == runs)
    w = slice(99, 200)  # steps 100..200, 1-based inclusive
    mse_pos = np.mean(series["rmse_x"][w] ** 2)
    mse_vel = np.mean(series["rmse_vel"][w] ** 2)
    np.testing.assert_allclose(stats["filters"]["ab"]["summary"]["rmse_x"] ** 2, mse_pos, rtol=1e-12)

    lam = sigma_v * T**2 / sigma_w
    a, b = (float(v) for v in kalata_alpha_beta(jnp.asarray(lam)))
    p11 = a * sigma_w**2
    p22 = b * (2 * a - b) / (2 * (1 - a) * T**2) * sigma_w**2

    # Tolerance: the exact MC standard error of each window average (≈0.55 % here, from the
    # error autocovariance A^j P of the steady-state filter, see _window_se), times 4. The
    # prior transient (closed-loop pole ≈ 0.885) has decayed by ~1e-10 in variance by step 100.
    # 4 SE ≈ 2.2 % < 3 %: the test stays sharp enough to catch e.g. a β/T vs β or a factor-2 error.
    F = np.array([[1.0, T], [0.0, 1.0]])
    A = (np.eye(2) - np.outer([a, b / T], [1.0, 0.0])) @ F
    P = np.array([[p11, b / T * sigma_w**2], [b / T * sigma_w**2, p22]])
    se_pos = _window_se(A, P, 0, 101, runs)
    se_vel = _window_se(A, P, 1, 101, runs)
    assert 4 * max(se_pos, se_vel) < 0.03
    assert abs(mse_pos / p11 - 1) < 4 * se_pos, (mse_pos, p11, se_pos)
    assert abs(mse_vel / p22 - 1) < 4 * se_vel, (mse_vel, p22, se_vel)
    # the filter's own covariance is consistent: average NEES ≈ 2 (two states)
    nees = np.mean(series["nees"][w])
    assert abs(nees / 2 - 1) < 0.05, nees


# ---------------------------------------------------------------- 4. explicit gains; gradients


def _truth_and_data(T, n_steps, seed, sigma_v=3.0, sigma_w=100.0):
    rng = np.random.default_rng(seed)
    F, Gam = model_matrices(2, T)
    x = np.array([10.0, 88.0])
    truth = []
    for _ in range(n_steps):
        x = F @ x + Gam * sigma_v * rng.standard_normal()
        truth.append(x)
    truth = np.array(truth)
    z = truth[:, :1] + sigma_w * rng.standard_normal((n_steps, 1))
    return truth, z


@pytest.mark.parametrize("order", [2, 3])
def test_explicit_gains_equal_kalata_gains(order):
    T, lam = 0.5, 0.08
    truth, z = _truth_and_data(T, 150, seed=5)
    m = cv(1, T) if order == 2 else ca(1, T)
    base = {"q": jnp.asarray(9.0), "r": jnp.asarray([1e4])}
    fk = model_alpha_beta(m, cartesian_1d(100.0), {**base, "lam": jnp.asarray([lam])}, gains="kalata")
    kal = (kalata_alpha_beta if order == 2 else kalata_alpha_beta_gamma)(jnp.asarray(lam))
    names = ("alpha", "beta", "gamma")[:order]
    fe = model_alpha_beta(m, cartesian_1d(100.0), {**base, **dict(zip(names, kal))}, gains="explicit")
    x0, P0 = np.array([0.0, 80.0, 0.0][:order]), np.diag([1e4, 100.0, 1.0][:order])
    rk = tracklab.run_filter(fk, z, x0=x0, P0=P0, dt=T)
    re = tracklab.run_filter(fe, z, x0=x0, P0=P0, dt=T)
    np.testing.assert_allclose(np.asarray(re.x), np.asarray(rk.x), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(np.asarray(re.P), np.asarray(rk.P), rtol=1e-12, atol=1e-9)
    # and a different explicit gain does change the estimates (the gains are really used)
    fe2 = model_alpha_beta(m, cartesian_1d(100.0), {**base, **dict(zip(names, kal)), "alpha": kal[0] * 1.1}, gains="explicit")
    assert np.max(np.abs(np.asarray(tracklab.run_filter(fe2, z, x0=x0, P0=P0).x) - np.asarray(rk.x))) > 1e-3


def test_gradient_wrt_explicit_gains_matches_finite_difference():
    T = 1.0
    truth, z = _truth_and_data(T, 120, seed=9)
    m = cv(1, T)
    params = {"q": jnp.asarray(9.0), "r": jnp.asarray([1e4]), "alpha": jnp.asarray(0.3), "beta": jnp.asarray(0.05)}
    flt = model_alpha_beta(m, cartesian_1d(100.0), params, gains="explicit")
    x0, P0 = np.array([10.0, 88.0]), np.diag([1e4, 100.0])

    def loss(p):
        res = tracklab.run_filter(flt, z, x0=x0, P0=P0, params=p, dt=T)
        return jnp.sum((res.x[:, 0] - truth[:, 0]) ** 2)

    g = jax.grad(loss)(params)  # the gains are leaves of the params pytree
    assert set(g) == set(params)
    for name in ("alpha", "beta"):
        gv = float(g[name])
        assert np.isfinite(gv) and gv != 0.0
        h = 1e-6
        fd = (float(loss({**params, name: params[name] + h})) - float(loss({**params, name: params[name] - h}))) / (2 * h)
        np.testing.assert_allclose(gv, fd, rtol=1e-5, err_msg=name)


# ---------------------------------------------------------------- 5. growing memory with a Kalata floor (from a config)


def test_growing_memory_with_kalata_floor_from_config(tmp_path):
    T, sigma_v, sigma_w = 0.5, 3.0, 10.0
    path = tmp_path / "floor.toml"
    path.write_text(
        textwrap.dedent(
            f"""
            [experiment]
            name = "floor"
            runs = 1
            dt = {T}
            steps = 300

            [scenario]
            kind = "constant_velocity"
            initial = [10.0, 88.0]
            accel_sigma = {sigma_v}

            [sensor]
            kind = "cartesian"
            sigma = {sigma_w}

            [[filter]]
            kind = "alpha_beta"
            label = "gm"
            gains = "growing_memory"
            floor = "kalata"

            [[filter]]
            kind = "alpha_beta"
            label = "kalata"
            """
        )
    )
    specs = {s.label: s for s in tracklab.load_experiment(path).filter_specs()}
    gm, kal = specs["gm"].filter, specs["kalata"].filter
    lam = sigma_v * T**2 / sigma_w
    np.testing.assert_allclose(np.asarray(gm.params["lam"]), [lam], rtol=1e-14)

    truth, z = _truth_and_data(T, 300, seed=3, sigma_v=sigma_v, sigma_w=sigma_w)
    x0, P0 = np.array([0.0, 0.0]), np.diag([1e4, 1e4])
    r = tracklab.run_filter(gm, z, x0=x0, P0=P0, dt=T)
    x, xp, nu = np.asarray(r.x), np.asarray(r.x_pred), np.asarray(r.nu)[:, 0]

    # the gain applied at the k-th measurement is max(growing-memory gain, Kalata gain), per gain
    k = np.arange(1, 301, dtype=float)
    ga, gb = (np.asarray(v) for v in growing_memory_alpha_beta(jnp.asarray(k)))
    ka, kb = (float(v) for v in kalata_alpha_beta(jnp.asarray(lam)))
    K = np.stack([np.maximum(ga, ka), np.maximum(gb, kb) / T], axis=-1)
    np.testing.assert_allclose(x, xp + K * nu[:, None], rtol=1e-12, atol=1e-9)
    switch = int(np.max(np.flatnonzero((ga > ka) | (gb > kb)))) + 1  # last growing-memory step
    assert 5 < switch < 100  # the schedule really is exercised on both sides
    np.testing.assert_allclose(K[switch:], np.broadcast_to([ka, kb / T], K[switch:].shape), rtol=1e-14)

    # after the switch both filters run the same recursion, so their estimates converge
    rk = tracklab.run_filter(kal, z, x0=x0, P0=P0, dt=T)
    d = np.abs(x - np.asarray(rk.x))
    assert np.max(d[:switch]) > 1.0  # different early on
    assert np.max(d[-50:]) < 1e-8


# ---------------------------------------------------------------- 6. missed measurements


@pytest.mark.parametrize("order", [2, 3])
def test_nan_rows_are_predict_only_and_do_not_advance_the_counter(order):
    T = 0.5
    rng = np.random.default_rng(17)
    N = 40
    z = (50.0 + 20.0 * rng.standard_normal(N))[:, None]
    missing = np.zeros(N, bool)
    missing[[0, 4, 5, 6, 13, 25, 39]] = True
    z[missing] = np.nan
    m = cv(1, T) if order == 2 else ca(1, T)
    params = {"q": jnp.asarray(2.0), "r": jnp.asarray([400.0])}
    flt = model_alpha_beta(m, cartesian_1d(20.0), params, gains="growing_memory")
    x0 = np.array([3.0, -1.0, 0.2][:order])
    P0 = np.eye(order) * 50.0
    r = tracklab.run_filter(flt, z, x0=x0, P0=P0, dt=T)
    x, P, xp, nu = (np.asarray(a) for a in (r.x, r.P, r.x_pred, r.nu))
    F, Gam = model_matrices(order, T)
    Q = 2.0 * np.outer(Gam, Gam)

    np.testing.assert_array_equal(np.asarray(r.valid), ~missing)
    prev_x, prev_P = x0, P0
    for i in range(N):
        np.testing.assert_allclose(xp[i], F @ prev_x, rtol=1e-13, atol=1e-12)
        if missing[i]:
            np.testing.assert_allclose(x[i], F @ prev_x, rtol=1e-13, atol=1e-12)
            np.testing.assert_allclose(P[i], F @ prev_P @ F.T + Q, rtol=1e-12)
        prev_x, prev_P = x[i], P[i]

    # the gain at each update is the growing-memory gain for the number of measurements processed
    n_meas = np.cumsum(~missing).astype(float)
    sched = growing_memory_alpha_beta if order == 2 else growing_memory_alpha_beta_gamma
    gains = [np.asarray(v) for v in sched(jnp.asarray(n_meas))]
    K = np.stack([g * s for g, s in zip(gains, [1.0, 1.0 / T, 1.0 / (2 * T**2)])], axis=-1)
    upd = ~missing
    np.testing.assert_allclose(x[upd], xp[upd] + K[upd] * nu[upd, :1], rtol=1e-12, atol=1e-9)

    # the covariance of that fixed-gain update: Joseph form (I − KH) M (I − KH)ᵀ + K R Kᵀ, with the
    # gain actually used (not the optimal one, so the short form (I − KH) M would differ here)
    H = np.eye(1, order)
    prev_P = P0
    for i in range(N):
        M = F @ prev_P @ F.T + Q
        if upd[i]:
            IKH = np.eye(order) - np.outer(K[i], H)
            ref = IKH @ M @ IKH.T + 400.0 * np.outer(K[i], K[i])
        else:
            ref = M
        np.testing.assert_allclose(P[i], ref, rtol=1e-10, atol=1e-10 * np.max(np.abs(ref)), err_msg=f"step {i}")
        prev_P = ref

    # the counter itself, stepping the filter by hand
    s = flt.init(params, Prior(jnp.asarray(x0), jnp.asarray(P0)))
    assert isinstance(s, ABState)
    for i in range(N):
        s, _ = flt.step(params, s, Meas(jnp.asarray(z[i]), jnp.asarray(T * (i + 1)), jnp.asarray(True)))
        assert float(s.k) == n_meas[i]
