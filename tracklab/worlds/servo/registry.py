"""Every estimator kind a servo file's [[estimator]] may name (``estimators.EstimatorKind``), one line each."""

from tracklab.worlds.servo.estimators import DEKF, KF, EstimatorKind

ESTIMATORS: dict[str, EstimatorKind] = {k.name: k for k in (KF, DEKF)}
