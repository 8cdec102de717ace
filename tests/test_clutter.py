"""Tracking in clutter: the cluttered sensor's scans, the association filters against NumPy
references written from the papers' equations, and the statistics of track loss."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab.filters import Meas, Prior, ipda, kf, nearest_neighbour, pdaf
from tracklab.filters.association import chi2_gate, gate_probability
from tracklab.sensors import Cluttered, Sensor
from tracklab.sensors.clutter import information_reduction_factor, poisson_count

DT = 1.0
F = np.array([[1, DT, 0, 0], [0, 1, 0, 0], [0, 0, 1, DT], [0, 0, 0, 1.0]])
H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
Q = 0.5**2 * np.kron(np.eye(2), np.array([[DT**4 / 4, DT**3 / 2], [DT**3 / 2, DT**2]]))
R = 5.0**2 * np.eye(2)


def _scans(sensor, steps, seed, truth):
    """The sensor's scans of a truth sequence (steps, 2) from one key."""
    with jax.enable_x64(True):
        return np.asarray(sensor.measure(jax.random.key(seed), jnp.asarray(truth)))


def _truth(steps):
    k = np.arange(1, steps + 1)
    return np.stack([10.0 * k, 5.0 * k], axis=1)


def test_poisson_count_inverts_the_distribution_function():
    with jax.enable_x64(True):
        for mean in (0.0, 0.3, 3.0, 12.0):
            pk = np.array([math.exp(-mean) * mean**k / math.factorial(k) for k in range(9)])
            cdf = np.cumsum(pk)
            for u in (0.0005, 0.2, 0.5, 0.9, 0.9999):
                n = int(poisson_count(jnp.asarray(u), jnp.asarray(mean), 8))
                assert n == int(np.sum(u > cdf)), (mean, u)


def test_scan_false_alarm_count_and_positions_follow_their_laws():
    """The number of returns per scan: Poisson (χ² goodness of fit, 10 000 scans); the false
    alarms uniform over their window (mean and variance); the detection among them."""
    lam_v = 3.0
    half = (60.0, 40.0)
    sensor = Cluttered(Sensor("cartesian", 2, (5.0, 5.0), 1.0, dt=DT), lam_v / (4 * 60.0 * 40.0), half, None, 16)
    steps = 10_000
    truth = np.zeros((steps, 2))
    scans = _scans(sensor, steps, 1, truth)
    returns = np.all(np.isfinite(scans), axis=-1)
    n_false = returns.sum(axis=1) - 1  # p_detect = 1: one return is the target's
    counts = np.bincount(n_false, minlength=9)[:9].astype(float)
    counts[8] = np.sum(n_false >= 8)
    p = np.array([math.exp(-lam_v) * lam_v**k / math.factorial(k) for k in range(8)])
    p = np.append(p, 1 - p.sum())
    chi2 = float(np.sum((counts - steps * p) ** 2 / (steps * p)))
    assert chi2 < 26.1, chi2  # χ²₈ at 0.999
    pts = scans[returns]
    far = np.any(np.abs(pts) > 4 * 5.0, axis=1)  # leave out the target's return (σ = 5)
    clutter = pts[far]
    assert np.all(np.abs(clutter) <= np.array(half) + 1e-9)
    # uniform on the window minus the target's neighbourhood: check the variance on the far part
    assert abs(np.mean(clutter[:, 0])) < 3.0 and abs(np.mean(clutter[:, 1])) < 2.0
    # the target's return sits at any row of the scan, not at a fixed one
    near = np.all(np.abs(scans) < 4 * 5.0, axis=-1)  # (steps, rows)
    rows = np.argmax(near, axis=1)[near.any(axis=1)]
    assert len(np.unique(rows)) == 16 and np.max(np.bincount(rows)) < 0.1 * len(rows)


