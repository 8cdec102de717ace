"""``batching.runs_last`` against ``jax.vmap``: the same values and derivatives for every kind of
primitive it batches by a rule of its own (elementwise with NumPy broadcasting, slices, reshapes,
transposes, reductions, concatenation, splits, padding, slices at shared offsets, matrix products with either operand shared, a
``cond`` on a shared predicate, nested ``jit``) and for those it hands to ``vmap`` (a Cholesky
factor, a triangular solve, a loop (``scan``), a ``cond`` on a per-run predicate, a custom derivative); and which of a filter's errors the chunk carries once."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab.batching import runs_last


@jax.custom_jvp
def _soft_abs(x):
    return jnp.sqrt(x * x + 1e-3)


@_soft_abs.defjvp
def _soft_abs_jvp(p, t):
    (x,), (dx,) = p, t
    return _soft_abs(x), 2.0 * x * dx  # deliberately not the true derivative: it must be the one used


def one_run(x, P, A, s):
    """One run's (x (3,), P (3, 3)) with shared A (3, 3) and s (): a bit of everything."""
    y = A @ x + jnp.sin(x) * s  # shared · per run, elementwise with a shared scalar
    M = jnp.outer(y, y) + P @ P.T + jnp.eye(3)  # broadcasting (3, 1) * (1, 3), per run · per run
    L = jnp.linalg.cholesky(M)  # a fallback to vmap
    w = jax.scipy.linalg.solve_triangular(L, y, lower=True)
    B = (P @ A)[:2, 1:].reshape(4)  # per run · shared, slice, reshape
    z = jnp.concatenate([jnp.pad(w, (1, 0)), B, jnp.stack([w.max(), jnp.abs(y).sum()])])
    c = jax.lax.cond(s > 0, lambda a: a * 2.0, lambda a: a - 1.0, y)  # shared predicate
    d = jax.lax.cond(y[0] > 0, lambda a: a * 3.0, lambda a: -a, x)  # per-run predicate: a select
    n = jax.lax.fori_loop(0, 3, lambda i, c: c * 0.5 + jnp.float64(i), w)  # a scan
    e = jnp.einsum("ij,kj->ik", P, M[:, :3])  # contraction over the minor axis of both
    i = jnp.asarray(s > 0, jnp.int32)  # a start index shared by the runs
    left, right = jnp.split(P, [1], axis=1)
    f = jnp.concatenate([A[0], jax.lax.dynamic_slice(w, (i,), (2,)), right[0], left[:, 0]])  # shared operand first
    return {"z": z, "c": c, "d": d, "n": n, "e": e, "A": A.T @ A, "soft": _soft_abs(y), "det": jnp.prod(jnp.diag(L)),
            "f": f}


def test_runs_last_agrees_with_vmap_in_values_and_derivatives():
    rng = np.random.default_rng(1)
    B = 5
    x, P = rng.normal(size=(B, 3)), rng.normal(size=(B, 3, 3))
    A, s = rng.normal(size=(3, 3)), 0.7
    ref = jax.vmap(one_run, in_axes=(0, 0, None, None))(x, P, A, s)
    out_axes = {k: (None if k == "A" else -1) for k in ref}
    got = jax.jit(runs_last(one_run, in_axes=(-1, -1, None, None), out_axes=out_axes))(x.T, np.moveaxis(P, 0, -1), A, s)
    for k in ref:
        g = np.asarray(got[k])[None] if k == "A" else np.moveaxis(np.asarray(got[k]), -1, 0)  # A: shared, once
        np.testing.assert_allclose(np.broadcast_to(g, ref[k].shape), ref[k], rtol=1e-13, atol=1e-13, err_msg=k)

    def loss(batch, A, s):
        x, P = batch
        if batch_last:
            out = runs_last(one_run, in_axes=(-1, -1, None, None), out_axes=out_axes)(x, P, A, s)
        else:
            out = jax.vmap(one_run, in_axes=(0, 0, None, None))(x, P, A, s)
            out["A"] = out["A"][0]  # the shared output once, as runs_last gives it
        return sum(jnp.sum(jnp.sin(v)) for v in jax.tree_util.tree_leaves(out))

    batch_last = False
    g_ref = jax.grad(loss, argnums=(0, 1, 2))((x, P), A, s)
    batch_last = True
    g_new = jax.grad(loss, argnums=(0, 1, 2))((x.T, np.moveaxis(P, 0, -1)), A, s)
    np.testing.assert_allclose(np.moveaxis(g_new[0][0], -1, 0), g_ref[0][0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.moveaxis(g_new[0][1], -1, 0), g_ref[0][1], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g_new[1], g_ref[1], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g_new[2], g_ref[2], rtol=1e-12, atol=1e-12)


def test_runs_last_refuses_a_shared_output_that_depends_on_the_runs():
    f = runs_last(lambda x, a: (x * a, a + x.sum()), in_axes=(-1, None), out_axes=(-1, None))
    with pytest.raises(ValueError, match="shared"):
        f(np.ones((2, 4)), 1.0)


@pytest.mark.parametrize("varying", [("e", "x_sum", "nu", "e_pred"), ("e", "Pe", "x_sum", "nu", "S", "valid", "e_pred")])
def test_the_errors_carried_once_are_the_same_in_every_run(varying):
    """``lanes.errors_dependence``: the chunk carries a field of the errors once where it says the
    field is the same in every run. Error inputs of five runs that differ where ``varying`` says
    (a linear KF's: its covariance and S shared; an EKF's with a gate: every matrix per run): each
    field it calls shared is equal in every run; it calls the KF's variances and log det S shared,
    never a field outside ``MAY_BE_SHARED``, and nothing that reads a per-run input."""
    from tracklab.worlds.tracking.errors import MAY_BE_SHARED, ErrorInputs, errors_of
    from tracklab.worlds.tracking.lanes import errors_dependence

    rng = np.random.default_rng(3)
    G = rng.normal(size=(5, 4, 4))
    one = {"e": rng.normal(size=(5, 4)), "Pe": G @ np.swapaxes(G, 1, 2) + np.eye(4), "x_sum": rng.normal(size=5),
           "nu": rng.normal(size=(5, 2)), "S": G[:, :2, :2] @ np.swapaxes(G[:, :2, :2], 1, 2) + np.eye(2),
           "valid": rng.uniform(size=5) < 0.5, "dof": np.full(5, 2.0), "e_pred": rng.normal(size=(5, 2)),
           "validated": np.full(5, np.nan), "existence": np.full(5, np.nan)}
    runs = ErrorInputs(**{k: v if k in varying else np.broadcast_to(v[:1], v.shape) for k, v in one.items()})
    shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), runs)
    flags = [k in varying for k in ErrorInputs._fields]
    shared = errors_dependence(shapes, flags, jnp.float64)
    errors = jax.vmap(lambda a: errors_of(a, jnp.float64))(runs)
    for name, s, v in zip(shared._fields, shared, errors):
        assert not s or name in MAY_BE_SHARED
        if s:
            np.testing.assert_array_equal(np.asarray(v), np.broadcast_to(np.asarray(v)[:1], np.shape(v)), err_msg=name)
    reads = {"var": {"Pe"}, "logdet_s": {"S", "valid"}, "valid": {"valid"}}  # of the inputs, beside the constants
    assert {n for n, s in zip(shared._fields, shared) if s} == {n for n in MAY_BE_SHARED
                                                                if not reads.get(n, set()) & set(varying)}
