"""Filters: pure ``init``/``step`` pairs over pytrees (see ``core``)."""

from tracklab.filters.core import Filter, Gaussian, Meas, Out, Prior, kalman_update, wrap_angle
from tracklab.filters.kalman import (
    ekf,
    gaussian_filter,
    kf,
    model_cmkf,
    model_ekf,
    model_kf,
    model_sequential_ekf,
    noise_params,
)
from tracklab.filters.polar import model_polar_kf

# kind -> (one-line description, sensors it accepts)
FILTER_KINDS = {
    "kf": ("linear Kalman filter (needs a linear 'cartesian' sensor)", ("cartesian",)),
    "ekf": ("extended Kalman filter, Jacobians by autodiff", ("polar", "spherical", "cartesian")),
    "cmkf": ("converted-measurement KF; debias = plain | additive | unbiased", ("polar", "spherical")),
    "polar_kf": ("polar-state KF [r, ṙ, β, β̇], two decoupled channels (2-D)", ("polar",)),
    "sequential_ekf": ("sequential EKF: angles first, re-linearise, then range", ("polar", "spherical")),
}


def build(kind, model, sensor, params, options=None) -> Filter:
    """Build an experiment filter of ``kind`` for a motion model and a sensor."""
    options = options or {}
    if kind == "kf":
        return model_kf(model, sensor, params)
    if kind == "ekf":
        return model_ekf(model, sensor, params)
    if kind == "cmkf":
        return model_cmkf(model, sensor, params, options.get("debias", "plain"))
    if kind == "polar_kf":
        return model_polar_kf(model.F[0, 1], sensor, params)
    if kind == "sequential_ekf":
        return model_sequential_ekf(model, sensor, params)
    raise KeyError(kind)


__all__ = [
    "FILTER_KINDS", "Filter", "Gaussian", "Meas", "Out", "Prior", "build", "ekf", "gaussian_filter",
    "kalman_update", "kf", "noise_params", "wrap_angle",
]
