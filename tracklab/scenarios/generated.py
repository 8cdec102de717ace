"""A truth of one's own: any function of a run's random key.

``Generated(truth, dt=…, steps=…, dim=…)`` calls ``truth(key)`` once per Monte-Carlo run
and takes the (steps + 1, 2·dim) array it returns as that run's true states in the CV
layout [x, ẋ, y, ẏ(, z, ż)]; row 0 is the prior epoch, one sample period before the
first measurement. ``key`` is a JAX key (``jax.random.normal(key, …)`` and the like draw
from it): each run gets its own, the same whatever the chunk size or device count. The
function is traced with ``jax.numpy`` and is part of the program's structure (a new
function compiles anew); numbers it should take as inputs go in ``params``, handed to it
as ``truth(key, params)`` when given. Without a linear-Gaussian model no PCRLB is drawn.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.errors import failure
from tracklab.pytree import Code, static, traced_key
from tracklab.scenarios.kind import Scenario


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Generated(Scenario):
    truth: Callable = static()  # key -> (steps + 1, 2·dim), or (key, params) -> … when params is given
    dt: float = static(1.0)
    steps: int = static(1)
    dim: int = static(2)
    params: Any = None  # numbers the truth function takes as inputs (a pytree)

    per_run = True  # every run draws its own truth
    gaussian = False  # no linear-Gaussian model: no PCRLB

    def simulate(self, key):
        return self.truth(key) if self.params is None else self.truth(key, self.params)

    def linear_gaussian(self):
        return None

    def keyed(self) -> "Generated":
        """This truth held as structure by what it traces to (``pytree.Code``): read again from a file,
        the same code is the same program."""
        if isinstance(self.truth, Code):
            return self
        key = jax.ShapeDtypeStruct((), jax.random.key(0).dtype)
        with jax.enable_x64(True):
            params = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(np.shape(a), jnp.result_type(a)), self.params)
            k = traced_key([(self.truth, (key,) if self.params is None else (key, params))])
        return replace(self, truth=Code(self.truth, k))

    def problem(self) -> str | None:
        """Why this truth cannot be used (None if it can): it fails, or its shape is not (steps + 1, 2·dim)."""
        try:
            with jax.enable_x64(True):
                out = jax.eval_shape(self.simulate, jax.random.key(0))
        except BaseException as e:  # noqa: BLE001 - the user's function: any error, a sys.exit too
            if isinstance(e, KeyboardInterrupt):
                raise
            return f"truth(key) fails: {failure(e)}"
        want = (self.steps + 1, 2 * self.dim)
        if getattr(out, "shape", None) != want or not jnp.issubdtype(out.dtype, jnp.floating):
            return (f"truth(key) gives {getattr(out, 'shape', type(out).__name__)}"
                    f"{' ' + str(out.dtype) if hasattr(out, 'dtype') else ''}: expected floats of shape {want} "
                    f"(steps + 1 rows of [x, ẋ, y, ẏ{', z, ż' if self.dim == 3 else ''}])")
        return None
