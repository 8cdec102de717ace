"""A shared test case: a straight pass across the negative x axis, where the angle wraps at ±π."""

import numpy as np

from tracklab.models import cv

SIGMA = np.array([5.0, 0.001])  # range (m), angle (rad)


def wrapping_pass(seed=4, steps=60):
    """(model, truth (T, 4), noisy polar measurements (T, 2) wrapped to (-π, π])."""
    rng = np.random.default_rng(seed)
    m = cv(2, 1.0)
    s = np.array([-10000.0, 0.0, -300.0, 10.0])
    truth = []
    for _ in range(steps):
        s = m.F @ s
        truth.append(s)
    truth = np.array(truth)
    z = np.stack([np.hypot(truth[:, 0], truth[:, 2]), np.arctan2(truth[:, 2], truth[:, 0])], 1)
    z = z + rng.normal(size=z.shape) * SIGMA
    z[:, 1] = np.angle(np.exp(1j * z[:, 1]))
    return m, truth, z
