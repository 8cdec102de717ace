"""Small dense linear algebra written as elementwise arithmetic.

Filters work on matrices of a few rows (n ≤ 9, m ≤ 3) batched over thousands of
Monte-Carlo runs. XLA on CPU runs batched LAPACK calls (cholesky, solve) and
batched dot_general on such tiny matrices slowly, while elementwise arithmetic
over the run axis vectorises well. These routines unroll the loops over rows at
trace time (the sizes are static), so under ``vmap`` every operation is an
elementwise operation on (runs, …) arrays.
"""

from __future__ import annotations

import math

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
    """Matrix product of small matrices.

    A sum of outer products, one per inner index: under ``vmap`` each term is an
    elementwise multiply, with no reduction. When one factor is known at trace time (F, H, G,
    their transposes), each output row (column) is made of that factor's nonzero entries only,
    a 1 not multiplied (``_known_times``): a constant-velocity F P Fᵀ costs 16 products instead
    of 128.
    """
    vec_a, vec_b = A.ndim == 1, B.ndim == 1
    A2 = A[None, :] if vec_a else A
    B2 = B[:, None] if vec_b else B
    ca, cb = _concrete(A2), _concrete(B2)
    dtype = jnp.result_type(A, B)
    n, K, m = A2.shape[0], A2.shape[1], B2.shape[1]
    if ca is not None:
        out = _known_times(ca, B2, dtype)
    elif cb is not None:
        out = _known_times(cb.T, A2.T, dtype).T
    else:  # column k of A times row k of B, each one static slice
        out = jnp.zeros((n, m), dtype) if K == 0 else None
        for k in range(K):
            t = jax.lax.slice_in_dim(A2, k, k + 1, axis=1) * jax.lax.slice_in_dim(B2, k, k + 1, axis=0)
            out = t if out is None else out + t
    if vec_a or vec_b:
        return jnp.reshape(out, (m,) if vec_a else (n,))
    return out


def _known_times(C, B, dtype):
    """C B for a C known at trace time (a NumPy array): row i is Σₖ C[i, k] B[k] over the k where
    C[i, k] ≠ 0, in increasing k, a factor of 1 not multiplied. Where B is finite this is ``mm``'s
    sum of outer products to the bit (its skipped terms add exact zeros); a structurally sparse C
    (a transition matrix, a selection matrix) costs its nonzero entries only."""
    rows = []
    for i in range(C.shape[0]):
        acc = None
        for k in np.flatnonzero(C[i]):
            t = B[k].astype(dtype) if C[i, k] == 1 else np.asarray(C[i, k]) * B[k]
            acc = t if acc is None else acc + t
        rows.append(jnp.zeros(B.shape[1:], dtype) if acc is None else acc)
    return jnp.stack(rows)


