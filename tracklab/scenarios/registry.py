"""Every scenario kind a [scenario] table may name: the declarations at the end of each scenario's
module (``kind.ScenarioKind``), one line each, in the order ``tracklab list`` shows."""

from tracklab.scenarios.constant_velocity import CONSTANT_VELOCITY, CROSSING
from tracklab.scenarios.kind import ScenarioKind
from tracklab.scenarios.manoeuvre import MANOEUVRE
from tracklab.scenarios.overflight import OVERFLIGHT
from tracklab.scenarios.sine import SINE
from tracklab.scenarios.trajectory import TRAJECTORY

SCENARIOS: dict[str, ScenarioKind] = {k.name: k for k in (CROSSING, CONSTANT_VELOCITY, TRAJECTORY, OVERFLIGHT, SINE,
                                                           MANOEUVRE)}
