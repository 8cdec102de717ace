"""Small dense linear algebra written as elementwise arithmetic.

Filters work on matrices of a few rows (n ≤ 9, m ≤ 3) batched over thousands of
Monte-Carlo runs. XLA on CPU runs batched LAPACK calls (cholesky, solve) and
batched dot_general on such tiny matrices slowly, while elementwise arithmetic
over the run axis vectorises well. These routines unroll the loops over rows at
trace time (the sizes are static), so under ``vmap`` every operation is an
elementwise operation on (runs, …) arrays. Within ``elementwise_products`` (the
engine's per-run filter steps) products up to 4 × 4 go one step further: element
by element, so that every operation is on a run-length vector.
"""

from __future__ import annotations

import contextlib
import math
import threading

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


def _elements(A):
    """The elements of a small 2-D array as a nested list of scalars; NumPy values for an
    array known at trace time."""
    c = _concrete(A)
    if c is not None:
        return [[c[i, j] for j in range(A.shape[1])] for i in range(A.shape[0])]
    n, m = A.shape
    return [[jax.lax.squeeze(jax.lax.slice(A, (i, j), (i + 1, j + 1)), (0, 1)) for j in range(m)] for i in range(n)]


def _from_elements(rows, dtype):
    """The (n, m) array of a nested list of scalars (inverse of ``_elements``)."""
    return jnp.stack([jnp.stack([jnp.asarray(v, dtype) for v in r]) for r in rows])


SCALAR_TERMS = 64  # the most multiply terms a product is written out element by element (4 × 4 × 4)
_FORM = threading.local()  # whether products are written element by element (trace time)


@contextlib.contextmanager
def elementwise_products(on: bool = True):
    """Within this context (at trace time), ``mm`` and ``symmetrise`` write products of up to
    ``SCALAR_TERMS`` terms element by element.

    Element by element, every operation of a filter vmapped over runs is on a run-length
    vector, which XLA's loops over the runs vectorise: the lidar EKF runs 1.4–1.9× faster end
    to end than with (runs, n, n) arrays, whose loops run over n-long rows. It costs
    compile time (about a third more for a 4-state filter) and makes reverse-mode gradients
    slow to compile, so the engine turns it on only around the per-run filter steps of a
    Monte-Carlo chunk.
    """
    before = getattr(_FORM, "on", False)
    _FORM.on = on
    try:
        yield
    finally:
        _FORM.on = before


def _elementwise() -> bool:
    """Whether products are written element by element here (see ``elementwise_products``)."""
    return getattr(_FORM, "on", False)


def mm(A, B):
    """Matrix product of small matrices.

    A sum of outer products, one per inner index: under ``vmap`` each term is an
    elementwise multiply, with no reduction. Within ``elementwise_products`` a product
    of up to ``SCALAR_TERMS`` multiply terms (a 4 × 4 product) is instead written out
    element by element, each element a chain of multiply-adds of single elements
    (larger ones would compile slowly: a 9 × 9 product is 729 terms). Either way, terms
    whose factor is known to be zero at trace time (the structural zeros of F, H, G)
    are skipped.
    """
    vec_a, vec_b = A.ndim == 1, B.ndim == 1
    A2 = A[None, :] if vec_a else A
    B2 = B[:, None] if vec_b else B
    ca, cb = _concrete(A2), _concrete(B2)
    dtype = jnp.result_type(A, B)
    n, K, m = A2.shape[0], A2.shape[1], B2.shape[1]
    nonzero = np.ones((n, K, m), bool)
    if ca is not None:
        nonzero &= (ca != 0)[:, :, None]
    if cb is not None:
        nonzero &= (cb != 0)[None, :, :]
    if _elementwise() and nonzero.sum() <= SCALAR_TERMS:
        ea, eb = _elements(A2), _elements(B2)
        out = _from_elements([[_dot_terms([(ea[i][k], eb[k][j]) for k in range(K) if nonzero[i, k, j]], dtype)
                              for j in range(m)] for i in range(n)], dtype)
    else:
        out = None
        for k in range(K):
            if not nonzero[:, k, :].any():
                continue
            t = A2[:, k, None] * B2[None, k, :]
            out = t if out is None else out + t
        if out is None:
            out = jnp.zeros((n, m), dtype)
    if vec_a:
        return out[0]
    if vec_b:
        return out[:, 0]
    return out


def _dot_terms(pairs, dtype):
    """Σ a·b over the pairs, with lax's elementwise ops (cheap to trace); a factor known to be 1 is
    not multiplied."""
    def cast(v):
        if isinstance(v, np.generic):
            return np.asarray(v, dtype)
        return v if v.dtype == dtype else jax.lax.convert_element_type(v, dtype)

    acc = None
    for a, b in pairs:
        if isinstance(a, np.generic) and isinstance(b, np.generic):
            t = np.asarray(a * b, dtype)
        elif isinstance(a, np.generic) and a == 1:
            t = cast(b)
        elif isinstance(b, np.generic) and b == 1:
            t = cast(a)
        else:
            t = jax.lax.mul(cast(a), cast(b))
        acc = t if acc is None else jax.lax.add(acc, t)
    return np.zeros((), dtype) if acc is None else acc


def symmetrise(P):
    """(P + Pᵀ)/2; element by element up to 4 × 4 within ``elementwise_products``."""
    if not _elementwise() or P.ndim != 2 or P.shape[-1] > 4:
        return 0.5 * (P + jnp.swapaxes(P, -1, -2))
    e = _elements(P)
    n = len(e)
    return _from_elements([[e[i][i] if i == j else 0.5 * (e[i][j] + e[j][i]) for j in range(n)] for i in range(n)],
                          P.dtype)


def jacobian(f, x):
    """∂f/∂x of f: (n,) -> (m,) at x, one forward-mode column per state component.

    ``jax.jacfwd`` pushes the n tangents through f as one batch: under ``vmap`` over runs
    each intermediate is then a (runs, n) array. Column by column every intermediate is
    a run-length vector, as in ``mm``.
    """
    _, f_jvp = jax.linearize(f, x)  # f traced once, its linear map applied to each unit tangent
    eye = np.eye(x.shape[0], dtype=x.dtype)
    return jnp.stack([f_jvp(e) for e in eye], axis=-1)


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
    theta = math.exp((math.lgamma(degree + 2) - 16 * math.log(10)) / (degree + 1))
    norm1 = jnp.max(jnp.sum(jnp.abs(A), axis=-2))
    s = jnp.clip(jnp.ceil(jnp.log2(norm1 / theta)), 0, max_squarings)
    X = A / 2.0**s
    eye = jnp.eye(n, dtype=A.dtype)
    # loops, not unrolled products: a few kernels to compile, whatever the degree
    E = jax.lax.fori_loop(0, degree, lambda i, E: eye + mm(X, E) / (degree - i).astype(A.dtype), eye)  # Horner
    E = jax.lax.fori_loop(0, max_squarings, lambda i, E: jnp.where(i < s, mm(E, E), E), E)
    return jnp.where(norm1 <= theta * 2.0**max_squarings, E, jnp.nan)
