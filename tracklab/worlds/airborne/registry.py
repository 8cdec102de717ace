"""Every tracker kind an airborne file's [[tracker]] may name: the declarations at the end of each
tracker's module (``tracker.TrackerKind``), one line each, in the order ``tracklab list`` shows."""

from tracklab.worlds.airborne.cd_ekf import CD_EKF
from tracklab.worlds.airborne.classical import CLASSICAL
from tracklab.worlds.airborne.decoupled import DECOUPLED
from tracklab.worlds.airborne.moose import MOOSE
from tracklab.worlds.airborne.tracker import TrackerKind

TRACKERS: dict[str, TrackerKind] = {k.name: k for k in (CD_EKF, DECOUPLED, CLASSICAL, MOOSE)}
