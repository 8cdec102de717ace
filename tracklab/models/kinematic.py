"""Kinematic motion models in Cartesian coordinates.

States are interleaved per axis, as in paper 000 eq. (2): CV in 2-D is
[x, ẋ, y, ẏ]; CA in 3-D is [x, ẋ, ẍ, y, ẏ, ÿ, z, ż, z̈].

Process noise (Bar-Shalom's discrete models):

* CV — discrete white-noise acceleration (DWNA): a piecewise-constant
  acceleration of std ``sigma`` per axis, G = [T²/2, T]ᵀ (paper 000 eq. 4),
  Q = σ² G Gᵀ.
* CA — discrete Wiener-process acceleration (DWPA): the acceleration increment
  per step has std ``sigma``, Γ = [T²/2, T, 1]ᵀ, Q = σ² Γ Γᵀ.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from tracklab.models.layout import Layout


class Kinematic(NamedTuple):
    """A linear motion model: x_{k+1} = F x_k + G w_k, w_k ~ N(0, q I)."""

    name: str  # "cv" or "ca"
    dim: int  # spatial dimensions (2 or 3)
    order: int  # states per axis (2 for CV, 3 for CA)
    F: np.ndarray  # (n, n)
    G: np.ndarray  # (n, dim): noise gain, one column per axis

    @property
    def n(self) -> int:
        return self.dim * self.order

    @property
    def pos_idx(self) -> tuple[int, ...]:
        return tuple(a * self.order for a in range(self.dim))

    @property
    def vel_idx(self) -> tuple[int, ...]:
        return tuple(a * self.order + 1 for a in range(self.dim))

    def Q(self, q):
        """Process-noise covariance for noise variance ``q`` (scalar or per axis)."""
        q = jnp.broadcast_to(jnp.asarray(q), (self.dim,))
        return (self.G * q) @ self.G.T

    @property
    def layout(self) -> Layout:
        return Layout(self.n, self.pos_idx, self.vel_idx)

    def embed(self, x_cv, P_cv, extra_var=0.0):
        """Place a CV-layout prior [x, ẋ, y, ẏ, ...] into this model's state.

        Higher derivatives (CA acceleration) get zero mean and variance ``extra_var``.
        """
        return self.layout.embed(x_cv, P_cv, extra_var)


def _block(per_axis_F, per_axis_G, dim):
    o = per_axis_F.shape[0]
    F = np.zeros((dim * o, dim * o))
    G = np.zeros((dim * o, dim))
    for a in range(dim):
        F[a * o:(a + 1) * o, a * o:(a + 1) * o] = per_axis_F
        G[a * o:(a + 1) * o, a] = per_axis_G
    return F, G


def cv(dim: int, dt: float) -> Kinematic:
    """Constant velocity with DWNA noise (paper 000 eq. 4)."""
    F, G = _block(np.array([[1.0, dt], [0.0, 1.0]]), np.array([dt**2 / 2, dt]), dim)
    return Kinematic("cv", dim, 2, F, G)


def ca(dim: int, dt: float) -> Kinematic:
    """Constant acceleration with DWPA noise (docs/mathematics.md §2)."""
    Fa = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    F, G = _block(Fa, np.array([dt**2 / 2, dt, 1.0]), dim)
    return Kinematic("ca", dim, 3, F, G)


MODELS = {"cv": cv, "ca": ca}
