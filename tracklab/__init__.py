"""tracklab: Monte-Carlo evaluation of target-tracking filters in JAX.

Importing tracklab has no side effects: ``tracklab.configure()`` sets the process-wide JAX
settings it is measured with (one CPU device per core, single-threaded Eigen kernels,
64-bit mode); the ``tracklab`` command calls it first thing (``tracklab.runtime``).

The public names (``__all__``) are imported on first use (PEP 562): ``import tracklab``
itself loads neither JAX nor the engine, so the ``tracklab`` command starts, and catches
Ctrl-C, before anything heavy is imported. ``tracklab.run_filter``, ``from tracklab import
run_filter`` and ``dir(tracklab)`` see every public name as usual.
"""

from __future__ import annotations

import importlib

TYPE_CHECKING = False  # typing.TYPE_CHECKING, without importing typing; checkers read it as true
__version__ = "0.1.0"

_PUBLIC = {  # name -> the module that defines it (a subpackage: itself)
    "filters": "tracklab.filters",
    "models": "tracklab.models",
    "scenarios": "tracklab.scenarios",
    "sensors": "tracklab.sensors",
    "load_experiment": "tracklab.config",
    "experiment": "tracklab.config.python",
    "evaluate": "tracklab.worlds.tracking.recorded",
    "FilterResult": "tracklab.filtering",
    "run_filter": "tracklab.filtering",
    "FilterContext": "tracklab.filters.context",
    "SensorModel": "tracklab.filters.context",
    "filter_context": "tracklab.filters.context",
    "Filter": "tracklab.filters.core",
    "Meas": "tracklab.filters.core",
    "Out": "tracklab.filters.core",
    "Prior": "tracklab.filters.core",
    "declare": "tracklab.filters.factory",
    "Layout": "tracklab.models",
    "Param": "tracklab.parameters",
    "configure": "tracklab.runtime",
    "tune": "tracklab.studies.tune",
    "FilterSpec": "tracklab.worlds.tracking.lanes",
    "MonteCarloResult": "tracklab.worlds.tracking.outcome",
    "monte_carlo": "tracklab.worlds.tracking.outcome",
}

__all__ = sorted([*_PUBLIC, "__version__"], key=str.lower)


def __getattr__(name: str):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'tracklab' has no attribute {name!r}")
    mod = importlib.import_module(module)
    value = mod if module == f"{__name__}.{name}" else getattr(mod, name)
    globals()[name] = value  # found directly from now on
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))


if TYPE_CHECKING:  # what type checkers and editors read; at run time __getattr__ serves them
    from tracklab import filters, models, scenarios, sensors
    from tracklab.config import load_experiment
    from tracklab.config.python import experiment
    from tracklab.filtering import FilterResult, run_filter
    from tracklab.filters.context import FilterContext, SensorModel, filter_context
    from tracklab.filters.core import Filter, Meas, Out, Prior
    from tracklab.filters.factory import declare
    from tracklab.models import Layout
    from tracklab.parameters import Param
    from tracklab.runtime import configure
    from tracklab.studies.tune import tune
    from tracklab.worlds.tracking.lanes import FilterSpec
    from tracklab.worlds.tracking.outcome import MonteCarloResult, monte_carlo
    from tracklab.worlds.tracking.recorded import evaluate
