"""Small dense linear algebra written as elementwise arithmetic.

Filters work on matrices of a few rows (n ≤ 9, m ≤ 3) batched over thousands of
Monte-Carlo runs. XLA on CPU runs batched LAPACK calls (cholesky, solve) and
batched dot_general on such tiny matrices slowly, while elementwise arithmetic
over the run axis vectorises well. These routines unroll the loops over rows at
trace time (the sizes are static), so under ``vmap`` every operation is an
elementwise operation on run-length vectors.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _concrete(A):
    """A's values when they are known at trace time (a NumPy array or a constant), else None."""
    if isinstance(A, np.ndarray):
        return A
    if isinstance(A, jax.Array) and not isinstance(A, jax.core.Tracer):
        return np.asarray(A)
    return None


def mm(A, B):
    """Matrix product of small matrices: a sum of outer products, one per inner index.

    Each term is an elementwise multiply of a column of A and a row of B, so under
    ``vmap`` there is no reduction at all (XLA on CPU runs the reductions of a
    broadcast-and-sum product slowly). Terms whose column of A or row of B is known to
    be zero at trace time (the structural zeros of F, H, G) are skipped.
    """
    vec_a, vec_b = A.ndim == 1, B.ndim == 1
    A2 = A[None, :] if vec_a else A
    B2 = B[:, None] if vec_b else B
    ca, cb = _concrete(A2), _concrete(B2)
    acc = None
    for k in range(A2.shape[1]):
        if (ca is not None and not ca[:, k].any()) or (cb is not None and not cb[k, :].any()):
            continue
        t = A2[:, k, None] * B2[None, k, :]
        acc = t if acc is None else acc + t
    if acc is None:
        acc = jnp.zeros((A2.shape[0], B2.shape[1]), jnp.result_type(A, B))
    if vec_a:
        return acc[0]
    if vec_b:
        return acc[:, 0]
    return acc


def cholesky(A):
    """Lower Cholesky factor; NaN wherever A is not (numerically) positive definite."""
    n = A.shape[-1]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        s = A[j, j] - sum((L[j][k] ** 2 for k in range(j)), jnp.zeros_like(A[j, j]))
        d = jnp.sqrt(jnp.where(s > 0, s, jnp.nan))
        L[j][j] = d
        for i in range(j + 1, n):
            t = A[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), jnp.zeros_like(A[i, j]))
            L[i][j] = t / d
    zero = jnp.zeros_like(A[0, 0])
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


def _forward(L, v):
    n = L.shape[-1]
    y = []
    for i in range(n):
        t = v[i] - sum((L[i, k] * y[k] for k in range(i)), jnp.zeros_like(v[i]))
        y.append(t / L[i, i])
    return jnp.stack(y)


def sum_elements(v):
    """The sum of a short vector's elements as a chain of elementwise adds.

    Under ``vmap`` a ``jnp.sum`` over a few elements per run becomes a reduction
    kernel of its own; a chain of adds fuses with what surrounds it.
    """
    acc = v[0]
    for i in range(1, v.shape[0]):
        acc = acc + v[i]
    return acc


def norm(v):
    """Euclidean norm of a short vector (elementwise, see ``sum_elements``)."""
    return jnp.sqrt(sum_elements(v * v))


def mahalanobis2(A, v):
    """vᵀ A⁻¹ v for symmetric positive-definite A (NaN if A is not)."""
    y = _forward(cholesky(A), v)
    return sum_elements(y * y)


def mahalanobis2_logdet(A, v):
    """(vᵀ A⁻¹ v, log det A) for symmetric positive-definite A (NaN if A is not)."""
    L = cholesky(A)
    y = _forward(L, v)
    return sum_elements(y * y), 2.0 * sum_elements(jnp.log(jnp.diagonal(L)))


def spd_inverse(A):
    """Inverse of a small symmetric positive-definite matrix via its Cholesky factor."""
    n = A.shape[-1]
    if n == 1:
        return 1.0 / A
    if n == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return jnp.stack([jnp.stack([A[1, 1], -A[0, 1]]), jnp.stack([-A[1, 0], A[0, 0]])]) / det
    L = cholesky(A)
    eye = jnp.eye(n, dtype=A.dtype)
    Linv = jnp.stack([_forward(L, eye[:, j]) for j in range(n)], axis=1)  # columns of L⁻¹
    return mm(Linv.T, Linv)
