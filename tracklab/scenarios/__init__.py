"""Truth generators: ``simulate(key) -> (steps + 1, 2·dim)`` in CV layout."""

from tracklab.scenarios.constant_velocity import ConstantVelocity, Crossing
from tracklab.scenarios.generated import Generated
from tracklab.scenarios.manoeuvre import Manoeuvre
from tracklab.scenarios.mount_frame import MountFrame, mount_angles
from tracklab.scenarios.overflight import Overflight
from tracklab.scenarios.sine import Sine
from tracklab.scenarios.trajectory import Trajectory, TrajectoryError, read_csv

SCENARIO_KINDS = {
    "crossing": "straight crossing pass, CV with white acceleration (paper 000)",
    "constant_velocity": "CV with white acceleration from a given initial state, 1-3 D (paper 002 §3)",
    "trajectory": "truth from a CSV file with columns t,x,y,z (s, m)",
    "overflight": "straight level pass over the site: altitude, speed, max_elevation (deg), t_closest (paper 004)",
    "sine": "one angle, A sin(omega t + phase): amplitude (deg), omega (rad/s) (paper 003's equivalent target)",
    "manoeuvre": "straight legs, N-g coordinated turns, longitudinal accelerations: initial, segments (2-D or 3-D)",
}

__all__ = [
    "SCENARIO_KINDS", "ConstantVelocity", "Crossing", "Generated", "Manoeuvre", "MountFrame", "Overflight", "Sine", "Trajectory", "TrajectoryError",
    "mount_angles", "read_csv",
]
