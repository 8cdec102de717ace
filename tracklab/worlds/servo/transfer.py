"""Continuous transfer functions and their discretisation (paper 003's servo, docs/mathematics.md §7).

A ``TransferFunction`` holds numerator and denominator polynomials in s
(highest power first). ``lead_lag(k, num_taus, den_taus)`` builds the
k·Π(τs + 1)/Π(τs + 1) form the paper writes its correctors in.

Discretisation, to a state space x' = A x + B u, y = C x + D u at period T:

* ``"zoh"`` — zero-order hold (the plant behind a DAC that holds its input):
  exact for piecewise-constant inputs, strictly proper when the plant is, so
  a loop closed around it at sample k has no algebraic loop;
* ``"bilinear"`` — Tustin, s = (2/T)(z − 1)/(z + 1) (the digital correctors):
  maps the jω axis onto the unit circle with frequency warping
  ω_d = (2/T) tan(ωT/2), 0.02 % at 50 rad/s and T = 1 ms.

Both are computed from a controllable canonical realisation with NumPy (ZOH: the matrix
exponential ``linalg.host_expm``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from tracklab.linalg import host_expm


@dataclass(frozen=True)
class TransferFunction:
    num: tuple[float, ...]  # coefficients of s, highest power first
    den: tuple[float, ...]

    @staticmethod
    def lead_lag(gain, num_taus=(), den_taus=()) -> "TransferFunction":
        num = np.array([float(gain)])
        for t in num_taus:
            num = np.polymul(num, [t, 1.0])
        den = np.array([1.0])
        for t in den_taus:
            den = np.polymul(den, [t, 1.0])
        return TransferFunction(tuple(num), tuple(den))

    @staticmethod
    def integrator() -> "TransferFunction":
        return TransferFunction((1.0,), (1.0, 0.0))

    def __mul__(self, other: "TransferFunction") -> "TransferFunction":
        return TransferFunction(tuple(np.polymul(self.num, other.num)), tuple(np.polymul(self.den, other.den)))

    def feedback(self, other: "TransferFunction | None" = None) -> "TransferFunction":
        """G / (1 + G H) (unit negative feedback when H is None)."""
        h_num, h_den = (np.array([1.0]), np.array([1.0])) if other is None else (np.array(other.num), np.array(other.den))
        num = np.polymul(self.num, h_den)
        den = np.polyadd(np.polymul(self.den, h_den), np.polymul(self.num, h_num))
        return TransferFunction(tuple(num), tuple(den))

    def __call__(self, s):
        """G(s) at complex s (array)."""
        return np.polyval(self.num, s) / np.polyval(self.den, s)

    def dc_gain(self) -> float:
        return float(self.num[-1] / self.den[-1])

    def state_space(self):
        """Controllable canonical (A, B, C, D) of a proper transfer function."""
        num, den = np.trim_zeros(np.asarray(self.num, float), "f"), np.trim_zeros(np.asarray(self.den, float), "f")
        n = len(den) - 1
        if len(num) > len(den):
            raise ValueError("improper transfer function")
        num, den = np.concatenate([np.zeros(len(den) - len(num)), num]) / den[0], den / den[0]
        D = num[0]
        rest = num[1:] - D * den[1:]  # strictly proper part's numerator, degree < n
        A = np.zeros((n, n))
        if n:
            A[0, :] = -den[1:]
            A[1:, :-1] = np.eye(n - 1)
        B = np.zeros((n, 1))
        if n:
            B[0, 0] = 1.0
        C = rest[None, :]
        return A, B, C, np.array([[D]])


class DiscreteSystem(NamedTuple):
    """x' = A x + B u, y = C x + D u (single input, single output)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: float

    @property
    def order(self) -> int:
        return self.A.shape[0]

    def output(self, x, u):
        """y at this sample (before the state moves on)."""
        return (jnp.asarray(self.C) @ x)[0] + self.D[0, 0] * u

    def advance(self, x, u):
        return jnp.asarray(self.A) @ x + jnp.asarray(self.B)[:, 0] * u

    def response(self, w):
        """Frequency response at angular frequencies ``w`` (rad/s): C (e^{jωT} I − A)⁻¹ B + D."""
        z = np.exp(1j * np.asarray(w, float) * self.dt)
        n = self.order
        out = []
        for zi in np.atleast_1d(z):
            out.append((self.C @ np.linalg.solve(zi * np.eye(n) - self.A, self.B))[0, 0] + self.D[0, 0] if n else self.D[0, 0])
        return np.array(out)


def discretise(tf: TransferFunction, dt: float, method: str = "bilinear") -> DiscreteSystem:
    return discretise_state_space(*tf.state_space(), dt, method)


def discretise_state_space(A, B, C, D, dt: float, method: str = "bilinear") -> DiscreteSystem:
    A, B, C, D = (np.atleast_2d(np.asarray(a, float)) for a in (A, B, C, D))
    n = A.shape[0]
    if method == "bilinear":
        if n == 0:
            return DiscreteSystem(A, B, C, D, dt)
        ima = np.eye(n) - 0.5 * dt * A
        Ad = np.linalg.solve(ima, np.eye(n) + 0.5 * dt * A)
        Bd = np.linalg.solve(ima, dt * B)
        Cd = np.linalg.solve(ima.T, C.T).T
        Dd = D + 0.5 * C @ Bd
        return DiscreteSystem(Ad, Bd, Cd, Dd, dt)
    if method == "zoh":
        M = np.zeros((n + 1, n + 1))
        M[:n, :n], M[:n, n:] = A, B
        E = host_expm(M * dt)
        return DiscreteSystem(E[:n, :n], E[:n, n:], C, D, dt)
    raise ValueError(f"unknown discretisation {method!r}: bilinear or zoh")
