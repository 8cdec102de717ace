"""The servo's target-angle estimators (paper 003) and their kinds.

An estimator runs at the camera rate on the delivered angle and predicts across the camera's
delay (``Estimator``). A kind an ``[[estimator]]`` table names is declared once (an
``EstimatorKind``: its numbers, its options, what its code is compiled for, its params) and
listed in ``worlds.servo.registry``; the file's reader, ``tracklab list``, tuning, sweeps and
the tuned file's write-back read the declaration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.filters import build, noise_params
from tracklab.filters.dual_ekf import Network, dekf_params, dual_ekf, predict_ahead
from tracklab.models import ca
from tracklab.parameters import Option, Param, positive, unit_interval
from tracklab.sensors import Sensor


@dataclass(frozen=True)
class Estimator:
    """A target-angle estimator at the camera rate: Filter + ``ahead(params, state, out, n)`` -> (θ̂, ω̂, α̂).

    ``ahead`` predicts ``n`` frames past the filter's latest estimate (the exposure frame).
    """

    filter: object
    ahead: Callable
    params: object = None
    filter_net: object = None  # the DEKF's network, for training


def kalman_estimator(frame_dt: float, sigma: float, q: float) -> Estimator:
    """The baseline: a CA-model Kalman filter on the measured angle, predicting n frames ahead with Φⁿ."""
    model = ca(1, frame_dt)
    flt = build("kf", model, Sensor("cartesian", 1, (sigma,)), noise_params(q, jnp.reshape(jnp.asarray(sigma) ** 2, (1,))))
    F = jnp.asarray(model.F)

    def ahead(params, state, out, n):
        return jnp.linalg.matrix_power(F, n) @ state.x

    return Estimator(flt, ahead)


def dekf_estimator(net, params) -> Estimator:
    """The dual EKF of paper 003, predicting n frames ahead with the network (eq. 17)."""
    def ahead(p, state, out, n):
        return predict_ahead(net, state.x, state.w, n)

    return Estimator(dual_ekf(net, params), ahead, params, net)


class Setting(NamedTuple):
    """What an estimator's kind makes its code and numbers with: the camera's frame period (s), the
    measured angle's noise (deg) and the target's typical |θ|, |θ̇|, |θ̈| (a network's input scaling)."""

    frame_dt: float
    sigma: float
    scale: tuple


@dataclass(frozen=True)
class EstimatorKind:
    """A kind of estimator an [[estimator]] table may name: what it is, the numbers of its table
    (``params``), its structural fields (``options``), what its code is compiled for beyond its kind
    (``structure(setting, options)``, hashable: a DEKF's network), its code (``build(frame_dt,
    structure) -> Estimator``, its numbers arriving with the params) and its params (``numbers(setting,
    structure, numbers, options)``)."""

    name: str
    doc: str
    params: Mapping[str, Param]
    options: Mapping[str, Option] = field(default_factory=dict)
    structure: Callable[[Setting, Mapping], Any] = lambda setting, options: None
    build: Callable[[float, Any], Estimator] = None
    numbers: Callable[[Setting, Any, Mapping, Mapping], Any] = None


JERK = Param("variance of the acceleration increment per frame (the CA model's process noise)", positive, "(deg/s²)²", 1.0,
             tune=True, sweep=True)

KF = EstimatorKind(
    "kf", "CA-model Kalman filter on the measured angle, predicting across the delay with Φⁿ", {"q": JERK},
    build=lambda frame_dt, structure: kalman_estimator(frame_dt, 1.0, 1.0),
    numbers=lambda setting, structure, n, o: noise_params(n["q"], np.array([setting.sigma**2])))


def _network(setting: Setting, o) -> Network:
    return Network(o["hidden"], setting.scale, setting.frame_dt, o["reading"] == "residual")


DEKF = EstimatorKind(
    "dekf", "dual EKF with a neural motion model (paper 003), predicting across the delay with the network",
    {"q": JERK,
     "lam": Param("the weight filter's forgetting factor λ", unit_interval, "", 0.999),
     "r_e": Param("the weight filter's observation noise", positive, "", 0.5),
     "pw0": Param("the initial weights' variance", positive, "", 1e-4),
     "train_lr": Param("Adam's learning rate when trained first", positive, "", 1e-3)},
    {"hidden": Option("hidden units of the network", 4, lo=1, hi=256),
     "reading": Option("the network's reading of the paper: a residual on the CA model, or literal", "residual",
                       choices=("residual", "literal")),
     "seed": Option("the initial weights' draw", 0, lo=0, hi=2**32 - 1),
     "train_steps": Option("Adam steps training w0 and λ before the runs (0: none)", 0, lo=0, hi=100_000),
     "train_runs": Option("runs per training step", 8, lo=1, hi=100_000)},
    structure=_network,
    build=lambda frame_dt, net: dekf_estimator(net, None),
    numbers=lambda setting, net, n, o: dekf_params(net, q=n["q"], r=setting.sigma**2, lam=n["lam"], r_e=n["r_e"],
                                                   pw0=n["pw0"], key=jax.random.key(o["seed"])))
