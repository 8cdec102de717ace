"""The posterior Cramér–Rao lower bound (Tichavský, Muravchik & Nehorai, "Posterior Cramér-Rao
bounds for discrete-time nonlinear filtering", IEEE Trans. Signal Processing, 1998) for
scenarios with linear-Gaussian truth dynamics, the measurement information averaged over the
simulated truths.
"""

from __future__ import annotations


import jax
import jax.extend
import jax.numpy as jnp
import numpy as np



def pcrlb64(scenario, P0_cv, info_pos):
    with jax.enable_x64(True):
        return pcrlb(scenario, P0_cv, info_pos)

def pcrlb(scenario, P0_cv, info_pos):
    """Tichavský et al. recursion (docs/mathematics.md §5) for linear-Gaussian dynamics.

    J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + E[H̃ᵀ R⁻¹ H̃], the expectation averaged over
    the simulated truths (``info_pos``, (T, dim, dim), position block); J_0 = P0⁻¹.
    ``F`` is one matrix, or one per step (T, n, n): the Jacobians of a deterministic
    truth's motion along it, with Q = 0 (the bound of a known, manoeuvring path).
    Returns J⁻¹ per measurement step, or None when the truth has no Gaussian model.
    """
    lg = scenario.linear_gaussian()
    if lg is None:
        return None
    F, Q = (np.asarray(a, float) for a in lg)
    pos = np.arange(scenario.dim) * 2
    Jz = np.zeros((len(info_pos),) + np.shape(P0_cv))
    Jz[:, pos[:, None], pos[None, :]] = np.asarray(info_pos)
    Fs = F if F.ndim == 3 else np.broadcast_to(F, (len(info_pos),) + F.shape)
    return np.asarray(_pcrlb_recursion(np.asarray(P0_cv, float), Q, Fs, Jz))

@jax.jit
def _pcrlb_recursion(P0, Q, Fs, Jz):
    """J⁻¹ per step (compiled once per shape, not per call; its inputs built on the host)."""

    def step(Jinv, inp):
        Jz_k, F_k = inp
        Jinv = jnp.linalg.inv(jnp.linalg.inv(Q + F_k @ Jinv @ F_k.T) + Jz_k)
        return Jinv, Jinv

    return jax.lax.scan(step, P0, (Jz, Fs))[1]
