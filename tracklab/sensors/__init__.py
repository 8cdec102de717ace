"""Sensors: measurement geometry, noise, timing, detection, converted measurements."""

from tracklab.sensors.clutter import Cluttered
from tracklab.sensors.conversion import CONVERSIONS
from tracklab.sensors.custom import CustomSensor
from tracklab.sensors.geometry import (
    SENSOR_SIGMAS,
    SENSORS,
    Sensor,
    SensorKind,
    SensorSuite,
    angles_h,
    cartesian_h,
    epochs,
    polar_h,
    spherical_h,
)

__all__ = [
    "CONVERSIONS", "Cluttered", "CustomSensor", "SENSORS", "SENSOR_SIGMAS", "Sensor", "SensorKind", "SensorSuite", "angles_h", "cartesian_h", "epochs", "polar_h",
    "spherical_h",
]
