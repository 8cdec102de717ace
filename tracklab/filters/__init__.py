"""Filters: pure ``init``/``step`` pairs over pytrees (see ``core``), and the blocks they are
written with (``blocks``: predict, update, ekf_update, kalman_filter, …).

The kinds an experiment file names are declared beside their code (``kind.FilterKind``)
and collected in ``registry.KINDS``; ``build`` makes one.
"""

from tracklab.filters.alphabeta import (
    kalata_alpha_beta,
    kalata_alpha_beta_gamma,
    growing_memory_alpha_beta,
    growing_memory_alpha_beta_gamma,
    model_alpha_beta,
    tracking_index,
)
from tracklab.filters.blocks import (
    Gaussian,
    Update,
    ekf_predict,
    ekf_update,
    innovation,
    innovation_update,
    joseph_covariance,
    kalman_filter,
    predict,
    update,
    wrap_angle,
)
from tracklab.filters.core import Filter, Meas, Out, Prior, masked_meas, measuring
from tracklab.filters.association import ipda, nearest_neighbour, pdaf, strongest_neighbour
from tracklab.filters.kalman import (
    ekf,
    kf,
    model_cmkf,
    model_ekf,
    model_kf,
    model_sequential_ekf,
    noise_params,
)
from tracklab.filters.dual_ekf import model_dekf
from tracklab.filters.error_space import model_error_space
from tracklab.filters.imm import imm_params, model_imm
from tracklab.filters.kind import FilterKind
from tracklab.parameters import Param
from tracklab.filters.polar import model_polar_kf
from tracklab.filters.registry import KINDS
from tracklab.filters.strong_tracking import model_stf, strong_tracking
from tracklab.filters.unscented import model_ukf


def build(kind, model, sensor, params, options=None) -> Filter:
    """Build an experiment filter of ``kind`` (its declaration: ``registry.KINDS``) for a motion model and a
    measurement model; parameters with a fixed default may be left out of ``params``. The filter
    refuses, when traced, a measurement of other than the sensor's ``m`` components (a filter of
    scans, ``association``: a scan of returns of other than ``m`` components)."""
    k = KINDS[kind]
    flt = k.build(model, sensor, k.with_defaults(params), dict(options or {}))
    return flt if k.scans else measuring(flt, sensor.m)  # a filter of scans checks its scans' shape itself


__all__ = [
    "Filter", "FilterKind", "Gaussian", "KINDS", "Meas", "Out", "Param", "Prior", "Update", "build", "ekf", "ekf_predict",
    "ekf_update", "growing_memory_alpha_beta", "growing_memory_alpha_beta_gamma", "imm_params", "innovation",
    "innovation_update", "ipda", "joseph_covariance", "kalata_alpha_beta", "kalata_alpha_beta_gamma", "kalman_filter", "kf",
    "masked_meas", "model_alpha_beta", "model_error_space", "model_imm", "model_stf", "model_ukf", "nearest_neighbour", "noise_params", "pdaf", "predict", "strongest_neighbour",
    "strong_tracking", "tracking_index", "update", "wrap_angle",
]
