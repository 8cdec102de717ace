"""Converted-measurement KF, polar-state KF and sequential EKF against NumPy references.

Every reference below is written from the formulas (docs/mathematics.md §4; paper 000
eqs. 8/12, 13–17, 31–34) in plain float64 NumPy with Python loops, without
calling tracklab. Each filter is run on the same simulated measurements and must
match its reference to a relative difference of 1e-9 at every step. The last
tests check the conversions themselves by Monte Carlo (bias and covariance).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tracklab
from tracklab.filters import build, noise_params
from tracklab.models import cv
from tracklab.sensors import Sensor
from tracklab.sensors import conversion

RTOL = 1e-9
DT = 0.5
Q_ACC = 1.0  # acceleration variance (m²/s⁴), truth and filters
SIG2 = (100.0, 0.003)  # polar sensor: range (m), angle (rad)
SIG3 = (100.0, 0.003, 0.004)  # spherical sensor: range (m), azimuth, elevation (rad)


# ----------------------------------------------------------------- NumPy helpers


def wrap(a):
    """Angle to (-π, π]."""
    return a - 2.0 * np.pi * np.ceil((a - np.pi) / (2.0 * np.pi))


def cv_matrices(dim, dt, q):
    """Interleaved CV model [x, ẋ, y, ẏ(, z, ż)]: F and Q = q G Gᵀ, G = [dt²/2, dt] per axis."""
    Fa = np.array([[1.0, dt], [0.0, 1.0]])
    Qa = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    return np.kron(np.eye(dim), Fa), np.kron(np.eye(dim), Qa)


def joseph(x, P, nu, H, R):
    """Kalman update with the Joseph-form covariance; returns (x, P, S)."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    A = np.eye(len(x)) - K @ H
    return x + K @ nu, A @ P @ A.T + K @ R @ K.T, S


def crossing_truth(rng, dim, steps, start, vel):
    """CV truth with DWNA noise; row 0 is the prior epoch, rows 1.. are measured."""
    F, Q = cv_matrices(dim, DT, Q_ACC)
    s = np.zeros(2 * dim)
    s[0::2], s[1::2] = start, vel
    out = [s]
    for _ in range(steps):
        w = rng.normal(size=dim) * np.sqrt(Q_ACC)
        g = np.zeros(2 * dim)
        g[0::2], g[1::2] = DT**2 / 2 * w, DT * w
        s = F @ s + g
        out.append(s)
    return np.array(out)


def measure(rng, truth, sigma, missed=()):
    """Polar [r, β] or spherical [r, az, el] measurements of truth[1:] with Gaussian noise."""
    pos = truth[1:, 0::2]
    x, y = pos[:, 0], pos[:, 1]
    if pos.shape[1] == 2:
        z = np.stack([np.hypot(x, y), np.arctan2(y, x)], axis=1)
    else:
        rho = np.hypot(x, y)
        z = np.stack([np.sqrt(rho**2 + pos[:, 2] ** 2), np.arctan2(y, x), np.arctan2(pos[:, 2], rho)], axis=1)
    z = z + rng.normal(size=z.shape) * np.asarray(sigma)
    z[:, 1] = wrap(z[:, 1])
    z[list(missed)] = np.nan
    return z


