"""A sensor of one's own: any measurement function of the position and a noise covariance.

``CustomSensor(h, R, angles=…)`` measures z = h(p) + v, v ~ N(0, R), of the target's
position p (dim,), with ``R`` a full (m, m) covariance (a leaf of the pytree: an input of
the compiled program) and ``angles`` flagging the components that are angles in radians
(wrapped to (−π, π], as filters wrap their innovations). Timing and detection are those of
every sensor (``period``, ``offset``, ``p_detect``). ``h`` must be written with
``jax.numpy`` (the engine differentiates it for the Fisher information and the EKFs'
Jacobians) and is part of the structure: read from a file, by what it traces to (``keyed``);
otherwise by identity.

Built-in filters that accept any sensor (``ekf``, ``ukf``, ``stf``, ``imm``,
``sequential_ekf``) see it with the diagonal of ``R`` as their default noise; a user's
own filter gets the whole ``R`` (``tracklab.filters.context``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.errors import failure
from tracklab.linalg import jacobian
from tracklab.pytree import Code, static, traced_key
from tracklab.sensors.geometry import measure_whole, report_mask, reported, sensor_draws


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class CustomSensor:
    h_fn: Callable = static()  # h(p): position (dim,) -> measurement (m,)
    R: Any = ()  # (m, m) true noise covariance
    angles: tuple = static(())  # per component: an angle in radians (wrapped); default none
    dim: int = static(3)  # spatial dimension of the positions it observes
    p_detect: float = 1.0
    name: str = static("custom")
    component_names: tuple = static(())  # default z0, z1, …
    dt: float = static(0.0)  # the experiment's step; with period/offset, sets the report epochs
    period: float = static(0.0)  # 0: every step
    offset: float = static(0.0)
    misses: bool | None = static(None)  # draws detections (p_detect < 1); None: from p_detect

    kind = "custom"
    linear = False

    def __post_init__(self):
        if self.misses is None:
            object.__setattr__(self, "misses", bool(np.asarray(self.p_detect) < 1.0))

    @property
    def m(self) -> int:
        return int(np.shape(self.R)[-1])

    def keyed(self) -> "CustomSensor":
        """This sensor with ``h`` held as structure by what it traces to (``pytree.Code``): read again
        from a file, the same code is the same program."""
        if isinstance(self.h_fn, Code):
            return self
        with jax.enable_x64(True):
            k = traced_key([(self.h_fn, (jax.ShapeDtypeStruct((self.dim,), jnp.float64),))])
        return replace(self, h_fn=Code(self.h_fn, k))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.component_names) or tuple(f"z{i}" for i in range(self.m))

    @property
    def angle_mask(self) -> tuple[bool, ...]:
        return tuple(bool(a) for a in self.angles) or (False,) * self.m

    @property
    def sigma(self) -> tuple:
        """The noise standard deviations (the square roots of R's diagonal)."""
        return tuple(float(v) for v in np.sqrt(np.diag(np.asarray(self.R, float))))

    @property
    def sensors(self) -> tuple["CustomSensor", ...]:
        return (self,)

    def h(self, p):
        """h of one position (dim,), or of each of a stack of them (..., dim)."""
        if jnp.ndim(p) == 1:
            return self.h_fn(p)
        return jax.vmap(self.h)(p)

    def report_mask(self, steps: int) -> np.ndarray:
        return report_mask(self, steps)

    def draws(self, key, steps):
        return sensor_draws(key, steps, self.m, self.misses)

    def measure_step(self, draws_k, k, steps, p):
        """Step k's noisy measurement (m,) of the position ``p`` (dim,): v = chol(R)·(standard normals)."""
        noise, u = draws_k
        z = self.h(p) + jnp.linalg.cholesky(jnp.asarray(self.R, p.dtype)) @ noise.astype(p.dtype)
        return reported(self, z, k, steps, u)

    def measure(self, key, pos):
        return measure_whole(self, key, pos)

    def information(self, p):
        """Expected Fisher information of one report about the position: Pd·Hᵀ R⁻¹ H."""
        H = jacobian(self.h, p)
        R = jnp.asarray(self.R, p.dtype)
        return self.p_detect * H.T @ jnp.linalg.solve(R, H)

    def problem(self) -> str | None:
        """Why this sensor cannot be used (None if it can): R not a symmetric positive-definite
        (m, m) matrix, angles of the wrong length, h not giving m components."""
        R = np.asarray(self.R, float)
        if R.ndim != 2 or R.shape[0] != R.shape[1] or R.shape[0] < 1:
            return f"R has shape {R.shape}: expected a square (m, m) covariance"
        if not np.all(np.isfinite(R)) or not np.allclose(R, R.T, rtol=1e-12, atol=0.0):
            return "R must be finite and symmetric"
        if np.min(np.linalg.eigvalsh(R)) <= 0:
            return "R must be positive definite"
        if self.angles and len(self.angles) != self.m:
            return f"angles has {len(self.angles)} entries, R is {self.m} x {self.m}"
        if self.component_names and len(self.component_names) != self.m:
            return f"component_names has {len(self.component_names)} entries, R is {self.m} x {self.m}"
        try:
            with jax.enable_x64(True):
                shape = jax.eval_shape(self.h, jax.ShapeDtypeStruct((self.dim,), jnp.float64)).shape
        except BaseException as e:  # noqa: BLE001 - the user's function: any error, a sys.exit too
            if isinstance(e, KeyboardInterrupt):
                raise
            return f"h(p) fails on a position of shape ({self.dim},): {failure(e)}"
        if shape != (self.m,):
            return f"h(p) gives shape {shape}, R is {self.m} x {self.m}: expected ({self.m},)"
        return None
