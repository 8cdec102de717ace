"""Experiment objects as pytrees: their numbers are leaves, everything else is structure.

A scenario, a sensor or an engagement is a frozen dataclass registered with
``jax.tree_util.register_dataclass``. Its numeric fields are leaves, so they
enter a compiled program as arguments and editing one reuses the program; the
fields made with ``static()`` (kinds, names, step counts, report timing) are
part of the pytree's structure, which the program is compiled for.
"""

from dataclasses import field

import jax
import jax.numpy as jnp


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
