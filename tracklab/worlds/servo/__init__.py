"""Servo loops of an electro-optical theodolite (paper 003): transfer functions, discretisation, tracking."""

from tracklab.worlds.servo.estimators import Estimator
from tracklab.worlds.servo.loops import (
    MODES,
    AzimuthAxis,
    closed_position_loop,
    sine_target,
    track,
)
from tracklab.worlds.servo.transfer import (
    DiscreteSystem,
    TransferFunction,
    discretise,
    discretise_state_space,
)

__all__ = [
    "MODES", "AzimuthAxis", "DiscreteSystem", "Estimator", "TransferFunction", "closed_position_loop", "discretise",
    "discretise_state_space", "sine_target", "track",
]
