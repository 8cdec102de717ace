"""Paper 001: the boresight model's kinematics, the EKF's consistency, the classical loop, the experiment."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tracklab  # noqa: F401  (64-bit mode)
from tracklab.worlds.airborne.boresight import ModelParams, antenna_motion, drift, los_frame, los_state, rotate
from tracklab.worlds.airborne.cd_ekf import CDParams, cd_ekf
from tracklab.worlds.airborne.classical import ClassicalParams, classical, crossover, loop_gains, open_loop
from tracklab.worlds.airborne.decoupled import channel_matrices, van_loan
from tracklab.worlds.airborne.engagement import Engagement, singer_block
from tracklab.worlds.airborne.tracker import Timing
from tracklab.config import load_experiment
from tracklab.montecarlo.statistics import average_chi2_interval


def _geometry(eng, t):
    p_t, v_t, a_t = eng.target(t)
    p_m, v_m, a_m = eng.own(t)
    return p_t - p_m, v_t - v_m, a_t, a_m


@pytest.mark.parametrize("t0", [5.0, 25.0, 33.0])  # straight flight, inside the 4 g turn, after it
def test_los_kinematics_match_finite_differences(t0):
    """The model's ε, ω, r, ṙ rows against 5-point differences of the simulated geometry (docs/mathematics.md §1).

    The antenna is on the LOS at t0 and turns at fixed rates (ω_Ae, ω_Ad); the
    true state is read off the geometry at t0 ± h, ± 2h.
    """
    eng = Engagement()
    rel_p0 = _geometry(eng, t0)[0]
    C0 = los_frame(rel_p0)
    w_a = jnp.array([0.03, -0.02])  # rad/s about e (z_A) and d (y_A)

    def state(t):
        rel_p, rel_v, a_t, a_m = _geometry(eng, t)
        C = rotate(C0, jnp.stack([0.0, w_a[1], w_a[0]]) * (t - t0))
        return los_state(rel_p, rel_v, a_t, a_m, C)

    h = 1e-3
    xs = [state(t0 + k * h)[0] for k in (-2, -1, 1, 2)]
    fd = (xs[0] - 8 * xs[1] + 8 * xs[2] - xs[3]) / (12 * h)
    x, a_m = state(t0)
    model = drift(x, w_a, a_m, ModelParams(*(jnp.asarray(v) for v in (30.0, 10.0, 30.0, 10.0))))
    rows = np.array([0, 1, 3, 4, 6, 7])  # ε_e, ω_e, ε_d, ω_d, r, ṙ (a's are the Singer model's own)
    scale = np.abs(np.asarray(fd)[rows]) + 1e-6 * np.array([1e-3, 1e-3, 1e-3, 1e-3, 300.0, 1.0])
    np.testing.assert_array_less(np.abs(np.asarray(model - fd)[rows]) / scale, 1e-6)


def test_inertial_los_identities():
    """ω̇ = −2(ṙ/r)ω + u×a/r and r̈ = r|ω|² + u·a, the vector relations the model rests on."""
    eng = Engagement()
    t0, h = 24.0, 1e-3

    def omega_r(t):
        rel_p, rel_v, a_t, a_m = _geometry(eng, t)
        r = jnp.linalg.norm(rel_p)
        u = rel_p / r
        return jnp.cross(u, rel_v) / r, jnp.dot(u, rel_v)

    w = [omega_r(t0 + k * h) for k in (-2, -1, 1, 2)]
    d = lambda i: (w[0][i] - 8 * w[1][i] + 8 * w[2][i] - w[3][i]) / (12 * h)
    rel_p, rel_v, a_t, a_m = _geometry(eng, t0)
    r = np.linalg.norm(rel_p)
    u = rel_p / r
    omega, rdot = omega_r(t0)
    a = a_t - a_m
    np.testing.assert_allclose(d(0), -2 * rdot / r * omega + np.cross(u, a) / r, rtol=1e-6)
    np.testing.assert_allclose(d(1), r * np.dot(omega, omega) + np.dot(u, a), rtol=1e-6)


def test_singer_block_matches_closed_form():
    """Van Loan against docs/mathematics.md §1's closed forms where they are well conditioned."""
    for T, tau, sigma in ((1.0, 10.0, 30.0), (0.5, 2.0, 5.0)):
        a = 1 / tau
        e, e2 = math.exp(-a * T), math.exp(-2 * a * T)
        q = 2 * a * sigma**2
        Q = q * np.array([
            [(1 - e2 + 2 * a * T + 2 * a**3 * T**3 / 3 - 2 * a**2 * T**2 - 4 * a * T * e) / (2 * a**5),
             (e2 + 1 - 2 * e + 2 * a * T * e - 2 * a * T + a**2 * T**2) / (2 * a**4), (1 - e2 - 2 * a * T * e) / (2 * a**3)],
            [0.0, (4 * e - 3 - e2 + 2 * a * T) / (2 * a**3), (e2 + 1 - 2 * e) / (2 * a**2)],
            [0.0, 0.0, (1 - e2) / (2 * a)]])
        Q = np.triu(Q) + np.triu(Q, 1).T
        phi = np.array([[1, T, (a * T - 1 + e) / a**2], [0, 1, (1 - e) / a], [0, 0, e]])
        phi_vl, Q_vl = singer_block(T, tau, sigma)
        np.testing.assert_allclose(phi_vl, phi, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(Q_vl, Q, rtol=1e-9)


def test_decoupled_range_channel_is_a_singer_block():
    """With no LOS rate the decoupled range channel's Van Loan discretisation is the Singer block."""
    x = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 8000.0, -300.0, 0.0])
    mp = ModelParams(*(jnp.asarray(v) for v in (30.0, 10.0, 20.0, 5.0)))
    blocks = van_loan(channel_matrices(x, mp, separate=False), 0.05)  # elevation, azimuth, range
    phi, gam, Qd, phi_inv = blocks[2]
    phi_s, Q_s = singer_block(0.05, 5.0, 20.0)
    np.testing.assert_allclose(np.asarray(phi), phi_s, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(np.asarray(Qd), Q_s, rtol=1e-8)
    for phi, gam, _, phi_inv in blocks:
        np.testing.assert_allclose(np.asarray(gam), 0.0, atol=1e-15)
        np.testing.assert_allclose(np.asarray(phi_inv) @ np.asarray(phi), np.eye(3), atol=1e-12)


def test_cd_ekf_tick_integrates_mean_covariance_and_the_transitions_tangent():
    """One RK4 tick of the joint EKF against a plain RK4 written here: the mean, the covariance
    (dP/dt = F P + P Fᵀ + G Q Gᵀ with F the full Jacobian), and the transition's columns, which
    must be the Jacobian ∂x(t+dt)/∂(x, u) of the mean's RK4 step (jax.jacfwd of it)."""
    from tracklab.worlds.airborne.boresight import antenna_rate_at, process_noise
    from tracklab.worlds.airborne.cd_ekf import rk4_tick

    rng = np.random.default_rng(3)
    x = jnp.array([2e-3, 0.05, 20.0, -1e-3, -0.03, -15.0, 8000.0, -300.0, 5.0])
    A = rng.normal(size=(9, 9))
    P = jnp.asarray(A @ A.T * 1e-2 + np.eye(9))
    u = jnp.array([3.0, -2.0, 1.0])
    M0, G0 = jnp.asarray(np.eye(9) + 0.1 * rng.normal(size=(9, 9))), jnp.asarray(rng.normal(size=(9, 3)))
    w0, cmd, dt, lag = jnp.array([0.04, -0.02]), jnp.array([0.06, -0.01]), 0.01, 0.05
    mp = ModelParams(*(jnp.asarray(v) for v in (30.0, 2.0, 20.0, 5.0)))
    a_m = jnp.zeros(3)

    def rk4(f, y, h):
        k1 = f(0.0, y)
        k2 = f(h / 2, y + h / 2 * k1)
        k3 = f(h / 2, y + h / 2 * k2)
        k4 = f(h, y + h * k3)
        return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    f = lambda s, y, v: drift(y, antenna_rate_at(w0, cmd, s, lag), a_m, mp, v)
    mean = lambda y, v: rk4(lambda s, z: f(s, z, v), y, dt)

    def pair(s, y):
        z, Pz = y[:9], y[9:].reshape(9, 9)
        F = jax.jacfwd(f, argnums=1)(s, z, u)
        return jnp.concatenate([f(s, z, u), jnp.ravel(F @ Pz + Pz @ F.T + process_noise(mp))])

    ref = rk4(pair, jnp.concatenate([x, jnp.ravel(P)]), dt)
    Jx, Ju = jax.jacfwd(mean, argnums=(0, 1))(x, u)
    x1, P1, M1, G1 = rk4_tick(x, P, w0, cmd, dt, lag, mp, u, M0, G0)
    np.testing.assert_allclose(x1, ref[:9], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(P1, ref[9:].reshape(9, 9), rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(M1, Jx @ M0, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(G1, Jx @ G0 + Ju, rtol=1e-11, atol=1e-12)
    x2, P2, M2, G2 = rk4_tick(x, P, w0, cmd, dt, lag, mp, None, M0)  # no mean levels: u = 0, no G
    np.testing.assert_allclose(M2, jax.jacfwd(mean)(x, jnp.zeros(3)) @ M0, rtol=1e-11, atol=1e-12)
    assert G2 is None


def test_classical_loop_matches_continuous_closed_loop():
    """The sampled angle loop (the tracker's own compensator and the antenna) against G/(1+G), eq. 17.

    A sinusoidal LOS angle drives one channel; the boresight's steady response,
    fitted by least squares, matches the continuous closed loop within 1 % at
    every frequency below the crossover.
    """
    tm = Timing(0.01, 5, 0.02)
    G = open_loop()
    wc = crossover(G)
    assert 6.0 < wc < 6.5
    tr = classical(tm)
    p = ClassicalParams(jnp.ones(4), *loop_gains(30.0, 10.0, 10.0, 1.0, tm))

    @jax.jit
    def boresight(w):
        n = 6000
        s = tr.start(p, jnp.zeros(9).at[6].set(1e4), jnp.eye(9))

        def step(c, j):
            s, th_a, wa = c
            i = j % tm.n
            cmd, _ = tr.tick(p, s, i)
            wa, turn = antenna_motion(wa, cmd, tm.dt, tm.lag)
            th_a = th_a + turn
            los = jnp.stack([jnp.sin(w * (j + 1) * tm.dt), 0.0])
            s = tr.sample(p, s, i, jnp.concatenate([los - th_a, jnp.zeros(2)]))
            s = jax.lax.cond(i == tm.n - 1, lambda s: tr.update(p, s, wa), lambda s: s, s)
            return (s, th_a, wa), th_a[0]

        return jax.lax.scan(step, (s, jnp.zeros(2), jnp.zeros(2)), jnp.arange(n))[1]

    t = tm.dt * np.arange(1, 6001)
    for w in (0.5, 1.0, 2.0, 4.0, 0.95 * wc):
        y = np.asarray(boresight(w))
        late = t > 30.0
        B = np.stack([np.sin(w * t), np.cos(w * t)], -1)[late]
        a, b = np.linalg.lstsq(B, y[late], rcond=None)[0]
        Gw = G(1j * w)
        T = Gw / (1 + Gw)
        assert abs((a + 1j * b) - T) / abs(T) < 0.01, w


def _model_truth_nees(runs=300, periods=160):
    """NEES of the joint EKF when the truth is the model itself (the 9-state SDE, fine steps)."""
    tm = Timing(0.01, 5, 0.02)
    mp = ModelParams(*(jnp.asarray(v) for v in (30.0, 10.0, 30.0, 10.0)))
    sigma = jnp.array([1e-3, 1e-3, 10.0, 1.0])
    params = CDParams(mp, sigma**2, jnp.ones(4), jnp.asarray(5.0))
    tr = cd_ekf(tm)
    sub = 10  # truth substeps per radar sample
    h = tm.dt / sub
    decay = jnp.exp(-h / 10.0)
    a_sd = 30.0 * jnp.sqrt(1 - decay**2)
    P0 = jnp.diag(jnp.array([3e-3, 2e-3, 30.0, 3e-3, 2e-3, 30.0, 30.0, 3.0, 30.0]) ** 2)
    acc = jnp.array([2, 5, 8])
    x_mean = jnp.array([0.0, 0.01, 0.0, 0.0, -0.005, 0.0, 10_000.0, -300.0, 0.0])

    def run(key):
        k0, k1 = jax.random.split(key)
        x = x_mean + jnp.sqrt(jnp.diag(P0)) * jax.random.normal(k0, (9,))
        s = tr.start(params, x_mean, P0)

        def tick(c, inp):
            s, x, w = c
            i, key = inp
            cmd, gates = tr.tick(params, s, i)
            ka, kz = jax.random.split(key)
            xi = jax.random.normal(ka, (sub, 3))

            def fine(c, xi):
                x, w = c
                w_mid, _ = antenna_motion(w, cmd, h / 2, tm.lag)  # the exact lag, at the substep's midpoint
                a = x[acc]
                x = x + h * drift(x, w_mid, jnp.zeros(3), mp)  # Euler for ε, ω, r, ṙ
                x = x.at[acc].set(a * decay + a_sd * xi)  # the Singer accelerations exactly
                w, _ = antenna_motion(w, cmd, h, tm.lag)
                return (x, w), None

            (x, w), _ = jax.lax.scan(fine, (x, w), xi)
            z = jnp.stack([x[0], x[3], x[6] - gates[0], x[7] - gates[1]]) + sigma * jax.random.normal(kz, (4,))
            return (tr.sample(params, s, i, z), x, w), None

        def period(c, key):
            s, x, w = c
            (s, x, w), _ = jax.lax.scan(tick, (s, x, w), (jnp.arange(tm.n), jax.random.split(key, tm.n)))
            s = tr.update(params, s, w)
            x_hat, P = tr.estimate(s)
            e = x_hat - x
            return (s, x, w), e @ jnp.linalg.solve(P, e)

        return jax.lax.scan(period, (s, x, jnp.zeros(2)), jax.random.split(k1, periods))[1]

    return np.asarray(jax.jit(jax.vmap(run))(jax.random.split(jax.random.key(7), runs)))


def test_cd_ekf_nees_in_chi2_band_with_the_true_model():
    """Truth from the model's own SDE (Euler at 1 ms, exact Singer accelerations): NEES inside its χ² band."""
    nees = _model_truth_nees()
    runs, periods = nees.shape
    avg = nees.mean(axis=0)
    lo, hi = average_chi2_interval(9, runs)
    inside = np.mean((avg >= lo) & (avg <= hi))
    assert inside >= 0.9, (inside, avg.min(), avg.max())
    lo_all, hi_all = average_chi2_interval(9, runs * periods)
    # the periods are correlated, so the overall mean gets the per-period band, not the tighter one
    assert lo <= nees.mean() <= hi, (nees.mean(), lo, hi, lo_all, hi_all)


EXPERIMENT = """
[experiment]
name = "airborne_small"
runs = 12
seed = 3
chunk = 12

[airborne]
duration = 8.0

[disturbance]
time = 5.0
pointing = 8.0

[[tracker]]
label = "joint"
kind = "cd_ekf"

[[tracker]]
label = "decoupled"
kind = "decoupled"

[[tracker]]
label = "classical"
kind = "classical"

[report.windows]
acquisition = [0.0, 2.0]
steady = [2.5, 4.5]
disturbance = [5.0, 7.0]
"""


def test_airborne_experiment_writes_results_and_float32_agrees(tmp_path):
    path = tmp_path / "airborne_small.toml"
    path.write_text(EXPERIMENT)
    exp = load_experiment(path)
    doc = exp.run(out=tmp_path / "out", figures=False)
    # six quantities, two paired differences, the percentiles, settling and lock
    assert (tmp_path / "out" / "table.md").read_text().count("| joint |") == 10
    joint, dec, cls = (doc["filters"][k]["summary"] for k in ("joint", "decoupled", "classical"))
    hw = doc["filters"]["decoupled"]["half_width"]
    assert 0 < hw["pointing[steady]"] < joint["pointing[steady]"] and np.isfinite(hw["nees[steady]"])
    assert doc["filters"]["decoupled"]["paired"]["baseline"] == "joint"
    assert joint["pointing_p50[steady]"] <= joint["pointing_p90[steady]"] <= joint["pointing_p99[steady]"]
    for s in (joint, dec, cls):
        assert s["lost_lock"] == 0
    # the filters' pointing errors in steady state are well below the single-sample noise (1 mrad)
    assert joint["pointing[steady]"] < 0.6 and dec["pointing[steady]"] < 0.6
    # the jolt is seen by every tracker
    assert joint["pointing[disturbance]"] > 2 * joint["pointing[steady]"]
    head, windows = EXPERIMENT.split("[[tracker]]")[0], EXPERIMENT[EXPERIMENT.index("[report.windows]"):]
    path.write_text(head + '[[tracker]]\nlabel = "joint"\nkind = "cd_ekf"\n\n' + windows)
    doc32 = load_experiment(path).run(out=tmp_path / "out32", figures=False, precision="float32")
    for label in ("joint",):
        a, b = doc["filters"][label]["summary"], doc32["filters"][label]["summary"]
        for key in ("pointing[steady]", "los_rate[steady]", "range[steady]", "range_rate[steady]"):
            assert b[key] == pytest.approx(a[key], rel=0.01), (label, key)  # the same draws: arithmetic only


def test_moose_that_cannot_switch_is_the_joint_ekf():
    """With p_stay = 1 the bank keeps its initial zero level: Moose's shifts and spread vanish and it is the joint EKF.

    (The merged level of a bank that can switch is pulled by every level with any probability, so an
    absurd level is not harmless: it must be impossible.)"""
    from tracklab.worlds.airborne.moose import MooseParams, moose

    tm = Timing(0.01, 5, 0.02)
    mp = ModelParams(*(jnp.asarray(v) for v in (30.0, 10.0, 30.0, 10.0)))
    base = CDParams(mp, jnp.array([1e-6, 1e-6, 100.0, 1.0]), jnp.ones(4), jnp.asarray(5.0))
    mparams = MooseParams(base, jnp.array([-40.0, 0.0, 40.0]), jnp.asarray(1.0))
    x0 = jnp.array([1e-3, 0.01, 0.0, -2e-3, -0.005, 0.0, 10_000.0, -300.0, 0.0])
    P0 = jnp.diag(jnp.array([3e-3, 2e-3, 30.0, 3e-3, 2e-3, 30.0, 30.0, 3.0, 30.0]) ** 2)
    z = 1e-3 * jax.random.normal(jax.random.key(0), (3, tm.n, 4)) * jnp.array([1.0, 1.0, 1e4, 1e3])

    def run(tr, params):
        def period(s, zs):
            for i in range(tm.n):
                s = tr.sample(params, s, i, zs[i])
            s = tr.update(params, s, jnp.array([0.01, -0.004]))
            return s, tr.estimate(s)

        return jax.lax.scan(period, tr.start(params, x0, P0), z)[1]

    (xe, Pe), (xm, Pm) = jax.jit(lambda: (run(cd_ekf(tm), base), run(moose(tm), mparams)))()
    np.testing.assert_allclose(np.asarray(xm), np.asarray(xe), rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(np.asarray(Pm), np.asarray(Pe), rtol=1e-10, atol=1e-16)


def test_the_fusion_emitters_are_on_when_trackers_share_their_code():
    """Each bundled airborne file's programs compile with XLA's fusion emitters on exactly when
    two of its trackers have the same kind and range-velocity channel (``world.compiler_options``)."""
    from pathlib import Path

    from tracklab.worlds.airborne.world import compiler_options

    on = (("xla_cpu_use_fusion_emitters", True),)
    found = {}
    for path in sorted((Path(__file__).resolve().parents[1] / "experiments").glob("airborne_radar*.toml")):
        found[path.stem] = compiler_options(load_experiment(path).structure()) == on
    assert found == {"airborne_radar": False, "airborne_radar_lambda": True, "airborne_radar_mismatch": True,
                     "airborne_radar_moose": True, "airborne_radar_range": False}
