"""tracklab: Monte-Carlo evaluation of target-tracking filters in JAX.

Importing tracklab turns on JAX's 64-bit mode: ranges of 10⁴–10⁵ m with
milliradian angles need float64.

It also runs XLA's Eigen kernels (dense matrix products) single-threaded on the
CPU, unless XLA_FLAGS already says otherwise: with the multi-threaded Eigen
pool, long vmapped scans of small matrix products (the airborne trackers)
intermittently never finish, every thread idle in the pool
(``--xla_cpu_multi_thread_eigen=false``; it must be set before JAX starts its
CPU backend, so import tracklab before running any JAX computation).
"""

import os

if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from tracklab import filters  # noqa: E402
from tracklab.engine import FilterResult, FilterSpec, MonteCarloResult, monte_carlo, run_filter  # noqa: E402

__version__ = "0.1.0"


def load_experiment(path):
    """Read and validate an experiment file; ``.run()`` does what ``tracklab run`` does."""
    from tracklab.config import load_experiment as _load

    return _load(path)


__all__ = [
    "FilterResult", "FilterSpec", "MonteCarloResult", "__version__", "filters", "load_experiment",
    "monte_carlo", "run_filter",
]
