"""Sensors: measurement geometry, noise, detection, and converted measurements."""

from tracklab.sensors.conversion import CONVERSIONS
from tracklab.sensors.geometry import SENSOR_KINDS, Sensor, cartesian_h, polar_h, spherical_h

__all__ = ["CONVERSIONS", "SENSOR_KINDS", "Sensor", "cartesian_h", "polar_h", "spherical_h"]
