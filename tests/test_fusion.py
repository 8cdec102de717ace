"""Laser + infrared time registration and angle fusion (paper 002 §2.2–2.3, eqs. 19–21)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab.filters.fusion import LaserIrFusion, Select, fuse_angles, register, registration_weights
from tracklab.sensors import Sensor, SensorSuite, epochs
from tracklab.sensors.geometry import wrap


def angdiff(a, b):
    """a − b wrapped to (−π, π], in NumPy."""
    return np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))


# ---------------------------------------------------------------- 7. registration onto its own epochs


@pytest.mark.parametrize("method", ["interpolate", "none"])
def test_registration_onto_own_epochs_is_identity(method):
    dt, T = 0.001, 400
    s = Sensor("spherical", 3, (5.0, 0.02, 0.02), name="laser", dt=dt, period=0.02, offset=0.007)
    t = dt * np.arange(1, T + 1)
    # a target whose azimuth sweeps through ±π (x < 0, y changes sign) and whose
    # measurements therefore take values on both sides of the cut
    pos = jnp.asarray(np.stack([-3000.0 + 0 * t, 40.0 - 100.0 * t, 200.0 + 0 * t], axis=-1))
    z = s.measure(jax.random.key(3), pos)
    mask = s.report_mask(T)
    zr = register(z, mask, mask, s.angle_mask, method)
    zn, zrn = np.asarray(z), np.asarray(zr)
    np.testing.assert_array_equal(np.isnan(zrn), np.isnan(zn))
    np.testing.assert_array_equal(zrn[mask], zn[mask])  # exactly
    az = zn[mask, 1]
    assert np.any(az > 3.1) and np.any(az < -3.1)  # both sides of ±π were exercised
    a, b, w = registration_weights(mask, mask, method)
    np.testing.assert_array_equal(a[mask], np.flatnonzero(mask))
    np.testing.assert_array_equal(w[mask], 0.0)


# ---------------------------------------------------------------- 8. interpolation, extrapolation, "none"


def _masks(T, dt):
    src = epochs(T, dt, 7 * dt, 5 * dt)  # steps 5, 12, 19, …
    tgt = epochs(T, dt, 3 * dt, 1 * dt)  # steps 1, 4, 7, …: before the first and after the last source epoch
    return src, tgt


def test_interpolation_is_exact_for_a_linear_signal():
    dt, T = 0.001, 64
    src, tgt = _masks(T, dt)
    k = np.flatnonzero(src) + 1
    assert k[0] == 5 and k[-1] == 61 and np.all(np.diff(k) == 7)
    assert np.flatnonzero(tgt)[0] + 1 < k[0] and np.flatnonzero(tgt)[-1] + 1 > k[-1]
    t = dt * np.arange(1, T + 1)
    line = np.stack([3.7 - 12.5 * t, 1500.0 + 250.0 * t], axis=-1)
    z_src = jnp.asarray(np.where(src[:, None], line, np.nan))
    zr = np.asarray(register(z_src, src, tgt))
    np.testing.assert_array_equal(np.isfinite(zr).all(-1), tgt)
    np.testing.assert_allclose(zr[tgt], line[tgt], rtol=1e-12, atol=1e-12)

    # onto every step: still exactly the line, including the extrapolated ends
    every = np.ones(T, bool)
    np.testing.assert_allclose(np.asarray(register(z_src, src, every)), line, rtol=1e-12, atol=1e-12)

    # the weights of eq. 19: z = z_a + w (z_b − z_a) with a ≤ k ≤ b inside the source span
    a, b, w = registration_weights(src, every)
    inside = (np.arange(T) >= k[0] - 1) & (np.arange(T) <= k[-1] - 1) & ~src
    assert np.all((a[inside] <= np.arange(T)[inside]) & (np.arange(T)[inside] <= b[inside]))
    assert np.all((w[inside] > 0) & (w[inside] < 1))
    assert np.all(w[: k[0] - 1] < 0) and np.all(w[k[-1]:] > 1)  # extrapolation at both ends


def test_interpolation_of_angles_goes_the_short_way_across_pi():
    dt, T = 0.01, 64
    src, tgt = _masks(T, dt)
    t = dt * np.arange(1, T + 1)
    phi = 3.0 + 0.9 * t  # crosses π at t ≈ 0.157
    rng_col = 1000.0 + 50.0 * t
    z = np.stack([rng_col, np.asarray(wrap(jnp.asarray(phi)))], axis=-1)
    z_src = jnp.asarray(np.where(src[:, None], z, np.nan))
    zr = np.asarray(register(z_src, src, tgt, angle_mask=(False, True)))
    np.testing.assert_allclose(zr[tgt, 0], rng_col[tgt], rtol=1e-12)
    assert np.all(np.abs(angdiff(zr[tgt, 1], phi[tgt])) < 1e-12)
    assert np.all((zr[tgt, 1] > -np.pi) & (zr[tgt, 1] <= np.pi))


def test_registration_none_takes_latest_sample_at_or_before():
    dt, T = 0.001, 64
    src, tgt = _masks(T, dt)
    rng = np.random.default_rng(0)
    z = rng.standard_normal((T, 2))
    z_src = jnp.asarray(np.where(src[:, None], z, np.nan))
    zr = np.asarray(register(z_src, src, tgt, method="none"))
    src_idx = np.flatnonzero(src)
    for i in range(T):
        if not tgt[i]:
            assert np.all(np.isnan(zr[i]))
            continue
        before = src_idx[src_idx <= i]
        j = before[-1] if len(before) else src_idx[0]  # the first sample before any exists
        np.testing.assert_array_equal(zr[i], z[j])


# ---------------------------------------------------------------- 9. inverse-variance angle fusion


def test_fusing_equal_variances_halves_the_variance():
    n, sigma = 100_000, 0.02
    theta = np.pi - 0.01  # near the cut: the samples straddle ±π
    ka, kb = jax.random.split(jax.random.key(7))
    za = wrap(theta + sigma * jax.random.normal(ka, (n,)))
    zb = wrap(theta + sigma * jax.random.normal(kb, (n,)))
    fused, var = fuse_angles(za, sigma**2, zb, sigma**2)
    np.testing.assert_allclose(float(var), sigma**2 / 2, rtol=1e-14)
    e = angdiff(np.asarray(fused), theta)
    # the variance estimate of 1e5 Gaussian samples has relative SE √(2/n) ≈ 0.45 %: 2 % ≈ 4.5 SE
    assert abs(np.var(e) / sigma**2 / 0.5 - 1) < 0.02, np.var(e) / sigma**2
    assert abs(np.mean(e)) < 4 * sigma / np.sqrt(2 * n)  # unbiased: wrapping did not pull samples to 0


def test_fusing_unequal_variances():
    n, sa, sb = 100_000, 0.01, 0.03
    theta = -np.pi + 0.005
    ka, kb = jax.random.split(jax.random.key(8))
    za = wrap(theta + sa * jax.random.normal(ka, (n,)))
    zb = wrap(theta + sb * jax.random.normal(kb, (n,)))
    fused, var = fuse_angles(za, sa**2, zb, sb**2)
    expect = sa**2 * sb**2 / (sa**2 + sb**2)  # eq. 21
    np.testing.assert_allclose(float(var), expect, rtol=1e-14)
    e = angdiff(np.asarray(fused), theta)
    assert abs(np.var(e) / expect - 1) < 0.02, np.var(e) / expect
    # eq. 20 on plain numbers: weights ∝ 1/σ²
    f, v = fuse_angles(jnp.asarray(0.1), 1.0, jnp.asarray(0.5), 3.0)
    np.testing.assert_allclose(float(f), (0.1 / 1.0 + 0.5 / 3.0) / (1 / 1.0 + 1 / 3.0), rtol=1e-14)
    np.testing.assert_allclose(float(v), 0.75, rtol=1e-14)


def test_fusion_wraps_around_pi():
    f, _ = fuse_angles(jnp.asarray(np.pi - 0.01), 1.0, jnp.asarray(-np.pi + 0.01), 1.0)
    assert abs(abs(float(f)) - np.pi) < 1e-12  # ±π, not 0
    f, _ = fuse_angles(jnp.asarray(np.pi - 0.01), 1.0, jnp.asarray(-np.pi + 0.03), 1.0)
    np.testing.assert_allclose(float(f), -np.pi + 0.01, atol=1e-12)  # the mean π + 0.01, wrapped
    f, _ = fuse_angles(jnp.asarray(-np.pi + 0.03), 1.0, jnp.asarray(np.pi - 0.01), 1.0)
    np.testing.assert_allclose(float(f), -np.pi + 0.01, atol=1e-12)  # symmetric in the order


# ---------------------------------------------------------------- 10. laser + infrared fusion on a suite


def _suite(sigma=1e-12):
    dt = 0.001
    laser = Sensor("spherical", 3, (sigma, sigma, sigma), name="laser", dt=dt, period=0.1, offset=0.013)
    ir = Sensor("angles", 3, (sigma, sigma), name="ir", dt=dt, period=0.02)
    return SensorSuite((laser, ir)), laser, ir


def _straight_line(T, dt=0.001):
    t = dt * np.arange(1, T + 1)
    # slow, nearly-linear angles (ω ≈ 2e-3 rad/s, curvature ~1e-8 rad/s²): linear interpolation
    # over 20 ms is then exact to ~1e-12, while a 13 ms-old sample lags by ~1e-5 rad
    return t, np.stack([4000.0 + 3.0 * t, -10.0 + 10.0 * t, 800.0 + 2.0 * t], axis=-1)


@pytest.mark.parametrize("registration", ["interpolate", "none"])
def test_laser_ir_fusion_rows_at_laser_epochs(registration):
    suite, laser, ir = _suite(1.0e-3)
    T = 1013  # last laser epoch (1.013 s) after the last IR epoch (1.000 s); first (0.013 s) before the first (0.02 s)
    _, pos = _straight_line(T)
    z = suite.measure(jax.random.key(0), jnp.asarray(pos))
    fusion = LaserIrFusion(suite, "laser", "ir", registration)
    out = np.asarray(fusion(z))
    assert out.shape == (T, 3)
    lm = laser.report_mask(T)
    np.testing.assert_array_equal(np.flatnonzero(lm) + 1, 13 + 100 * np.arange(11))
    np.testing.assert_array_equal(np.isfinite(out).all(-1), lm)
    np.testing.assert_array_equal(np.isnan(out).all(-1), ~lm)
    np.testing.assert_array_equal(out[lm, 0], np.asarray(z)[lm, 0])  # range from the laser as is
    m = fusion.model
    assert m.kind == "spherical" and m.period == laser.period and m.offset == laser.offset
    np.testing.assert_allclose(m.sigma, (1e-3, 1e-3 / np.sqrt(2), 1e-3 / np.sqrt(2)), rtol=1e-14)


def test_laser_ir_fusion_noise_free_straight_line():
    suite, laser, ir = _suite()
    T = 1013
    t, pos = _straight_line(T)
    z = suite.measure(jax.random.key(1), jnp.asarray(pos))
    truth = np.asarray(laser.h(jnp.asarray(pos)))  # (T, 3): r, az, el at every step
    lm = laser.report_mask(T)
    ir_idx = np.flatnonzero(ir.report_mask(T))

    # registered (eq. 19, extrapolating at both ends) then fused: the true angles
    f_int = np.asarray(LaserIrFusion(suite, "laser", "ir", "interpolate")(z))
    np.testing.assert_allclose(f_int[lm, 0], truth[lm, 0], rtol=1e-12)
    assert np.max(np.abs(angdiff(f_int[lm, 1:], truth[lm, 1:]))) < 1e-9

    # unregistered: the latest IR sample (13 ms old; the first laser epoch takes the first IR
    # sample, 7 ms in the future), averaged with equal weights with the laser's angles
    f_none = np.asarray(LaserIrFusion(suite, "laser", "ir", "none")(z))
    err = angdiff(f_none[lm, 1:], truth[lm, 1:])
    for row, i in enumerate(np.flatnonzero(lm)):
        before = ir_idx[ir_idx <= i]
        j = before[-1] if len(before) else ir_idx[0]
        lag = 0.5 * angdiff(truth[j, 1:], truth[i, 1:])
        np.testing.assert_allclose(err[row], lag, rtol=1e-6, atol=1e-11)
    assert np.all(np.abs(err[1:, 0]) > 5e-6)  # ≈ ½ ω_az · 13 ms ≈ 1.3e-5 rad: a clear lag
    assert np.max(np.abs(err)) > 1e3 * np.max(np.abs(angdiff(f_int[lm, 1:], truth[lm, 1:])))


def test_select_view():
    suite, laser, ir = _suite(1e-3)
    T = 120
    _, pos = _straight_line(T)
    z = np.asarray(suite.measure(jax.random.key(2), jnp.asarray(pos)))
    sel = Select(suite, ("ir",))
    np.testing.assert_array_equal(np.asarray(sel(z)), z[:, 3:5], strict=False)
    assert sel.model == ir
    both = Select(suite, ("ir", "laser"))
    np.testing.assert_array_equal(np.asarray(both(z)), z[:, [3, 4, 0, 1, 2]])
    assert both.model.sensors == (ir, laser)
