"""Truth read from a trajectory file (real flights or a user's own track).

File contract: text CSV, optional ``#`` comment lines, a header row naming the
columns ``t,x,y,z`` (in that order), then numeric rows: t in seconds, strictly
increasing; x, y, z in metres in a local east-north-up frame whose origin is
the sensor. Every value finite; at least two rows.

The track is resampled at the experiment's period by piecewise-cubic Hermite
interpolation: through the file's positions, with the central finite
differences of those positions as the velocities at the file's times. The
resampled position is continuously differentiable and the reported velocity
is its exact derivative, so a sampling rate far above the file's (a 25 Hz
mount on a 1 Hz track) sees no kinks between the file's rows. The truth is the same in every Monte-Carlo run (only the
measurement noise and the prior differ).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.parameters import Param, nonnegative
from tracklab.pytree import static
from tracklab.scenarios.kind import Scenario, ScenarioKind

COLUMNS = ("t", "x", "y", "z")


class TrajectoryError(ValueError):
    """A trajectory file that breaks the contract; the message says how."""


def read_csv(path) -> np.ndarray:
    """The validated (rows, 4) table of a trajectory file (parsed once per file version)."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError("does not exist or is not a file")
    st = path.stat()
    return _parse_csv(str(path.resolve()), st.st_mtime_ns, st.st_size).copy()


@functools.lru_cache(maxsize=32)
def _parse_csv(path: str, mtime_ns: int, size: int) -> np.ndarray:
    path = Path(path)
    try:
        lines = [ln.strip() for ln in path.read_text(encoding="utf-8-sig").splitlines()]
    except (OSError, UnicodeDecodeError) as e:
        raise TrajectoryError(f"cannot be read as text ({e.__class__.__name__})") from None
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    if not lines:
        raise TrajectoryError("is empty: expected a header 't,x,y,z' and numeric rows")
    header = tuple(c.strip().lower() for c in lines[0].split(","))
    if header != COLUMNS:
        raise TrajectoryError(f"header is {','.join(header)!r}: expected exactly 't,x,y,z'")
    rows = []
    for i, ln in enumerate(lines[1:], start=2):
        cells = ln.split(",")
        if len(cells) != 4:
            raise TrajectoryError(f"data row {i - 1} has {len(cells)} columns: expected 4 (t,x,y,z)")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise TrajectoryError(f"data row {i - 1} is not numeric: {ln[:60]!r}") from None
    data = np.array(rows, dtype=float).reshape(-1, 4)
    if len(data) < 2:
        raise TrajectoryError(f"has {len(data)} data rows: at least 2 are needed")
    if not np.all(np.isfinite(data)):
        bad = int(np.argmax(~np.all(np.isfinite(data), axis=1))) + 1
        raise TrajectoryError(f"data row {bad} holds NaN or inf: every value must be finite")
    dt = np.diff(data[:, 0])
    if np.any(dt <= 0):
        bad = int(np.argmax(dt <= 0)) + 2
        raise TrajectoryError(f"time is not strictly increasing at data row {bad}")
    return data


def hermite(t_knots, p_knots, t):
    """Piecewise-cubic Hermite position and velocity at ``t`` through (t_knots, p_knots).

    Knot velocities are the central differences of the knots (one-sided at the ends).
    """
    m = jnp.gradient(p_knots, t_knots, axis=0)
    i = jnp.clip(jnp.searchsorted(t_knots, t, side="right") - 1, 0, len(t_knots) - 2)
    h = (t_knots[i + 1] - t_knots[i])[:, None]
    s = (t - t_knots[i])[:, None] / h
    p0, p1, m0, m1 = p_knots[i], p_knots[i + 1], m[i] * h, m[i + 1] * h
    pos = (2 * s**3 - 3 * s**2 + 1) * p0 + (s**3 - 2 * s**2 + s) * m0 + (-2 * s**3 + 3 * s**2) * p1 + (s**3 - s**2) * m1
    vel = ((6 * s**2 - 6 * s) * p0 + (3 * s**2 - 4 * s + 1) * m0 + (-6 * s**2 + 6 * s) * p1 + (3 * s**2 - 2 * s) * m1) / h
    return pos, vel


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Trajectory(Scenario):
    path: str = static()
    dt: float = static()
    steps: int = static()
    dim: int = static(3)
    per_run = False  # the same truth in every run
    gaussian = False
    start: float = 0.0  # seconds after the file's first time
    knots: Any = None  # the file's (rows, 4) table t, x, y, z; None: read from ``path``

    def __post_init__(self):
        if self.knots is None:
            object.__setattr__(self, "knots", read_csv(self.path))

    def table(self) -> np.ndarray:
        return np.asarray(self.knots)

    def duration(self) -> float:
        d = self.table()
        return float(d[-1, 0] - d[0, 0])

    def max_steps(self) -> int:
        return int(np.floor((self.duration() - self.start) / self.dt + 1e-9))

    def linear_gaussian(self):
        return None  # deterministic truth: no bound from a Gaussian motion model

    def truth(self):
        d = jnp.asarray(self.knots)
        t = d[0, 0] + self.start + self.dt * jnp.arange(self.steps + 1)
        pos, vel = hermite(d[:, 0], d[:, 1:1 + self.dim], t)
        return jnp.stack([pos, vel], axis=-1).reshape(len(t), 2 * self.dim)

    def simulate(self, key):
        return self.truth()


def _trajectory(context, n, fields):
    """path (a t,x,y,z file, relative to the experiment file), dims (default the sensors' or 3), start."""
    p = fields.string("path", required=True)
    try:
        tpath = (context.folder / p).resolve()
        read_csv(tpath)
    except (RuntimeError, OSError) as e:  # a symbolic-link loop, a name too long, …
        raise fields.error("path", p, f"trajectory file cannot be opened ({e.__class__.__name__})") from None
    except TrajectoryError as e:
        raise fields.error("path", p, f"trajectory file {e}") from None
    dims = fields.integer("dims", context.dim or 3, lo=2, hi=3)
    if context.dim is not None and dims != context.dim:
        raise fields.error("dims", dims, f"must be {context.dim} for the sensors given")
    scenario = Trajectory(path=str(tpath), dt=context.dt, steps=context.steps, dim=dims, start=n["start"])
    avail = scenario.max_steps()
    if context.steps > avail:
        raise fields.error("experiment.steps", context.steps,
                           f"the trajectory from start = {n['start']} s holds at most {avail} steps of {context.dt} s")
    return scenario


TRAJECTORY = ScenarioKind(
    "trajectory", "truth from a CSV file with columns t,x,y,z (s, m): path, dims",
    {"start": Param("seconds after the file's first time", nonnegative, "s", 0.0)}, _trajectory)
