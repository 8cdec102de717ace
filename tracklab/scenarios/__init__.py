"""Truth generators: ``simulate(key) -> (steps + 1, 2·dim)`` in CV layout."""

from tracklab.scenarios.crossing import Crossing
from tracklab.scenarios.trajectory import Trajectory, TrajectoryError, read_csv

SCENARIO_KINDS = {
    "crossing": "straight crossing target, CV with white acceleration (paper 000)",
    "trajectory": "truth from a CSV file with columns t,x,y,z (s, m)",
}

__all__ = ["SCENARIO_KINDS", "Crossing", "Trajectory", "TrajectoryError", "read_csv"]
