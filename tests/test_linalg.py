"""Small-matrix algebra against NumPy, under vmap, with the structural zeros."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab.batching import runs_last
from tracklab.linalg import expm, host_expm, jacobian, mahalanobis2, mahalanobis2_logdet, mm, solve, symmetrise
from tracklab.models import cv


@pytest.mark.parametrize("shapes", [((4, 4), (4, 4)), ((2, 4), (4, 2)), ((4, 2), (2,)), ((4,), (4, 4)), ((6, 6), (6, 6))])
def test_products_equal_numpy_under_vmap(shapes):
    """Batched over runs, with one factor known at trace time (a CV F with its zeros) or both traced."""
    rng = np.random.default_rng(0)
    (sa, sb), B = shapes, 7
    A = rng.normal(size=(B,) + sa)
    Bm = rng.normal(size=(B,) + sb)
    F = np.asarray(cv(2, 0.5).F)  # structural zeros and ones
    both = jax.jit(jax.vmap(mm))(A, Bm)
    if sa == (4, 4):
        const = jax.jit(jax.vmap(lambda b: mm(F, b)))(Bm)
        np.testing.assert_allclose(const, np.einsum("ij,bj...->bi...", F, Bm), rtol=1e-13, atol=1e-13)
        # a known factor's zeros and ones skipped, on either side, batched either way: the same
        # numbers to the bit as the product with that factor traced
        known = lambda b: (mm(F, b), mm(b, F.T))
        traced = jax.jit(jax.vmap(lambda f, b: (mm(f, b), mm(b, f.T)), in_axes=(None, 0)))(F, Bm)
        last = jax.jit(runs_last(known, in_axes=(-1,), size=B))(np.moveaxis(Bm, 0, -1))
        for got in (jax.jit(jax.vmap(known))(Bm), tuple(np.moveaxis(g, -1, 0) for g in last)):
            for g, t in zip(got, traced):
                np.testing.assert_array_equal(g, t)
    np.testing.assert_allclose(both, np.matmul(A, Bm[..., None])[..., 0] if len(sb) == 1 else
                               (np.einsum("bi,bij->bj", A, Bm) if len(sa) == 1 else np.matmul(A, Bm)),
                               rtol=1e-13, atol=1e-13)


def test_symmetrise_is_symmetric_and_keeps_the_symmetric_part():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(5, 4, 4))
    S = np.asarray(jax.jit(jax.vmap(symmetrise))(P))
    np.testing.assert_array_equal(S, np.swapaxes(S, 1, 2))
    np.testing.assert_allclose(S, (P + np.swapaxes(P, 1, 2)) / 2, rtol=1e-15)


def test_jacobian_equals_jacfwd():
    def h(x):
        return jnp.stack([jnp.hypot(x[0], x[2]), jnp.arctan2(x[2], x[0]), x[1] * x[3]])

    xs = np.random.default_rng(2).normal(size=(6, 4)) * [1e3, 10.0, 1e3, 10.0]
    np.testing.assert_allclose(jax.vmap(lambda x: jacobian(h, x))(xs), jax.vmap(jax.jacfwd(h))(xs), rtol=1e-14)


@pytest.mark.parametrize("scale", [1e-3, 0.05, 1.0, 5.0])
def test_expm_equals_the_eigendecomposition_under_vmap(scale):
    """Symmetric matrices, whose exponential is V e^Λ Vᵀ (NumPy), over norms that need no squaring up
    to several; and a non-normal upper-triangular 2 × 2 against its closed form. The same for
    ``host_expm``."""
    rng = np.random.default_rng(3)
    X = rng.normal(size=(5, 6, 6)) * scale
    S = (X + np.swapaxes(X, 1, 2)) / 2
    lam, V = np.linalg.eigh(S)
    want = np.einsum("bij,bj,bkj->bik", V, np.exp(lam), V)
    np.testing.assert_allclose(jax.jit(jax.vmap(expm))(S), want, rtol=1e-12 * max(1.0, scale), atol=1e-15)
    a, c, b = -0.3 * scale, 0.2 * scale, 5.0
    T = np.array([[a, b], [0.0, c]])
    closed = np.array([[np.exp(a), b * (np.exp(a) - np.exp(c)) / (a - c)], [0.0, np.exp(c)]])
    np.testing.assert_allclose(expm(jnp.asarray(T)), closed, rtol=1e-12)
    for Si, wi in zip(S, want):  # the host's, NumPy in float64
        np.testing.assert_allclose(host_expm(Si), wi, rtol=1e-12 * max(1.0, scale), atol=1e-15)
    np.testing.assert_allclose(host_expm(T), closed, rtol=1e-12)


def test_expm_beyond_its_squarings_is_nan():
    assert np.isnan(np.asarray(expm(jnp.eye(3) * 1e4))).all()


def test_solve_equals_numpy_on_transition_matrices():
    """A transition over a short interval (the identity, small terms, one large coupling) under vmap."""
    rng = np.random.default_rng(4)
    A = np.eye(9) + rng.normal(size=(7, 9, 9)) * 0.05
    A[:, 7, 1] = 20.0
    B = rng.normal(size=(7, 9, 3))
    np.testing.assert_allclose(jax.jit(jax.vmap(solve))(A, B), np.linalg.solve(A, B), rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(jax.vmap(solve)(A, B[..., 0]), np.linalg.solve(A, B[..., :1])[..., 0], rtol=1e-11,
                               atol=1e-12)


@pytest.mark.parametrize("name", ["lidar_crossing", "laser_ir_alpha_beta", "error_space_overflight", "tuning_stf"])
def test_a_filter_built_inside_a_trace_keeps_its_known_matrices(name):
    """The chunk builds its filters inside its own trace, where ``jnp.asarray`` of a model's F or
    H is a staged constant that ``mm`` cannot read: each bundled filter's step then multiplies by
    their zeros. Built inside a trace or outside it, a filter's step has the same products."""
    from pathlib import Path

    from tracklab.config import load_experiment
    from tracklab.filters.core import Meas, Prior
    from tracklab.models import MODELS

    exp = load_experiment(Path(__file__).resolve().parent.parent / "experiments" / f"{name}.toml")
    params = exp.params()
    for fc, p in zip(exp.filters, params.filters):
        lane = exp.lane(fc)
        if not hasattr(lane, "kind"):  # a plug-in's own filter
            continue
        n = MODELS[lane.model](exp.scenario.dim, exp.scenario.dt).n
        m = lane.sees(exp.sensor)[1].m
        meas = Meas(jnp.zeros(m), jnp.asarray(1.0), jnp.asarray(True))
        realise = lambda: lane.realise(exp.scenario, exp.sensor, p, 0.0).filter  # noqa: E731
        state = realise().init(p, Prior(jnp.zeros(n), jnp.eye(n)))
        outside = realise()
        products = [str(jax.make_jaxpr(step)(p, state)).count(" mul ")
                    for step in (lambda p, s: outside.step(p, s, meas)[0], lambda p, s: realise().step(p, s, meas)[0])]
        assert products[0] == products[1], (name, fc.label, products)