def symmetrise(P):
    """(P + Pᵀ)/2."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


def jacobian(f, x, columns=None):
    """∂f/∂x of f: (n,) -> (m,) at x, one forward-mode column per state component; with
    ``columns`` (a tuple of components) only theirs, (m, len(columns)).

    ``jax.jacfwd`` pushes the n tangents through f as one batch: under ``vmap`` over runs
    each intermediate is then a (runs, n) array. Column by column every intermediate is
    a run-length vector, as in ``mm``.
    """
    _, f_jvp = jax.linearize(f, x)  # f traced once, its linear map applied to each unit tangent
    eye = np.eye(x.shape[0], dtype=x.dtype)
    return jnp.stack([f_jvp(eye[k]) for k in (range(x.shape[0]) if columns is None else columns)], axis=-1)


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


def pick(a, idx, axis=0):
    """``a``'s entries ``idx`` (known at trace time) along ``axis`` by static slices, which fuse
    with what reads them (indexing by an index array is a gather, a kernel of its own)."""
    idx = [int(i) for i in idx]
    if idx == list(range(idx[0], idx[0] + len(idx))):
        return jax.lax.slice_in_dim(a, idx[0], idx[0] + len(idx), axis=axis)
    return jnp.stack([jax.lax.index_in_dim(a, i, axis, keepdims=False) for i in idx], axis=axis)


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


def _ldl_whitened(A, v):
    """(Σⱼ yⱼ² / Dⱼ, [Dⱼ]) for A = L D Lᵀ, L unit lower triangular and L y = v: no square root
    and one division a row, where a Cholesky factor takes a square root and a division a row and
    its forward substitution another division (NaN from the first Dⱼ ≤ 0: A not positive
    definite)."""
    n = A.shape[-1]
    zero = jnp.zeros_like(A[0, 0])
    W = [[None] * n for _ in range(n)]  # W[i][k] = L[i][k] Dₖ, k < i
    L = [[None] * n for _ in range(n)]
    D, y, total = [], [], None
    for j in range(n):
        d = A[j, j] - sum((L[j][k] * W[j][k] for k in range(j)), zero)
        d = jnp.where(d > 0, d, jnp.nan)
        inv_d = 1.0 / d
        for i in range(j + 1, n):
            W[i][j] = A[i, j] - sum((W[i][k] * L[j][k] for k in range(j)), zero)
            L[i][j] = W[i][j] * inv_d
        y.append(v[j] - sum((L[j][k] * y[k] for k in range(j)), zero))
        t = y[j] * y[j] * inv_d
        total = t if total is None else total + t
        D.append(d)
    return total, D


def mahalanobis2(A, v):
    """vᵀ A⁻¹ v for symmetric positive-definite A (NaN if A is not), by A = L D Lᵀ."""
    return _ldl_whitened(A, v)[0]


def mahalanobis2_logdet(A, v):
    """(vᵀ A⁻¹ v, log det A) for symmetric positive-definite A (NaN if A is not), by A = L D Lᵀ:
    log det A = Σⱼ log Dⱼ."""
    m2, D = _ldl_whitened(A, v)
    logdet = jnp.log(D[0])
    for d in D[1:]:
        logdet = logdet + jnp.log(d)
    return m2, logdet


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


def solve(A, B):
    """A⁻¹ B for a small square A, by Gauss–Jordan elimination without pivoting (unrolled).

    For matrices whose leading principal minors stay well away from zero, such as a state
    transition over a short interval (the identity plus small terms): under ``vmap``,
    ``jnp.linalg.solve`` is a LAPACK call per run. B is (n,) or (n, k).
    """
    vec = B.ndim == 1
    n = A.shape[-1]
    rows = [jnp.concatenate([A[i], B[i:i + 1] if vec else B[i]]) for i in range(n)]
    for j in range(n):
        pivot = rows[j] / rows[j][j]
        rows = [pivot if i == j else rows[i] - rows[i][j] * pivot for i in range(n)]
    out = jnp.stack([r[n:] for r in rows])
    return out[:, 0] if vec else out


def _taylor_theta(degree):
    """The largest 1-norm θ at which the Taylor polynomial of ``degree`` is exact to double precision
    (θ^(degree+1)/(degree+1)! ≤ 10⁻¹⁶; 0.068 for degree 8)."""
    return math.exp((math.lgamma(degree + 2) - 16 * math.log(10)) / (degree + 1))


def host_expm(A, degree=8):
    """``expm``'s scaling and squaring in float64 NumPy on the host, as many squarings as the norm
    needs: for the few exponentials a world's parameters are built from (an eager
    ``jax.scipy.linalg.expm`` compiles a program for each of its operations, about 1 s)."""
    A = np.asarray(A, np.float64)
    norm1 = np.abs(A).sum(axis=0).max()
    s = int(np.ceil(np.log2(norm1 / _taylor_theta(degree)))) if norm1 > 0 else 0
    X = A / 2.0 ** max(s, 0)
    eye = np.eye(A.shape[-1])
    E = eye
    for i in range(degree):  # Horner
        E = eye + X @ E / (degree - i)
    for _ in range(max(s, 0)):
        E = E @ E
    return E


def expm(A, degree=8, max_squarings=10):
    """The matrix exponential of a small square A by scaling and squaring a Taylor polynomial.

    A is scaled by 2⁻ˢ to a 1-norm θ at most where the polynomial of ``degree`` is exact to
    double precision (θ^(degree+1)/(degree+1)! ≤ 10⁻¹⁶ relative; 0.068 for degree 8), the
    polynomial is evaluated by Horner's rule and squared s times (s from the norm, at most
    ``max_squarings``). Every step is a product (``mm``): under ``vmap``,
    ``jax.scipy.linalg.expm`` evaluates every Padé degree its switch may pick and a LAPACK
    solve per run. NaN where the norm needs more than ``max_squarings`` squarings.
    """
    n = A.shape[-1]
    theta = _taylor_theta(degree)
    norm1 = jnp.max(jnp.sum(jnp.abs(A), axis=-2))
    s = jnp.clip(jnp.ceil(jnp.log2(norm1 / theta)), 0, max_squarings)
    X = A / 2.0**s
    eye = jnp.eye(n, dtype=A.dtype)
    # loops, not unrolled products: a few kernels to compile, whatever the degree
    E = jax.lax.fori_loop(0, degree, lambda i, E: eye + mm(X, E) / (degree - i).astype(A.dtype), eye)  # Horner
    E = jax.lax.fori_loop(0, max_squarings, lambda i, E: jnp.where(i < s, mm(E, E), E), E)
    return jnp.where(norm1 <= theta * 2.0**max_squarings, E, jnp.nan)
