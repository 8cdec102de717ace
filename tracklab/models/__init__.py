"""Motion models: constant velocity and constant acceleration, discretised."""

from tracklab.models.kinematic import MODELS, Kinematic, ca, cv
from tracklab.models.layout import Layout, interleaved

__all__ = ["MODELS", "Kinematic", "Layout", "ca", "cv", "interleaved"]
