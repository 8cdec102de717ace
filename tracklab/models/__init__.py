"""Motion models: constant velocity and constant acceleration, discretised."""

from tracklab.models.kinematic import MODELS, Kinematic, ca, cv
from tracklab.models.layout import Layout, cv_index, interleaved

__all__ = ["MODELS", "Kinematic", "Layout", "ca", "cv", "cv_index", "interleaved"]
