"""Where position and velocity sit in a filter's state: its reporting layout.

The engine compares a filter's estimate with the truth, which is in the interleaved
constant-velocity layout [x, ẋ, y, ẏ(, z, ż)]. A filter whose state is ordered otherwise
([x, y, ẋ, ẏ], or with accelerations, biases, …) names the indices of its position and
velocity components, per axis::

    Layout(n=4, pos_idx=(0, 1), vel_idx=(2, 3))        # state [x, y, ẋ, ẏ]

The prior, drawn in the truth's layout, is placed into the state the same way; the other
state components get zero mean and the experiment's extra prior variance.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np


class Layout(NamedTuple):
    n: int  # the state's dimension
    pos_idx: tuple[int, ...]  # index of the position along each axis
    vel_idx: tuple[int, ...]  # index of the velocity along each axis

    @property
    def dim(self) -> int:
        return len(self.pos_idx)

    def check(self, dim: int | None = None) -> str | None:
        """Why this layout is not usable (None if it is) for ``dim`` spatial dimensions."""
        idx = tuple(self.pos_idx) + tuple(self.vel_idx)
        if len(self.pos_idx) != len(self.vel_idx):
            return f"pos_idx {tuple(self.pos_idx)} and vel_idx {tuple(self.vel_idx)} must name the same axes"
        if dim is not None and len(self.pos_idx) != dim:
            return f"names {len(self.pos_idx)} position axes, the scenario has {dim}"
        if any(not isinstance(i, (int, np.integer)) or not 0 <= i < self.n for i in idx) or len(set(idx)) != len(idx):
            return f"indices {idx} must be distinct integers in [0, {self.n})"
        return None

    def embed(self, x_cv, P_cv, extra_var=0.0):
        """A prior in the truth's layout [x, ẋ, y, ẏ, …] placed into this state."""
        idx = cv_index(self)
        rest = np.setdiff1d(np.arange(self.n), idx)
        x = jnp.zeros(x_cv.shape[:-1] + (self.n,), x_cv.dtype).at[..., idx].set(x_cv)
        P = jnp.zeros(P_cv.shape[:-2] + (self.n, self.n), P_cv.dtype).at[..., idx[:, None], idx[None, :]].set(P_cv)
        if rest.size:
            P = P.at[..., rest, rest].set(extra_var)
        return x, P


def cv_index(layout) -> np.ndarray:
    """Indices of the truth's [x, ẋ, y, ẏ, …] in a state of ``layout`` (a Layout, or a motion model)."""
    return np.array([i for a in range(len(layout.pos_idx)) for i in (layout.pos_idx[a], layout.vel_idx[a])])


def interleaved(dim: int) -> Layout:
    """The truth's own layout [x, ẋ, y, ẏ(, z, ż)]."""
    return Layout(2 * dim, tuple(range(0, 2 * dim, 2)), tuple(range(1, 2 * dim, 2)))