def _numpy_pdaf(zs, x0, P0, gate, pd, lam, *, rule="pdaf", p_survive=0.98, psi0=0.9):
    """The PDAF (Bar-Shalom, Daum & Huang 2009, parametric clutter), the nearest neighbour and the
    IPDA's existence (Mušicki et al. 1994) for a linear model, from their equations."""
    x, P, psi = x0.copy(), P0.copy(), psi0
    m = H.shape[0]
    pg = float(gate_probability(gate, m))
    xs, Ps, psis, gated = [], [], [], []
    for Z in zs:
        xp, Pp = F @ x, F @ P @ F.T + Q
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        Z = Z[np.all(np.isfinite(Z), axis=1)]
        nus = Z - H @ xp
        d2 = np.einsum("ki,ij,kj->k", nus, np.linalg.inv(S), nus)
        nus = nus[d2 <= gate]
        d2 = d2[d2 <= gate]
        gated.append(len(nus))
        if rule == "nn":
            if len(nus):
                nu = nus[np.argmin(d2)]
                x, P = xp + K @ nu, Pp - K @ S @ K.T
            else:
                x, P = xp, Pp
        else:
            L = pd * np.exp(-0.5 * d2) / math.sqrt(np.linalg.det(2 * np.pi * S)) / lam
            denom = 1 - pd * pg + L.sum()
            b0, b = (1 - pd * pg) / denom, L / denom
            nu = b @ nus if len(nus) else np.zeros(m)
            spread = np.einsum("k,ki,kj->ij", b, nus, nus) - np.outer(nu, nu) if len(nus) else np.zeros((m, m))
            x = xp + K @ nu
            P = b0 * Pp + (1 - b0) * (Pp - K @ S @ K.T) + K @ spread @ K.T
            psi_p = p_survive * psi
            delta = pd * pg - L.sum()
            psi = (1 - delta) * psi_p / (1 - delta * psi_p)
        xs.append(x)
        Ps.append(P)
        psis.append(psi)
    return np.array(xs), np.array(Ps), np.array(psis), np.array(gated)


def _run(flt, zs, x0, P0):
    with jax.enable_x64(True):
        step = jax.jit(flt.step)
        state = flt.init(flt.params, Prior(jnp.asarray(x0), jnp.asarray(P0)))
        xs, Ps, aux = [], [], []
        for k, Z in enumerate(zs):
            state, out = step(flt.params, state, Meas(jnp.asarray(Z), jnp.asarray((k + 1) * DT), jnp.asarray(True)))
            xs.append(np.asarray(out.x))
            Ps.append(np.asarray(out.P))
            aux.append(None if out.aux is None else float(out.aux["existence"]))
    return np.array(xs), np.array(Ps), aux


@pytest.mark.parametrize("rule", ["pdaf", "nn", "ipda"])
def test_association_against_numpy_reference_on_the_same_returns(rule):
    steps = 40
    lam = 4.0 / (4 * 80.0 * 80.0)
    sensor = Cluttered(Sensor("cartesian", 2, (5.0, 5.0), 0.8, dt=DT), lam, (80.0, 80.0), None, 16)
    zs = _scans(sensor, steps, 7, _truth(steps))
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([25.0, 4.0, 25.0, 4.0])
    gate = chi2_gate(0.99, 2)
    with jax.enable_x64(True):
        base = kf(F, H, Q, R)
        flt = {"pdaf": lambda: pdaf(base, 2, clutter_density=lam, p_detect=0.8, gate=gate),
               "nn": lambda: nearest_neighbour(base, 2, gate=gate),
               "ipda": lambda: ipda(base, 2, clutter_density=lam, p_detect=0.8, gate=gate)}[rule]()
    xs, Ps, psi = _run(flt, zs, x0, P0)
    rx, rP, rpsi, gated = _numpy_pdaf(zs, x0, P0, gate, 0.8, lam, rule=rule)
    np.testing.assert_allclose(xs, rx, rtol=1e-9, atol=1e-7)
    np.testing.assert_allclose(Ps, rP, rtol=1e-8, atol=1e-7)
    if rule == "ipda":
        np.testing.assert_allclose(psi, rpsi, rtol=1e-9)
    # the association mattered: steps with several returns in the gate, and with none
    assert np.max(gated) >= 2 and np.min(gated) == 0, gated


def test_pdaf_without_clutter_and_with_certain_detection_is_its_base_filter():
    steps = 30
    sensor = Sensor("cartesian", 2, (5.0, 5.0), 1.0, dt=DT)
    with jax.enable_x64(True):
        zs = np.asarray(sensor.measure(jax.random.key(3), jnp.asarray(_truth(steps))))
        base = kf(F, H, Q, R)
        flt = pdaf(base, 2, clutter_density=1e-300, p_detect=1.0, gate=1e4)
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([25.0, 4.0, 25.0, 4.0])
    xs, Ps, _ = _run(flt, zs, x0, P0)
    bx, bP, _ = _run(base, zs, x0, P0)
    np.testing.assert_allclose(xs, bx, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(Ps, bP, rtol=1e-12, atol=1e-9)


def test_information_reduction_factor_limits():
    """q = P_D without clutter; it falls as the clutter grows and never passes P_D."""
    for pd in (0.5, 0.9, 1.0):
        q0 = information_reduction_factor(0.0, pd, (10.0, 10.0), 64, scans=100_000)
        assert abs(q0 - pd) < 0.02 * pd, (pd, q0)
    qs = [information_reduction_factor(lam, 0.9, (10.0, 10.0), 64, scans=50_000) for lam in (0.001, 0.01, 0.05)]
    assert qs[0] > qs[1] > qs[2] > 0.0
    assert qs[0] <= 0.9 + 0.02
