"""The checks the public Python functions make of their arguments, before anything compiles.

Each refusal is one line, as a bad experiment file's: ``function: argument = value: what is
allowed``. A value of the wrong kind raises ``TypeError`` (a string where a filter is expected),
a value of the right kind outside what is allowed ``ConfigError`` (a ``ValueError``: dt = nan, a
covariance that is not positive definite). Arrays are checked in NumPy, whole batches at once;
a refusal names the first element at fault (``P0[3]``, ``z[0, 7, 1]``).
"""

from __future__ import annotations

import numbers
from typing import TYPE_CHECKING

import numpy as np

from tracklab.errors import ConfigError, failure

if TYPE_CHECKING:
    from tracklab.filters.core import Filter

PRECISIONS = ("float64", "float32")
SYMMETRY_RTOL = 1e-9  # |P - Pᵀ| allowed, relative to P's largest entry (float64; more for float32 input)


class _Text(str):
    """A value as a refusal shows it, already written out (``ConfigError`` quotes its repr)."""

    def __repr__(self):
        return str(self)

MAX_RUNS = 100_000_000  # runs of one call, from a file or from Python
MAX_RUN_STEPS = 10**12  # runs × steps of one call


def _shaped(a) -> bool:
    """Whether ``a`` looks like an array (a shape and a dtype: NumPy's, JAX's, a tracer)."""
    return hasattr(a, "shape") and hasattr(a, "dtype")


def brief(value, limit: int = 120) -> str:
    """``value`` written out in one line, an array's entries elided past a few."""
    a = None
    if isinstance(value, (np.ndarray, np.generic)) or _shaped(value):
        try:
            a = np.asarray(value)
        except Exception:  # noqa: BLE001 - shaped, but no array: written as its repr
            a = None
    if a is not None and a.dtype.kind in "biufc":
        text = " ".join(np.array2string(a, threshold=16, edgeitems=2, precision=6, separator=", ",
                                        max_line_width=10**6).split())
        return text if a.ndim == 0 else f"{text} (shape {a.shape})"
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def shape_of(a) -> _Text:
    """An array as a refusal about its shape shows it: ``a (10, 3) array``."""
    return _Text(f"a {tuple(np.shape(a))} array")


def kind_of(value) -> _Text:
    """A value of the wrong kind as a refusal shows it: written out, then its type (``'x' (str)``)."""
    return _Text(f"{brief(value)} ({type(value).__name__})")


def refuse(where: str, name: str, value, allowed: str) -> ConfigError:
    """The ``ValueError`` of an argument outside what is allowed."""
    return ConfigError(where, name, _Text(brief(value)), allowed)


def wrong_type(where: str, name: str, value, allowed: str) -> TypeError:
    """The ``TypeError`` of an argument of the wrong kind."""
    return TypeError(f"{where}: {name} = {kind_of(value)}: {allowed}")


def check_filter(where: str, name: str, flt) -> Filter:
    """``flt`` if it is a ``tracklab.Filter`` with callable ``init`` and ``step``; else ``TypeError``."""
    from tracklab.filters.core import Filter  # tracklab.filters' factories use these checks

    if isinstance(flt, Filter) and callable(flt.init) and callable(flt.step):
        return flt
    hint = ""
    if isinstance(flt, str):
        hint = f" (a built-in kind is built with tracklab.filters.build({flt!r}, model, sensor, params))"
    raise wrong_type(where, name, flt, f"must be a tracklab.Filter(init, step, params){hint}")


def check_precision(where: str, precision, name: str = "precision", *, optional: bool = False) -> str | None:
    """``precision`` if it is "float64" or "float32" (``optional``: None passes as None)."""
    if precision is None and optional:
        return None
    if isinstance(precision, str) and precision in PRECISIONS:
        return precision
    allowed = f"must be one of {', '.join(repr(p) for p in PRECISIONS)}"
    raise refuse(where, name, precision, allowed + (" (or None)" if optional else ""))


