"""Experiment objects as pytrees: their numbers are leaves, everything else is structure.

A scenario, a sensor or an engagement is a frozen dataclass registered with
``jax.tree_util.register_dataclass``. Its numeric fields are leaves, so they
enter a compiled program as arguments and editing one reuses the program; the
fields made with ``static()`` (kinds, names, step counts, report timing) are
part of the pytree's structure, which the program is compiled for.
"""

import hashlib
import re
from dataclasses import dataclass, field
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np


def static(default=None):
    """A dataclass field that belongs to the structure (hashable; fixed in the compiled program)."""
    return field(default=default, metadata={"static": True})


def _name(path) -> str:
    return jax.tree_util.keystr(path, simple=True, separator=".")


def named_leaves(tree) -> dict:
    """The leaves of a pytree by name: the keys, attribute names and indices on the way to
    each leaf joined by '.' (``{"q": …, "r": …}``, ``{"noise": {"q": …}}`` -> "noise.q",
    ``[a, b]`` -> "0", "1"); a pytree that is one leaf is named ""."""
    return {_name(path): leaf for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def with_leaves(tree, values: dict):
    """``tree`` with the leaves named in ``values`` (as ``named_leaves`` names them) replaced."""
    paths, treedef = jax.tree_util.tree_flatten_with_path(tree)
    return jax.tree_util.tree_unflatten(treedef, [values.get(_name(path), leaf) for path, leaf in paths])


def like(new, old):
    """``new`` with each leaf in the dtype of the same leaf of ``old`` (a filter's next state in the
    precision of its state: one built in float64, run in float32)."""
    return jax.tree_util.tree_map(lambda a, b: jnp.asarray(a, jnp.result_type(b)), new, old)


def traced_key(calls) -> str | None:
    """What functions compile to, as a digest: each ``(fn, args)`` of ``calls`` traced at the shapes
    of ``args`` (``jax.ShapeDtypeStruct`` leaves) — its jaxpr and every constant it closes over.
    Two functions with the same key compile to the same program whatever their numeric inputs;
    a number a function bakes in, or an edit of its code, changes the key. None when one calls
    back into Python (nothing identifies it but its identity)."""
    h = hashlib.sha256()
    for fn, args in calls:
        closed = jax.make_jaxpr(fn)(*args)
        text = re.sub(r" at 0x[0-9a-f]+", "", str(closed.jaxpr))
        if "callback" in text:
            return None
        h.update(text.encode())
        for c in closed.consts:
            a = np.asarray(c)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class Code:
    """A function of one's own held as structure by what it traces to (``key``: ``traced_key``),
    so that the same code read from a file again is the same program (kept, swept, found on disk);
    without a key, by identity. Called as the function."""

    fn: Callable
    key: str | None = None

    def __call__(self, *args, **kwargs):
        return self.fn(*args, **kwargs)

    def __eq__(self, other):
        if not isinstance(other, Code):
            return NotImplemented
        return self is other or (self.key is not None and self.key == other.key)

    def __hash__(self):
        return hash(self.key) if self.key is not None else id(self)

    def __repr__(self):
        return f"Code({self.key!r})" if self.key is not None else f"<{self.fn!r}, by identity>"
