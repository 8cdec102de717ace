"""Truth generators: ``simulate(key) -> (steps + 1, 2·dim)`` in CV layout."""

from tracklab.scenarios.constant_velocity import ConstantVelocity, Crossing
from tracklab.scenarios.generated import Generated
from tracklab.scenarios.manoeuvre import Manoeuvre
from tracklab.scenarios.mount_frame import MountFrame, mount_angles
from tracklab.scenarios.overflight import Overflight
from tracklab.scenarios.sine import Sine
from tracklab.scenarios.kind import Scenario, ScenarioContext, ScenarioKind
from tracklab.scenarios.registry import SCENARIOS
from tracklab.scenarios.trajectory import Trajectory, TrajectoryError, read_csv


__all__ = [
    "SCENARIOS", "ConstantVelocity", "Crossing", "Generated", "Manoeuvre", "MountFrame", "Overflight", "Scenario", "ScenarioContext", "ScenarioKind", "Sine",
    "Trajectory", "TrajectoryError",
    "mount_angles", "read_csv",
]