def is_real(value) -> bool:
    """Whether ``value`` is one real number (not a bool; a 0-d array of one counts)."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, numbers.Real):
        return True
    return np.ndim(value) == 0 and np.asarray(value).dtype.kind in "iuf"


def check_positive(where: str, name: str, value) -> float:
    """``value`` as a float if it is a finite real number > 0 (a step, a learning rate)."""
    if not is_real(value):
        raise wrong_type(where, name, value, "must be a finite number > 0")
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise refuse(where, name, value, "must be a finite number > 0")
    return v


def check_count(where: str, name: str, value, lo: int = 1, hi: int | None = None, *, optional: bool = False):
    """``value`` as an int if it is an integer in [lo, hi] (``optional``: None passes as None)."""
    if value is None and optional:
        return None
    allowed = f"must be an integer >= {lo}" if hi is None else f"must be an integer in [{lo}, {hi}]"
    if optional:
        allowed += " (or None)"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise wrong_type(where, name, value, allowed)
    if value < lo or (hi is not None and value > hi):
        raise refuse(where, name, value, allowed)
    return int(value)


def numeric(where: str, name: str, a) -> np.ndarray:
    """``a`` as a float64 array, ``TypeError`` if it is not numbers."""
    try:
        arr = np.asarray(a)
    except Exception:  # noqa: BLE001 - whatever the object is, it is not an array of numbers
        if is_traced(a):  # no values to check
            raise wrong_type(where, name, a, "must be a concrete array of real numbers (its values are checked "
                             "before anything compiles: not a value traced inside jit, grad or vmap)") from None
        arr = None
    if arr is None or arr.dtype.kind not in "iuf":
        raise wrong_type(where, name, a, "must be an array of real numbers")
    return arr.astype(np.float64, copy=False)


def _at(name: str, shape, flat_index: int) -> str:
    """``name[i, j]``: the element of ``shape`` at a flat index (``name`` itself for a scalar)."""
    if not shape:
        return name
    return f"{name}[{', '.join(str(int(i)) for i in np.unravel_index(flat_index, shape))}]"


def _refuse_first(where: str, name: str, arr: np.ndarray, bad: np.ndarray, allowed: str) -> np.ndarray:
    """``arr``, or the refusal of its first entry marked ``bad``, named by its index."""
    if bad.any():
        i = int(np.argmax(bad.ravel()))
        raise refuse(where, _at(name, arr.shape, i), arr.ravel()[i], allowed)
    return arr


def check_finite(where: str, name: str, a) -> np.ndarray:
    """``a`` as a float64 array if every entry is finite (a mean, a truth)."""
    arr = numeric(where, name, a)
    return _refuse_first(where, name, arr, ~np.isfinite(arr), "must be finite (no NaN or ±inf)")


def check_measurements(where: str, name: str, z) -> np.ndarray:
    """``z`` as a float64 array if it holds no ±inf (a NaN is an absent measurement)."""
    arr = numeric(where, name, z)
    return _refuse_first(where, name, arr, np.isinf(arr),
                         "must be finite or NaN (a row of NaN is a missed detection), not ±inf")


def is_traced(a) -> bool:
    """Whether ``a`` is a value traced inside ``jit``, ``grad`` or ``vmap`` (its shape known, its values not)."""
    if not _shaped(a) or isinstance(a, (np.ndarray, np.generic)):
        return False
    import jax

    return isinstance(a, jax.core.Tracer)


def check_covariance(where: str, name: str, P, *, semidefinite: bool = False) -> np.ndarray:
    """``P`` as a float64 array if it is (…, n, n) with every matrix finite, symmetric (to
    ``SYMMETRY_RTOL`` of its largest entry; eight epsilons of a float32 input's dtype) and
    positive definite (its Cholesky factorisation succeeds): each of a batch checked.
    ``semidefinite``: positive semi-definite instead (a process noise G Gᵀ q is singular), its
    smallest eigenvalue no more negative than that same tolerance of its largest entry."""
    arr = numeric(where, name, P)
    if arr.ndim < 2 or arr.shape[-1] != arr.shape[-2] or arr.shape[-1] == 0:
        raise refuse(where, name, arr, "must be a square (n, n) covariance matrix, or a stack (…, n, n) of them")
    lead = arr.shape[:-2]
    flat = arr.reshape((-1,) + arr.shape[-2:])

    def each(i):
        return name if not lead else _at(name, lead, i)

    finite = np.isfinite(flat).all(axis=(-2, -1))
    if not finite.all():
        i = int(np.argmin(finite))
        raise refuse(where, each(i), flat[i], "must be finite (no NaN or ±inf)")
    dtype = np.asarray(P).dtype
    rtol = max(SYMMETRY_RTOL, 8 * float(np.finfo(dtype if dtype.kind == "f" else np.float64).eps))
    scale = np.abs(flat).max(axis=(-2, -1))
    asym = np.abs(flat - np.swapaxes(flat, -1, -2)).max(axis=(-2, -1))
    bad = asym > rtol * scale
    if bad.any():
        i = int(np.argmax(bad))
        raise refuse(where, each(i), flat[i], f"must be symmetric (|P - Pᵀ| reaches {asym[i]:.3g}, more than "
                     f"{rtol:.0e} of its largest entry {scale[i]:.3g})")
    if semidefinite:
        low = np.linalg.eigvalsh(0.5 * (flat + np.swapaxes(flat, -1, -2)))[:, 0]
        bad = low < -rtol * scale
        if bad.any():
            i = int(np.argmax(bad))
            raise refuse(where, each(i), flat[i], f"must be positive semi-definite (smallest eigenvalue {low[i]:.3g}, "
                         f"below -{rtol:.0e} of its largest entry {scale[i]:.3g})")
        return arr
    try:
        np.linalg.cholesky(flat)
    except np.linalg.LinAlgError:
        low = np.linalg.eigvalsh(0.5 * (flat + np.swapaxes(flat, -1, -2)))[:, 0]
        bad = low <= 0
        i = int(np.argmax(bad)) if bad.any() else int(np.argmin(low / np.maximum(scale, np.finfo(float).tiny)))
        raise refuse(where, each(i), flat[i], f"must be positive definite (its Cholesky factorisation fails; "
                     f"smallest eigenvalue {low[i]:.3g})") from None
    return arr


def check_matrix(where: str, name: str, a, shape: tuple, allowed: str, *, covariance: str | None = None):
    """``a`` if it is an array of real numbers of ``shape`` (an entry None: any size >= 1), every
    entry finite; ``covariance`` "definite" or "semidefinite": also a symmetric positive (semi-)
    definite matrix (``check_covariance``). ``allowed`` says what the shape is. A value traced
    inside ``jit``, ``grad`` or ``vmap`` has its shape checked alone (its values are not known)."""
    if not is_traced(a):
        arr = numeric(where, name, a)
    elif np.dtype(a.dtype).kind not in "iuf":
        raise wrong_type(where, name, a, "must be an array of real numbers")
    else:
        arr = None
    got = tuple(np.shape(a))
    if len(got) != len(shape) or any(w is not None and g != w for g, w in zip(got, shape)) or 0 in got:
        raise refuse(where, name, arr if arr is not None else _Text(f"(traced, shape {got})"),
                     f"must be {allowed}")
    if arr is None:
        return a
    if covariance is not None:
        check_covariance(where, name, arr, semidefinite=covariance == "semidefinite")
    else:
        check_finite(where, name, arr)
    return a


def check_traces(where: str, name: str, fn, n: int, shape: tuple, allowed: str):
    """``fn`` if it is a function that, traced on a state of ``n`` components (shapes alone:
    nothing compiles), returns an array of ``shape`` (an entry None: any size >= 1); its shape."""
    if not callable(fn):
        raise wrong_type(where, name, fn, f"must be a function of the state, {allowed}")
    shown = _Text(getattr(fn, "__qualname__", None) or brief(fn))
    import jax
    import jax.numpy as jnp

    try:
        out = jax.eval_shape(fn, jax.ShapeDtypeStruct((n,), jnp.result_type(float)))
    except BaseException as e:  # noqa: BLE001 - the user's function: any error, a sys.exit too
        if isinstance(e, KeyboardInterrupt):
            raise
        raise refuse(where, name, shown, f"fails when traced on a state of {n} components: {failure(e)}") from None
    got = getattr(out, "shape", None)
    if got is None or len(got) != len(shape) or any(w is not None and g != w for g, w in zip(got, shape)) or 0 in got:
        what = f"shape {got}" if got is not None else type(out).__name__
        raise refuse(where, name, shown, f"returns {what} for a state of {n} components: must be {allowed}")
    return tuple(got)


KEY_FORMS = ("an integer seed in [0, 2**64 - 1], a JAX key (jax.random.key(seed)) or a raw uint32[2] key "
             "(jax.random.PRNGKey(seed))")


def check_key(where: str, name: str, key):
    """``key`` as the typed threefry-2x32 key the simulation draws with: from an integer seed s
    (the key ``jax.random.key(s)`` gives in 64-bit mode, in either precision), a typed key
    (``jax.random.key``) or a raw uint32[2] key (``jax.random.PRNGKey``, wrapped)."""
    import jax

    dtype = getattr(key, "dtype", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        shown = _Text(f"{dtype}[{', '.join(str(d) for d in np.shape(key))}]")  # as JAX writes it: key<fry>[2]
        if str(jax.random.key_impl(key)) != "threefry2x32":
            raise refuse(where, name, shown, "must be a threefry2x32 key (JAX's default: jax.random.key(seed)), the "
                         "generator the simulation draws with")
        if np.shape(key) != ():
            raise refuse(where, name, shown, "must be one key, of shape () (not a batch of them)")
        return key
    integer = isinstance(key, (numbers.Integral, np.integer)) or (dtype is not None and np.dtype(dtype).kind in "iu")
    if isinstance(key, (bool, np.bool_)) or not integer:
        raise wrong_type(where, name, key, f"must be {KEY_FORMS}")
    if np.ndim(key) == 0 and not is_traced(key):  # a seed
        seed = int(key)
        if not 0 <= seed < 2**64:
            raise refuse(where, name, key, f"must be {KEY_FORMS}")
        return jax.random.wrap_key_data(np.array([seed >> 32, seed & 0xFFFFFFFF], np.uint32), impl="threefry2x32")
    if np.shape(key) != (2,):
        raise wrong_type(where, name, key, f"must be {KEY_FORMS}")
    if not is_traced(key):
        data = np.asarray(key)
        if (data < 0).any() or (data > 0xFFFFFFFF).any():
            raise refuse(where, name, data, f"must be {KEY_FORMS}")
    return jax.random.wrap_key_data(jax.numpy.asarray(key, jax.numpy.uint32), impl="threefry2x32")


_ABSENT = object()  # an argument a factory does not take (None is a value given, and refused)


def check_columns(where: str, n: int, columns):
    """``columns`` (an update's state components, ``filters.blocks.innovation_update``) if it is
    None or a tuple of increasing components of a state of n; else one refusal."""
    if columns is None:
        return None
    if not (isinstance(columns, tuple) and columns and all(isinstance(k, int) and 0 <= k < n for k in columns)
            and list(columns) == sorted(set(columns))):
        raise refuse(where, "columns", columns, f"must be None or a tuple of increasing state components in 0..{n - 1}")
    return columns


def check_h_columns(where: str, h, n: int, columns):
    """``check_columns``, and that h reads no state component outside ``columns``: ∂h/∂x is zero
    outside them at three random states."""
    if check_columns(where, n, columns) is None:
        return
    import jax
    import jax.numpy as jnp

    others = [k for k in range(n) if k not in columns]
    for x in np.random.default_rng(0).normal(0.0, 1e3, (3, n)):
        J = np.asarray(jax.jacfwd(h)(jnp.asarray(x)))
        read = [k for k in others if np.any(J[:, k] != 0)]
        if read:
            raise refuse(where, "columns", columns, f"h reads state component {read[0]} as well "
                         f"(∂h/∂x[{read[0]}] is not zero): name every component h reads")


def check_state_space(where: str, *, Q, R, F=_ABSENT, H=_ABSENT, f=_ABSENT, h=_ABSENT, angle_mask=None,
                      columns=None):
    """A Gaussian state-space model as a filter factory takes it: x' = F x + w (or f(x) + w),
    z = H x + v (or h(x) + v), w ~ N(0, Q), v ~ N(0, R). Each matrix numbers, finite and of its
    shape: F (n, n), H (m, n), Q (n, n) symmetric positive semi-definite (a process noise
    G Gᵀ q is singular), R (m, m) symmetric positive definite; ``f`` and ``h`` functions of the
    state traced on shapes alone, f giving (n,) and h (m,); ``angle_mask`` (if given) m flags.
    n comes from F (or Q), m from H (or R). One ``TypeError``/``ValueError`` naming the argument."""
    if F is not _ABSENT:
        check_matrix(where, "F", F, (None, None), "a square (n, n) transition matrix")
        n = np.shape(F)[0]
        if np.shape(F)[1] != n:
            check_matrix(where, "F", F, (n, n), "a square (n, n) transition matrix")
    else:
        check_matrix(where, "Q", Q, (None, None), "a square (n, n) process-noise covariance")
        n = np.shape(Q)[0]
    if H is not _ABSENT:
        check_matrix(where, "H", H, (None, n), f"an (m, {n}) measurement matrix: a column per state component "
                     f"(n = {n}{', from F' if F is not _ABSENT else ''})")
        m = np.shape(H)[0]
    else:
        check_matrix(where, "R", R, (None, None), "a square (m, m) measurement-noise covariance")
        m = np.shape(R)[0]
    check_matrix(where, "Q", Q, (n, n), f"the ({n}, {n}) process-noise covariance of a state of n = {n}"
                 f"{' (from F)' if F is not _ABSENT else ''}", covariance="semidefinite")
    check_matrix(where, "R", R, (m, m), f"the ({m}, {m}) measurement-noise covariance of m = {m} measurement "
                 f"components{' (from H)' if H is not _ABSENT else ''}", covariance="definite")
    if f is not _ABSENT:
        check_traces(where, "f", f, n, (n,), f"x (n,) -> f(x) ({n},) (n = {n}, from Q)")
    if h is not _ABSENT:
        check_traces(where, "h", h, n, (m,), f"x (n,) -> h(x) ({m},) (m = {m}, from R)")
        check_h_columns(where, h, n, columns)
    if angle_mask is not None:
        flags = tuple(angle_mask) if isinstance(angle_mask, (list, tuple, np.ndarray)) else None
        if flags is None or len(flags) != m or not all(
                isinstance(a, (bool, np.bool_, numbers.Integral, np.integer)) and a in (0, 1) for a in flags):
            raise refuse(where, "angle_mask", angle_mask, f"must be None or a flag per measurement component, "
                         f"m = {m} (True: an angle, its innovation wrapped to (-π, π])")
