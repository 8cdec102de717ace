"""Motion models: constant velocity and constant acceleration, discretised."""

from tracklab.models.kinematic import MODELS, Kinematic, ca, cv

__all__ = ["MODELS", "Kinematic", "ca", "cv"]
