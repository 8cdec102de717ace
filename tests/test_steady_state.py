"""The KF's steady-state covariance equals the discrete Riccati solution.

For a constant-velocity model with discrete white-noise acceleration and
position measurements, the steady-state filtered covariance has the closed form
of docs/mathematics.md §2 (Kalata's α, β from the tracking index λ = σ_v T²/σ_w):
P = σ_w² [[α, β/T], [β/T, β(2α−β)/(2(1−α)T²)]]. A second check solves the DARE
through the stable eigenvectors of the symplectic (Hamiltonian) matrix.
"""

import numpy as np
import pytest

import tracklab
from tracklab.filters import kf
from tracklab.models import cv


def kalata(lam):
    r = np.sqrt(lam**2 + 8 * lam)
    alpha = -(lam**2 + 8 * lam - (lam + 4) * r) / 8
    beta = (lam**2 + 4 * lam - lam * r) / 4
    return alpha, beta


def dare_symplectic(F, H, Q, R):
    """Predicted steady-state covariance from the symplectic pencil's stable subspace."""
    n = F.shape[0]
    Fi = np.linalg.inv(F)
    G = H.T @ np.linalg.inv(R) @ H
    Z = np.block([[F.T + G @ Fi @ Q, -G @ Fi], [-Fi @ Q, Fi]])
    w, V = np.linalg.eig(Z)
    idx = np.argsort(np.abs(w))[:n]  # eigenvalues inside the unit circle
    U1, U2 = V[:n, idx], V[n:, idx]
    return np.real(U2 @ np.linalg.inv(U1))


@pytest.mark.parametrize("sv,sw,T", [(0.1, 10.0, 1.0), (1.0, 100.0, 0.5), (3.0, 10.0, 1.0), (9.0, 2.0, 0.2)])
def test_kf_steady_state_equals_kalata_closed_form(sv, sw, T):
    m = cv(1, T)
    H = np.array([[1.0, 0.0]])
    flt = kf(m.F, H, np.asarray(m.Q(sv**2)), np.array([[sw**2]]))
    z = np.zeros((3000, 1))  # the covariance does not depend on the measurement values
    res = tracklab.run_filter(flt, z, x0=np.zeros(2), P0=np.eye(2) * 1e6, dt=T)
    P = np.asarray(res.P[-1])
    lam = sv * T**2 / sw
    a, b = kalata(lam)
    closed = sw**2 * np.array([[a, b / T], [b / T, b * (2 * a - b) / (2 * (1 - a) * T**2)]])
    np.testing.assert_allclose(P, closed, rtol=1e-8)
    # the predicted covariance against the symplectic DARE solution
    M = m.F @ P @ m.F.T + np.asarray(m.Q(sv**2))
    np.testing.assert_allclose(M, dare_symplectic(m.F, H, np.asarray(m.Q(sv**2)), np.array([[sw**2]])), rtol=1e-7)
