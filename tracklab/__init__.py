"""tracklab: Monte-Carlo evaluation of target-tracking filters in JAX.

Importing tracklab turns on JAX's 64-bit mode: ranges of 10⁴–10⁵ m with
milliradian angles need float64.

It also runs XLA's Eigen kernels (dense matrix products) single-threaded on the
CPU, unless XLA_FLAGS already says otherwise: with the multi-threaded Eigen
pool, long vmapped scans of small matrix products (the airborne trackers)
intermittently never finish, every thread idle in the pool
(``--xla_cpu_multi_thread_eigen=false``; it must be set before JAX starts its
CPU backend, so import tracklab before running any JAX computation).

And it gives JAX one CPU device per core this process may use, unless XLA_FLAGS
already sets ``--xla_force_host_platform_device_count``: the Monte-Carlo engine
splits every chunk of runs over the devices, each device running its share in
its own thread with no synchronisation until the chunk's sums are added, which
on the CPU is faster than XLA's splitting of each small kernel over threads.
"""

import os

if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ["XLA_FLAGS"] += f" --xla_force_host_platform_device_count={_cores}"

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from tracklab import filters  # noqa: E402
from tracklab.filtering import FilterResult, run_filter  # noqa: E402
from tracklab.worlds.tracking import FilterSpec, MonteCarloResult, monte_carlo  # noqa: E402

__version__ = "0.1.0"


def load_experiment(path):
    """Read and validate an experiment file; ``.run()`` does what ``tracklab run`` does."""
    from tracklab.config import load_experiment as _load

    return _load(path)


__all__ = [
    "FilterResult", "FilterSpec", "MonteCarloResult", "__version__", "filters", "load_experiment",
    "monte_carlo", "run_filter",
]
