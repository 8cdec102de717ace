"""tracklab: Monte-Carlo evaluation of target-tracking filters in JAX.

Importing tracklab has no side effects: ``tracklab.configure()`` sets the process-wide JAX
settings it is measured with (one CPU device per core, single-threaded Eigen kernels,
64-bit mode); the ``tracklab`` command calls it first thing (``tracklab.runtime``).
"""

__version__ = "0.1.0"  # first: modules below read it while the package is being imported

from tracklab import filters, models, scenarios, sensors
from tracklab.config import load_experiment
from tracklab.config.python import experiment
from tracklab.worlds.tracking.recorded import evaluate
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


__all__ = [
    "Filter", "FilterContext", "FilterResult", "FilterSpec", "Layout", "Meas", "MonteCarloResult", "Out", "Param", "Prior",
    "SensorModel", "__version__", "configure", "declare", "evaluate", "experiment", "filter_context", "filters", "load_experiment", "models",
    "monte_carlo", "run_filter", "scenarios", "sensors", "tune",
]