def test_mahalanobis_and_log_det_equal_numpy_and_are_nan_off_the_cone():
    """vᵀ A⁻¹ v and log det A by A = L D Lᵀ against NumPy's solve and slogdet, sizes 1 to 6,
    under vmap and with the runs last (the layout the chunk uses); NaN for a matrix that is
    not positive definite, its first pivot or a later one."""
    rng = np.random.default_rng(5)
    for n in range(1, 7):
        G = rng.normal(size=(8, n, n))
        A = G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(n) * 10.0 ** rng.uniform(-3, 3, (8, 1, 1))
        v = rng.normal(size=(8, n)) * 10.0 ** rng.uniform(-2, 2, (8, 1))
        want = np.einsum("bi,bi->b", v, np.linalg.solve(A, v[..., None])[..., 0])
        want_logdet = np.linalg.slogdet(A)[1]
        for m2, logdet in (jax.jit(jax.vmap(mahalanobis2_logdet))(A, v),
                           jax.jit(runs_last(mahalanobis2_logdet, in_axes=(-1, -1), size=8))(
                               np.moveaxis(A, 0, -1), np.moveaxis(v, 0, -1))):
            np.testing.assert_allclose(m2, want, rtol=1e-9)
            np.testing.assert_allclose(logdet, want_logdet, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(jax.jit(jax.vmap(mahalanobis2))(A, v), want, rtol=1e-9)
    for bad in (np.diag([-1.0, 2.0, 3.0]), np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])):
        assert np.isnan(mahalanobis2(bad, np.ones(3)))
        assert np.isnan(mahalanobis2_logdet(bad, np.ones(3))[1])
