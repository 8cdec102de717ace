"""Experiment objects as pytrees: their numbers are leaves, everything else is structure.

A scenario, a sensor or an engagement is a frozen dataclass registered with
``jax.tree_util.register_dataclass``. Its numeric fields are leaves, so they
enter a compiled program as arguments and editing one reuses the program; the
fields made with ``static()`` (kinds, names, step counts, report timing) are
part of the pytree's structure, which the program is compiled for.
"""

from dataclasses import field


def static(default=None):
    """A dataclass field that belongs to the structure (hashable; fixed in the compiled program)."""
    return field(default=default, metadata={"static": True})