def prior(rng, truth0):
    """Prior one period before the first measurement: truth + N(0, P0) draw, and P0."""
    n = len(truth0)
    P0 = np.diag(np.tile([200.0**2, 30.0**2], n // 2))
    return truth0 + rng.normal(size=n) * np.sqrt(np.diag(P0)), P0


def scenario(dim, seed, missed=()):
    """A crossing target (passes within a few km of the sensor) and its measurements."""
    rng = np.random.default_rng(seed)
    if dim == 2:
        truth = crossing_truth(rng, 2, 80, (-8000.0, 3000.0), (250.0, 0.0))
        sigma = SIG2
    else:
        truth = crossing_truth(rng, 3, 80, (-8000.0, 3000.0, 1500.0), (250.0, -20.0, 5.0))
        sigma = SIG3
    z = measure(rng, truth, sigma, missed)
    x0, P0 = prior(rng, truth[0])
    return z, x0, P0, np.asarray(sigma)


def branch_cut_scenario(seed, missed=()):
    """2-D target crossing the negative x-axis, where the measured angle jumps from π to -π."""
    rng = np.random.default_rng(seed)
    truth = crossing_truth(rng, 2, 60, (-4000.0, 100.0), (0.0, -8.0))
    z = measure(rng, truth, SIG2, missed)
    flips = np.sum(z[:-1, 1] * z[1:, 1] < -1.0)
    assert flips >= 3, "the measured angle must jump across β = ±π several times"
    x0, P0 = prior(rng, truth[0])
    return z, x0, P0, np.asarray(SIG2)


def run_lib(kind, dim, sigma, z, x0, P0, options=None):
    model = cv(dim, DT)
    sensor = Sensor("polar" if dim == 2 else "spherical", dim, tuple(sigma))
    flt = build(kind, model, sensor, noise_params(Q_ACC, np.square(sigma)), options)
    res = tracklab.run_filter(flt, z, x0=x0, P0=P0)
    return {k: np.asarray(getattr(res, k)) for k in ("x", "P", "nu", "S", "valid")}


def assert_matches(res, ref_x, ref_P, rtol=RTOL):
    """x within rtol of max(|x|, σ); P_ij within rtol·√(P_ii P_jj) (a scale-free relative test)."""
    sd = np.sqrt(np.diagonal(ref_P, axis1=-2, axis2=-1))
    ex = np.abs(res["x"] - ref_x) / np.maximum(np.abs(ref_x), sd)
    eP = np.abs(res["P"] - ref_P) / (sd[..., :, None] * sd[..., None, :])
    assert np.all(np.isfinite(res["x"])) and np.all(np.isfinite(res["P"]))
    assert ex.max() <= rtol, f"x: max rel diff {ex.max():.3e} at step {np.unravel_index(ex.argmax(), ex.shape)}"
    assert eP.max() <= rtol, f"P: max rel diff {eP.max():.3e} at step {np.unravel_index(eP.argmax(), eP.shape)}"


# ----------------------------------------------------- reference conversions (§4)


def ref_convert(z, sigma, debias):
    """Converted position and covariance from docs/mathematics.md §4, written out entry by entry."""
    if len(z) == 2:
        r, b = z
        sr2, sb2 = np.square(sigma)
        c, s = np.cos(b), np.sin(b)
        if debias == "plain":  # paper 000 eqs. (8) and (12)
            pos = np.array([r * c, r * s])
            R11 = sr2 * c**2 + r**2 * sb2 * s**2
            R22 = sr2 * s**2 + r**2 * sb2 * c**2
            R12 = (sr2 - r**2 * sb2) * s * c
        elif debias == "additive":  # Lerro & Bar-Shalom (1993)
            mu = r * (np.exp(-sb2) - np.exp(-sb2 / 2))
            pos = np.array([r * c - mu * c, r * s - mu * s])
            e = np.exp(-2 * sb2)
            A_r2 = np.cosh(2 * sb2) - np.cosh(sb2), np.sinh(2 * sb2) - np.sinh(sb2)
            A_sr = 2 * np.cosh(2 * sb2) - np.cosh(sb2), 2 * np.sinh(2 * sb2) - np.sinh(sb2)
            R11 = r**2 * e * (c**2 * A_r2[0] + s**2 * A_r2[1]) + sr2 * e * (c**2 * A_sr[0] + s**2 * A_sr[1])
            R22 = r**2 * e * (s**2 * A_r2[0] + c**2 * A_r2[1]) + sr2 * e * (s**2 * A_sr[0] + c**2 * A_sr[1])
            R12 = s * c * np.exp(-4 * sb2) * (sr2 + (r**2 + sr2) * (1 - np.exp(sb2)))
        elif debias == "unbiased":  # Mo et al. (1998), covariance conditioned on z
            lam, lamp = np.exp(-sb2 / 2), np.exp(-2 * sb2)
            pos = np.array([r * c, r * s]) / lam
            k, h = lam**-2 - 2, 0.5 * (r**2 + sr2)
            R11 = k * r**2 * c**2 + h * (1 + lamp * np.cos(2 * b))
            R22 = k * r**2 * s**2 + h * (1 - lamp * np.cos(2 * b))
            R12 = k * r**2 * s * c + h * lamp * np.sin(2 * b)
        else:
            raise KeyError(debias)
        return pos, np.array([[R11, R12], [R12, R22]])

    r, be, ep = z
    sr2, sb2, se2 = np.square(sigma)
    Cb, Sb, Ce, Se = np.cos(be), np.sin(be), np.cos(ep), np.sin(ep)
    if debias == "plain":  # J diag(σ²) Jᵀ with the analytic Jacobian of (r, az, el) -> (x, y, z)
        pos = r * np.array([Ce * Cb, Ce * Sb, Se])
        J = np.array([
            [Ce * Cb, -r * Ce * Sb, -r * Se * Cb],
            [Ce * Sb, r * Ce * Cb, -r * Se * Sb],
            [Se, 0.0, r * Ce],
        ])
        R = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                R[i, j] = sum(J[i, k] * J[j, k] * (sr2, sb2, se2)[k] for k in range(3))
        return pos, R
    if debias != "unbiased":
        raise KeyError(debias)
    lb, le = np.exp(-sb2 / 2), np.exp(-se2 / 2)
    lbp, lep = np.exp(-2 * sb2), np.exp(-2 * se2)
    pos = np.array([r * Ce * Cb / (lb * le), r * Ce * Sb / (lb * le), r * Se / le])
    L = (lb * le) ** -2 - 2
    h = r**2 + sr2
    R11 = L * r**2 * Cb**2 * Ce**2 + 0.25 * h * (1 + lbp * np.cos(2 * be)) * (1 + lep * np.cos(2 * ep))
    R22 = L * r**2 * Sb**2 * Ce**2 + 0.25 * h * (1 - lbp * np.cos(2 * be)) * (1 + lep * np.cos(2 * ep))
    R33 = (le**-2 - 2) * r**2 * Se**2 + 0.5 * h * (1 - lep * np.cos(2 * ep))
    R12 = L * r**2 * Sb * Cb * Ce**2 + 0.25 * h * lbp * np.sin(2 * be) * (1 + lep * np.cos(2 * ep))
    k13 = 1 / (lb * le**2) - 1 / lb - lb
    R13 = k13 * r**2 * Cb * Se * Ce + 0.5 * h * lb * lep * Cb * np.sin(2 * ep)
    R23 = k13 * r**2 * Sb * Se * Ce + 0.5 * h * lb * lep * Sb * np.sin(2 * ep)
    return pos, np.array([[R11, R12, R13], [R12, R22, R23], [R13, R23, R33]])


# ------------------------------------------------------------- reference filters


def ref_cmkf(z, x0, P0, sigma, debias):
    """Converted-measurement KF: linear KF on the converted position with R from §4."""
    dim = len(x0) // 2
    F, Q = cv_matrices(dim, DT, Q_ACC)
    H = np.zeros((dim, 2 * dim))
    H[np.arange(dim), 2 * np.arange(dim)] = 1.0
    x, P = x0.astype(float), P0.astype(float)
    xs, Ps, nus, Ss = [], [], [], []
    for zk in z:
        x, P = F @ x, F @ P @ F.T + Q
        nu, S = np.zeros(dim), None
        if np.all(np.isfinite(zk)):
            pos, R = ref_convert(zk, sigma, debias)
            nu = pos - H @ x
            x, P, S = joseph(x, P, nu, H, R)
        xs.append(x), Ps.append(P), nus.append(nu), Ss.append(S)
    return np.array(xs), np.array(Ps), np.array(nus), Ss


def cart_to_polar(x):
    px, vx, py, vy = x
    r = np.hypot(px, py)
    return np.array([r, (px * vx + py * vy) / r, np.arctan2(py, px), (px * vy - py * vx) / r**2])


def jac_cart_to_polar(x):
    """∂[r, ṙ, β, β̇]/∂[x, ẋ, y, ẏ], analytic."""
    px, vx, py, vy = x
    r2 = px**2 + py**2
    r = np.sqrt(r2)
    a, w = px * vx + py * vy, px * vy - py * vx
    return np.array([
        [px / r, 0.0, py / r, 0.0],
        [vx / r - a * px / r**3, px / r, vy / r - a * py / r**3, py / r],
        [-py / r2, 0.0, px / r2, 0.0],
        [vy / r2 - 2 * w * px / r2**2, -py / r2, -vx / r2 - 2 * w * py / r2**2, px / r2],
    ])


def polar_to_cart(s):
    r, rd, b, bd = s
    c, sn = np.cos(b), np.sin(b)
    return np.array([r * c, rd * c - r * bd * sn, r * sn, rd * sn + r * bd * c])


def jac_polar_to_cart(s):
    """∂[x, ẋ, y, ẏ]/∂[r, ṙ, β, β̇], analytic."""
    r, rd, b, bd = s
    c, sn = np.cos(b), np.sin(b)
    return np.array([
        [c, 0.0, -r * sn, 0.0],
        [-bd * sn, c, -rd * sn - r * bd * c, -r * sn],
        [sn, 0.0, r * c, 0.0],
        [bd * c, sn, rd * c - r * bd * sn, r * c],
    ])


def ref_polar_kf(z, x0, P0, sigma):
    """Paper 000 §3.2 as two separate 2-state filters (range channel, angle channel).

    Q per channel is q G Gᵀ with the gains of eqs. (15)–(16) at the filtered
    (r_k, β_k); the polar prior is the Jacobian map of the Cartesian one with the
    range–angle cross blocks dropped. Reported in Cartesian through the Jacobian.
    """
    T = DT
    F = np.array([[1.0, T], [0.0, 1.0]])
    H = np.array([[1.0, 0.0]])
    s0 = cart_to_polar(x0)
    J = jac_cart_to_polar(x0)
    Pp = J @ P0 @ J.T
    xr, Pr = s0[:2].copy(), Pp[:2, :2].copy()  # range channel [r, ṙ]
    xb, Pb = s0[2:].copy(), Pp[2:, 2:].copy()  # angle channel [β, β̇]
    xs, Ps = [], []
    for zk in z:
        r, b = xr[0], xb[0]
        c, s = np.cos(b), np.sin(b)
        Gr = np.array([[T**2 / 2 * c, T**2 / 2 * s], [T * c, T * s]])  # eq. (15)
        Gb = np.array([[-T**2 * s / (2 * r), T**2 * c / (2 * r)], [-T * s / r, T * c / r]])  # eq. (16)
        xr, Pr = F @ xr, F @ Pr @ F.T + Q_ACC * Gr @ Gr.T
        xb, Pb = F @ xb, F @ Pb @ F.T + Q_ACC * Gb @ Gb.T
        if np.all(np.isfinite(zk)):
            xr, Pr, _ = joseph(xr, Pr, np.array([zk[0] - xr[0]]), H, np.array([[sigma[0] ** 2]]))
            xb, Pb, _ = joseph(xb, Pb, np.array([wrap(zk[1] - xb[0])]), H, np.array([[sigma[1] ** 2]]))
        s = np.concatenate([xr, xb])
        P = np.zeros((4, 4))
        P[:2, :2], P[2:, 2:] = Pr, Pb
        Jc = jac_polar_to_cart(s)
        xs.append(polar_to_cart(s)), Ps.append(Jc @ P @ Jc.T)
    return np.array(xs), np.array(Ps)


def _angle_range_rows(x, dim):
    """Measurement functions and analytic gradient rows, in the sequential order."""
    n = 2 * dim
    if dim == 2:
        px, py = x[0], x[2]
        r2 = px**2 + py**2
        r = np.sqrt(r2)
        Hb, Hr = np.zeros(n), np.zeros(n)
        Hb[[0, 2]] = -py / r2, px / r2
        Hr[[0, 2]] = px / r, py / r
        return {1: (np.arctan2(py, px), Hb), 0: (r, Hr)}
    px, py, pz = x[0], x[2], x[4]
    rho2 = px**2 + py**2
    rho = np.sqrt(rho2)
    r2 = rho2 + pz**2
    r = np.sqrt(r2)
    Ha, He, Hr = np.zeros(n), np.zeros(n), np.zeros(n)
    Ha[[0, 2]] = -py / rho2, px / rho2
    He[[0, 2, 4]] = -px * pz / (r2 * rho), -py * pz / (r2 * rho), rho / r2
    Hr[[0, 2, 4]] = px / r, py / r, pz / r
    return {1: (np.arctan2(py, px), Ha), 2: (np.arctan2(pz, rho), He), 0: (r, Hr)}


def ref_sequential_ekf(z, x0, P0, sigma, relinearise=True):
    """Paper 000 §4.2: scalar EKF updates, angle(s) first, then range, each linearised
    at the estimate left by the previous scalar update; angle innovations wrapped.
    With ``relinearise=False`` every row uses the prediction (= a one-shot EKF)."""
    dim = len(x0) // 2
    F, Q = cv_matrices(dim, DT, Q_ACC)
    order = [1, 0] if dim == 2 else [1, 2, 0]
    x, P = x0.astype(float), P0.astype(float)
    xs, Ps, nus, Ss = [], [], [], []
    for zk in z:
        x, P = F @ x, F @ P @ F.T + Q
        nu, Sd = np.zeros(len(zk)), np.zeros(len(zk))
        if np.all(np.isfinite(zk)):
            rows_pred = _angle_range_rows(x, dim)
            for i in order:
                hi, Hi = (_angle_range_rows(x, dim) if relinearise else rows_pred)[i]
                nu[i] = wrap(zk[i] - hi) if i > 0 else zk[i] - hi
                x, P, S = joseph(x, P, nu[i : i + 1], Hi[None, :], np.array([[sigma[i] ** 2]]))
                Sd[i] = S[0, 0]
        xs.append(x), Ps.append(P), nus.append(nu), Ss.append(np.diag(Sd))
    return np.array(xs), np.array(Ps), np.array(nus), np.array(Ss)


# --------------------------------------------------------------------- the tests


@pytest.mark.parametrize(
    "dim, debias",
    [(2, "plain"), (2, "unbiased"), (2, "additive"), (3, "plain"), (3, "unbiased")],
)
def test_cmkf_matches_numpy_reference(dim, debias):
    """cmkf (each debiasing) = KF on the §4 converted measurement and covariance, every step."""
    z, x0, P0, sigma = scenario(dim, seed=10 + dim, missed=(7, 30))
    res = run_lib("cmkf", dim, sigma, z, x0, P0, {"debias": debias})
    x, P, nu, S = ref_cmkf(z, x0, P0, sigma, debias)
    assert_matches(res, x, P)
    ok = np.all(np.isfinite(z), axis=1)
    np.testing.assert_array_equal(res["valid"], ok)
    S_ref = np.array([s for s in S if s is not None])
    sd = np.sqrt(np.diagonal(S_ref, axis1=-2, axis2=-1))  # innovation std per component
    assert np.all(np.abs(res["nu"][ok] - nu[ok]) <= RTOL * sd)
    assert np.all(np.abs(res["S"][ok] - S_ref) <= RTOL * sd[:, :, None] * sd[:, None, :])


def test_cmkf_variants_are_distinguishable():
    """Sanity: the three 2-D conversions give different tracks here, so the
    comparisons above would notice a filter using the wrong one."""
    z, x0, P0, sigma = scenario(2, seed=12)
    xs = {d: ref_cmkf(z, x0, P0, sigma, d)[0] for d in ("plain", "unbiased", "additive")}
    sd = np.sqrt(np.diagonal(ref_cmkf(z, x0, P0, sigma, "plain")[1], axis1=-2, axis2=-1))
    for a, b in [("plain", "unbiased"), ("plain", "additive"), ("unbiased", "additive")]:
        assert np.max(np.abs(xs[a] - xs[b]) / sd) > 1e3 * RTOL


@pytest.mark.parametrize("case", ["crossing", "branch_cut"])
def test_polar_kf_matches_numpy_reference(case):
    """polar_kf = two decoupled polar CV filters with the eq. (15)-(16) noise gains at
    the filtered (r_k, β_k), reported in Cartesian; also across the β = ±π cut."""
    missed = (5, 6, 40)
    if case == "crossing":
        z, x0, P0, sigma = scenario(2, seed=21, missed=missed)
    else:
        z, x0, P0, sigma = branch_cut_scenario(seed=22, missed=missed)
    res = run_lib("polar_kf", 2, sigma, z, x0, P0)
    x, P = ref_polar_kf(z, x0, P0, sigma)
    assert_matches(res, x, P)


@pytest.mark.parametrize("case", ["2d", "2d_branch_cut", "3d"])
def test_sequential_ekf_matches_numpy_reference(case):
    """sequential_ekf = scalar EKF updates (angles, then range re-linearised at the
    intermediate estimate), with missed detections and the ±π angle wrap."""
    missed = (3, 4, 25, 51)
    if case == "2d":
        z, x0, P0, sigma = scenario(2, seed=31, missed=missed)
    elif case == "2d_branch_cut":
        z, x0, P0, sigma = branch_cut_scenario(seed=32, missed=missed)
    else:
        z, x0, P0, sigma = scenario(3, seed=33, missed=missed)
    dim = len(x0) // 2
    res = run_lib("sequential_ekf", dim, sigma, z, x0, P0)
    x, P, nu, S = ref_sequential_ekf(z, x0, P0, sigma)
    assert_matches(res, x, P)
    ok = np.all(np.isfinite(z), axis=1)
    np.testing.assert_array_equal(res["valid"], ok)
    np.testing.assert_array_equal(res["nu"][~ok], 0.0)
    scale = np.sqrt(np.diagonal(S[ok], axis1=-2, axis2=-1))  # innovation std per component
    assert np.all(np.abs(res["nu"][ok] - nu[ok]) <= 1e-8 * scale)
    np.testing.assert_allclose(res["S"][ok], S[ok], rtol=RTOL, atol=0)


def test_sequential_relinearisation_matters():
    """Sanity: re-linearising the range row at the intermediate estimate changes the
    track by far more than 1e-9 here, so the comparison above can tell the sequential
    EKF from a one-shot EKF (all rows linearised at the prediction)."""
    z, x0, P0, sigma = scenario(2, seed=31)
    x_seq, P_seq, _, _ = ref_sequential_ekf(z, x0, P0, sigma)
    x_one, _, _, _ = ref_sequential_ekf(z, x0, P0, sigma, relinearise=False)
    sd = np.sqrt(np.diagonal(P_seq, axis1=-2, axis2=-1))
    assert np.max(np.abs(x_seq - x_one) / sd) > 1e3 * RTOL


# ------------------------------------------------------- Monte-Carlo conversions

N_MC = 200_000


def _mc_measurements(seed, z_true, sigma):
    """N_MC noisy measurements of one true [r, angle(s)] and the true Cartesian position."""
    rng = np.random.default_rng(seed)
    zs = np.asarray(z_true) + rng.normal(size=(N_MC, len(z_true))) * np.asarray(sigma)
    if len(z_true) == 2:
        r, b = z_true
        return zs, r * np.array([np.cos(b), np.sin(b)])
    r, az, el = z_true
    return zs, r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _convert_many(name, zs, sigma):
    """The library's conversion applied to every sample (jax.vmap)."""
    f = jax.jit(jax.vmap(getattr(conversion, name), in_axes=(0, None)))
    pos, R = f(jnp.asarray(zs), jnp.asarray(sigma, dtype=float))
    return np.asarray(pos), np.asarray(R)


def _err_stats(pos, true):
    """Mean error, its standard error, and the error second moment about the truth."""
    err = pos - true
    return err.mean(axis=0), err.std(axis=0) / np.sqrt(len(err)), err.T @ err / len(err)


def _corr_scale(M):
    d = np.sqrt(np.diag(M))
    return np.outer(d, d)


@pytest.mark.parametrize("theta", [0.5, 2.3])
def test_mc_2d_bias_plain_vs_unbiased(theta):
    """Large angle noise (0.1 rad): the plain conversion's mean error is the predicted
    (λ-1)·r·[cos θ, sin θ], many standard errors from 0; the unbiased one's mean error
    is 0 within MC error; the additive one's small residual bias is the predicted
    (λ+λ²-λ³-1)·r·[cos θ, sin θ] (λ = e^{-σ²/2})."""
    r, sigma = 5000.0, (20.0, 0.1)
    zs, true = _mc_measurements(100 + int(10 * theta), (r, theta), sigma)
    lam = np.exp(-sigma[1] ** 2 / 2)
    u = np.array([np.cos(theta), np.sin(theta)])

    mean, se, _ = _err_stats(_convert_many("plain", zs, sigma)[0], true)
    bias_plain = (lam - 1) * r * u
    assert np.all(np.abs(bias_plain) > 8 * se)  # the bias is clearly visible
    assert np.all(np.abs(mean - bias_plain) < 4 * se)

    mean, se, _ = _err_stats(_convert_many("unbiased", zs, sigma)[0], true)
    assert np.all(np.abs(mean) < 4 * se)

    mean, se, _ = _err_stats(_convert_many("additive", zs, sigma)[0], true)
    assert np.all(np.abs(mean - (lam + lam**2 - lam**3 - 1) * r * u) < 4 * se)


@pytest.mark.parametrize("theta", [0.5, 2.3])
def test_mc_2d_unbiased_covariance(theta):
    """σ_β = 0.05 rad: the average over z of the unbiased conversion's conditional R
    equals the empirical covariance of (converted - true) within 3 % (MC error ≈ 0.5 %)."""
    zs, true = _mc_measurements(200 + int(10 * theta), (5000.0, theta), (20.0, 0.05))
    pos, R = _convert_many("unbiased", zs, (20.0, 0.05))
    _, _, emp = _err_stats(pos, true)
    assert np.all(np.abs(R.mean(axis=0) - emp) <= 0.03 * _corr_scale(emp)), (R.mean(axis=0), emp)


def test_mc_2d_unbiased_covariance_large_noise():
    """σ_β = 0.1 rad, checked against closed forms instead of each other: the empirical
    error covariance is the true-value MSE ½λ⁻²(r²+σ_r²)(1±λ′cos2θ) - r²cos²θ …, and the
    average of R is its exact expectation over z. (The two differ by ≈ ½r²cos2θ(1-λ′)²,
    about 5 % of R11 here: the z-conditioned R is not the MSE at fixed truth to O(σ⁴).)"""
    r, th, sr, sb = 5000.0, 0.5, 20.0, 0.1
    zs, true = _mc_measurements(250, (r, th), (sr, sb))
    pos, R = _convert_many("unbiased", zs, (sr, sb))
    _, _, emp = _err_stats(pos, true)
    lam, lamp = np.exp(-sb**2 / 2), np.exp(-2 * sb**2)
    c2, s2, a, h = np.cos(2 * th), np.sin(2 * th), 0.5 * (r**2 + sr**2), 0.5 * (r**2 + 2 * sr**2)
    mse = np.array([
        [a / lam**2 * (1 + lamp * c2) - r**2 * np.cos(th) ** 2, a / lam**2 * lamp * s2 - r**2 * np.sin(th) * np.cos(th)],
        [0.0, a / lam**2 * (1 - lamp * c2) - r**2 * np.sin(th) ** 2],
    ])
    mse[1, 0] = mse[0, 1]
    k = lam**-2 - 2
    ER = np.array([
        [k * a * (1 + lamp * c2) + h * (1 + lamp**2 * c2), k * a * lamp * s2 + h * lamp**2 * s2],
        [0.0, k * a * (1 - lamp * c2) + h * (1 - lamp**2 * c2)],
    ])
    ER[1, 0] = ER[0, 1]
    assert np.all(np.abs(emp - mse) <= 0.015 * _corr_scale(mse)), (emp, mse)
    assert np.all(np.abs(R.mean(axis=0) - ER) <= 0.015 * _corr_scale(ER)), (R.mean(axis=0), ER)


def test_mc_3d_plain_bias_vs_unbiased():
    """3-D spherical, 0.1 rad angle noise: the plain conversion's mean error is the
    predicted (λ_aλ_e - 1, λ_aλ_e - 1, λ_e - 1)·true; the unbiased one's is 0."""
    sigma = (20.0, 0.1, 0.1)
    zs, true = _mc_measurements(300, (5000.0, 0.7, 0.6), sigma)
    la, le = np.exp(-sigma[1] ** 2 / 2), np.exp(-sigma[2] ** 2 / 2)
    mean, se, _ = _err_stats(_convert_many("plain", zs, sigma)[0], true)
    bias_plain = (np.array([la * le, la * le, le]) - 1) * true
    assert np.all(np.abs(bias_plain) > 8 * se)
    assert np.all(np.abs(mean - bias_plain) < 4 * se)
    mean, se, _ = _err_stats(_convert_many("unbiased", zs, sigma)[0], true)
    assert np.all(np.abs(mean) < 4 * se)


def test_mc_3d_unbiased_covariance():
    """3-D spherical, 0.05 rad angle noise: the averaged conditional R of the unbiased
    conversion matches the empirical error covariance within 3 %."""
    sigma = (20.0, 0.05, 0.05)
    zs, true = _mc_measurements(310, (5000.0, 2.2, 0.6), sigma)
    pos, R = _convert_many("unbiased", zs, sigma)
    _, _, emp = _err_stats(pos, true)
    assert np.all(np.abs(R.mean(axis=0) - emp) <= 0.03 * _corr_scale(emp)), (R.mean(axis=0), emp)


def test_conversions_match_reference_formulas_pointwise():
    """The library's conversion functions equal the §4 formulas written out above, at a
    spread of measurements and noise levels (2-D: plain/additive/unbiased; 3-D:
    plain/unbiased)."""
    rng = np.random.default_rng(400)
    n = 40
    ang = lambda lo, hi: rng.uniform(lo, hi, size=n)
    z2 = np.stack([ang(100, 50000), ang(-np.pi, np.pi)], axis=1)
    s2 = np.stack([ang(1, 200), ang(1e-3, 0.2)], axis=1)
    z3 = np.stack([ang(100, 50000), ang(-np.pi, np.pi), ang(-1.4, 1.4)], axis=1)
    s3 = np.stack([ang(1, 200), ang(1e-3, 0.2), ang(1e-3, 0.2)], axis=1)
    cases = [(z2, s2, d) for d in ("plain", "additive", "unbiased")]
    cases += [(z3, s3, d) for d in ("plain", "unbiased")]
    for zs, ss, d in cases:
        pos, R = jax.jit(jax.vmap(getattr(conversion, d)))(jnp.asarray(zs), jnp.asarray(ss))
        for k in range(n):
            pos_ref, R_ref = ref_convert(zs[k], ss[k], d)
            np.testing.assert_allclose(np.asarray(pos[k]), pos_ref, rtol=RTOL, atol=0)
            sd = np.sqrt(np.diag(R_ref))
            assert np.all(np.abs(np.asarray(R[k]) - R_ref) <= RTOL * np.outer(sd, sd)), (d, zs[k], ss[k])
