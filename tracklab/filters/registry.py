"""Every filter kind an experiment file may name: the declarations beside each kind's code.

A kind is declared once, in its own module (a ``FilterKind``, see ``tracklab.filters.kind``);
its import below and its entry in ``KINDS`` register it. The configuration, tuning, sweeps and ``tracklab list``
read the kinds here, in this order.
"""

from __future__ import annotations

from tracklab.filters.kind import FilterKind
from tracklab.parameters import Param

# one line per module, in the order `tracklab list` shows
from tracklab.filters.kalman import KF, EKF, CMKF, SEQUENTIAL_EKF
from tracklab.filters.polar import POLAR_KF
from tracklab.filters.unscented import UKF
from tracklab.filters.alphabeta import ALPHA_BETA, ALPHA_BETA_GAMMA
from tracklab.filters.strong_tracking import STF
from tracklab.filters.imm import IMM
from tracklab.filters.dual_ekf import DEKF
from tracklab.filters.error_space import ERROR_SPACE
from tracklab.filters.association import association_kinds

# the Gaussian filters an association (nn, pdaf, ipda) may be built on
NN, SNF, PDAF, IPDA = association_kinds({k.name: k for k in (KF, EKF, CMKF, SEQUENTIAL_EKF, POLAR_KF, UKF)})


KINDS: dict[str, FilterKind] = {k.name: k for k in (KF, EKF, CMKF, SEQUENTIAL_EKF, POLAR_KF, UKF, ALPHA_BETA,
                                                    ALPHA_BETA_GAMMA, STF, IMM, DEKF, ERROR_SPACE, NN, SNF, PDAF,
                                                    IPDA)}


def declarations(name) -> list[Param]:
    """Every kind's declaration of the parameter ``name``."""
    return [k.params[name] for k in KINDS.values() if name in k.params]


def _names(chosen) -> tuple[str, ...]:
    return tuple(dict.fromkeys(n for k in KINDS.values() for n, p in k.params.items() if chosen(p)))


TUNABLE = _names(lambda p: p.tune)  # what `tracklab tune --params` may name
SCALABLE = _names(lambda p: p.sweep)  # what `tracklab sweep --grid` may scale

