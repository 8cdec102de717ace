"""The checks the public Python functions make of their arguments, before anything compiles.

Each refusal is one line, as a bad experiment file's: ``function: argument = value: what is
allowed``. A value of the wrong kind raises ``TypeError`` (a string where a filter is expected),
a value of the right kind outside what is allowed ``ConfigError`` (a ``ValueError``: dt = nan, a
covariance that is not positive definite). Arrays are checked in NumPy, whole batches at once;
a refusal names the first element at fault (``P0[3]``, ``z[0, 7, 1]``).
"""

from __future__ import annotations

import numbers

import numpy as np

from tracklab.errors import ConfigError
from tracklab.filters.core import Filter

PRECISIONS = ("float64", "float32")
SYMMETRY_RTOL = 1e-9  # |P - Pᵀ| allowed, relative to P's largest entry (float64; more for float32 input)


class _Text(str):
    """A value as a refusal shows it, already written out (``ConfigError`` quotes its repr)."""

    def __repr__(self):
        return str(self)


def brief(value, limit: int = 120) -> str:
    """``value`` written out in one line, an array's entries elided past a few."""
    a = None
    if isinstance(value, (np.ndarray, np.generic)) or (hasattr(value, "shape") and hasattr(value, "dtype")):
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


def refuse(where: str, name: str, value, allowed: str) -> ConfigError:
    """The ``ValueError`` of an argument outside what is allowed."""
    return ConfigError(where, name, _Text(brief(value)), allowed)


def wrong_type(where: str, name: str, value, allowed: str) -> TypeError:
    """The ``TypeError`` of an argument of the wrong kind."""
    return TypeError(f"{where}: {name} = {brief(value)} ({type(value).__name__}): {allowed}")


def check_filter(where: str, name: str, flt) -> Filter:
    """``flt`` if it is a ``tracklab.Filter`` with callable ``init`` and ``step``; else ``TypeError``."""
    if isinstance(flt, Filter) and callable(flt.init) and callable(flt.step):
        return flt
    hint = ""
    if isinstance(flt, str):
        hint = f" (a built-in kind is built with tracklab.filters.build({flt!r}, model, sensor, params))"
    raise wrong_type(where, name, flt, f"must be a tracklab.Filter(init, step, params){hint}")


def check_precision(where: str, precision, name: str = "precision") -> str:
    if isinstance(precision, str) and precision in PRECISIONS:
        return precision
    raise refuse(where, name, precision, f"must be one of {', '.join(repr(p) for p in PRECISIONS)}")


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
        if hasattr(a, "shape") and hasattr(a, "dtype"):  # a JAX tracer: no values to check
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


def check_finite(where: str, name: str, a) -> np.ndarray:
    """``a`` as a float64 array if every entry is finite (a mean, a truth)."""
    arr = numeric(where, name, a)
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.argmax(bad.ravel()))
        raise refuse(where, _at(name, arr.shape, i), arr.ravel()[i], "must be finite (no NaN or ±inf)")
    return arr


def check_measurements(where: str, name: str, z) -> np.ndarray:
    """``z`` as a float64 array if it holds no ±inf (a NaN is an absent measurement)."""
    arr = numeric(where, name, z)
    bad = np.isinf(arr)
    if bad.any():
        i = int(np.argmax(bad.ravel()))
        raise refuse(where, _at(name, arr.shape, i), arr.ravel()[i],
                     "must be finite or NaN (a row of NaN is a missed detection), not ±inf")
    return arr


def check_covariance(where: str, name: str, P) -> np.ndarray:
    """``P`` as a float64 array if it is (…, n, n) with every matrix finite, symmetric (to
    ``SYMMETRY_RTOL`` of its largest entry; eight epsilons of a float32 input's dtype) and
    positive definite (its Cholesky factorisation succeeds): each of a batch checked."""
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
    try:
        np.linalg.cholesky(flat)
    except np.linalg.LinAlgError:
        low = np.linalg.eigvalsh(0.5 * (flat + np.swapaxes(flat, -1, -2)))[:, 0]
        bad = low <= 0
        i = int(np.argmax(bad)) if bad.any() else int(np.argmin(low / np.maximum(scale, np.finfo(float).tiny)))
        raise refuse(where, each(i), flat[i], f"must be positive definite (its Cholesky factorisation fails; "
                     f"smallest eigenvalue {low[i]:.3g})") from None
    return arr
