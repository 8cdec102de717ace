"""Filters: pure ``init``/``step`` pairs over pytrees (see ``core``)."""

from tracklab.filters.alphabeta import (
    kalata_alpha_beta,
    kalata_alpha_beta_gamma,
    growing_memory_alpha_beta,
    growing_memory_alpha_beta_gamma,
    model_alpha_beta,
    tracking_index,
)
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
from tracklab.filters.dual_ekf import model_dekf
from tracklab.filters.error_space import model_error_space
from tracklab.filters.imm import IMM_MODELS, imm_params, model_imm
from tracklab.filters.polar import model_polar_kf
from tracklab.filters.strong_tracking import model_stf, strong_tracking
from tracklab.filters.unscented import model_ukf

# kind -> (one-line description, measurement models it accepts; "suite" = several sensors)
FILTER_KINDS = {
    "kf": ("linear Kalman filter (needs a linear 'cartesian' or 'mount' sensor)", ("cartesian", "mount", "suite")),
    "ekf": ("extended Kalman filter, Jacobians by autodiff", ("polar", "spherical", "angles", "cartesian", "mount", "suite")),
    "cmkf": ("converted-measurement KF; debias = plain | additive | unbiased", ("polar", "spherical")),
    "polar_kf": ("polar-state KF [r, ṙ, β, β̇], two decoupled channels (2-D)", ("polar",)),
    "sequential_ekf": ("sequential EKF: angles first, re-linearise, then range", ("polar", "spherical", "angles", "suite")),
    "ukf": ("unscented KF; ut_alpha, ut_beta, ut_kappa (default 1, 2, 0)", ("polar", "spherical", "angles", "cartesian", "mount", "suite")),
    "alpha_beta": ("α-β filter; gains = kalata | growing_memory | explicit alpha, beta", ("cartesian", "mount", "polar", "spherical")),
    "alpha_beta_gamma": ("α-β-γ filter; gains = kalata | growing_memory | explicit", ("cartesian", "mount", "polar", "spherical")),
    "stf": ("strong tracking filter (Zhou): fading factor, forgetting rho, weakening b; extended on nonlinear sensors",
            ("polar", "spherical", "angles", "cartesian", "mount", "suite")),
    "imm": ("interacting multiple models over cv / ca / ct (coordinated turn); mode probabilities in aux",
            ("polar", "spherical", "angles", "cartesian", "mount", "suite")),
    "dekf": ("dual EKF with a neural motion model (paper 003); one angle channel, 1-D linear sensor",
             ("cartesian",)),
    "error_space": ("error-space estimator (paper 004): guide-data and guide-error KFs; guide = previous | a sensor",
                    ("cartesian", "mount")),
}


def build(kind, model, sensor, params, options=None) -> Filter:
    """Build an experiment filter of ``kind`` for a motion model and a measurement model."""
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
    if kind == "ukf":
        return model_ukf(model, sensor, params, options.get("ut_alpha", 1.0), options.get("ut_beta", 2.0),
                         options.get("ut_kappa", 0.0))
    if kind == "stf":
        return model_stf(model, sensor, params)
    if kind == "imm":
        return model_imm(model.dim, float(model.F[0, 1]), sensor, params, tuple(options.get("models", IMM_MODELS)),
                         options.get("turn_rate_sigma", 0.1))
    if kind == "dekf":
        return model_dekf(model, sensor, params, options.get("hidden", 4), options.get("scale", (100.0, 50.0, 30.0)),
                          options.get("reading", "residual"))
    if kind == "error_space":
        guide = options.get("guide", "previous")
        m = sensor.m if guide == "previous" else sensor.m // 2
        return model_error_space(model, m, params, "previous" if guide == "previous" else "external",
                                 options.get("guide_delay", 0))
    if kind in ("alpha_beta", "alpha_beta_gamma"):
        return model_alpha_beta(
            model, sensor, params, options.get("gains", "kalata"), options.get("floor"), options.get("conversion", "plain")
        )
    raise KeyError(kind)


__all__ = [
    "FILTER_KINDS", "Filter", "Gaussian", "Meas", "Out", "Prior", "build", "ekf", "gaussian_filter",
    "growing_memory_alpha_beta", "growing_memory_alpha_beta_gamma", "kalata_alpha_beta", "kalata_alpha_beta_gamma",
    "imm_params", "kalman_update", "kf", "model_alpha_beta", "model_error_space", "model_imm", "model_stf", "model_ukf", "noise_params",
    "strong_tracking", "tracking_index", "wrap_angle",
]
