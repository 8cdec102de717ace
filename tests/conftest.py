"""Test-session settings.

One CPU device per worker process: ``pytest -n 2`` already keeps both cores busy, where
``tracklab.configure()`` alone would make one device per core; splitting each chunk over
devices costs compile time and no test needs it, except the device-count test, which
starts its own processes with 2 and 4 devices.

Each worker runs on a core of its own (its CPU affinity, set before JAX starts; the processes
a test starts inherit it) when there are as many cores as workers. XLA sizes its thread pools
by the cores a process may run on: two workers that may each run on both cores split every
kernel and every compilation over two threads, and the two workers' threads then fight for
the cores. On 2 cores, clean clones run in turn (interleaved pairs): the whole suite took 313.5
and 277.3 s with one core per worker against 332.4 and 285.8 s with both workers on both cores
(CPU time 600 and 526 s against 625 and 534 s); one run-bound test alone (a 120-step tuning)
10.0 s against 12.4 s.

One persistent compilation cache for the whole session, in a fresh temporary folder
shared by the workers and every subprocess the tests start (the CLI's included): the
suite's time is mostly XLA compiling, and tests that build the same program (the same
experiment at the same chunk size, the CLI run on the same file, a sweep point run again
on its own) compile it once, and the runner's store of compiled programs
(``montecarlo.programs``) in the same folder, so that a process that meets a program another
one compiled loads it without tracing. Nothing is read from or written to the user's own cache.

XLA's backend at optimisation level 0 (``--xla_backend_optimization_level=0``): the tests make
small calls, so compiling is most of their time, and at level 0 LLVM compiles each kernel about
a fifth faster while the kernels run slower (the whole suite: 602 s at the default level, 501 s
at level 0, on 2 cores). The numbers differ from the default level's only in rounding (about
1e-13 relative), so a test that compares a subprocess's numbers with its own hands the
subprocess the same flags (the ``xla_flags`` fixture). The command and the library keep XLA's
default level. At level 0 XLA's CPU fusion emitters off compile faster for every world, so the
flags name that too: the airborne world, which at the default level compiles with them on
(``runner.World.compiler_options``), then compiles as the others (the suite: 362 s with the
airborne programs' emitters on, 322 s off).
"""

import os
import shutil
import tempfile

import pytest

COMPILE_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"


def suite_flags(devices=None):
    """The suite's XLA_FLAGS, with ``devices`` CPU devices (None: XLA's own default, one)."""
    return COMPILE_FLAGS + ("" if devices is None else f" --xla_force_host_platform_device_count={devices}")


if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + suite_flags(1)).strip()

from tracklab.runtime import configure  # noqa: E402

configure()  # what the `tracklab` command sets: Eigen single-threaded, 64-bit mode (the device count above)

_CACHE_KEY = "tracklab_jax_cache"


def _use_cache(folder):
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.5"
    os.environ["TRACKLAB_CACHE_DIR"] = folder  # the command's store of compiled programs: <folder>/programs
    from tracklab.montecarlo import programs

    programs.keep_in(os.path.join(folder, "programs"))


def _own_core(worker):
    """Pin an xdist worker to one core (its number modulo the cores), if there are enough for one each."""
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if len(cores) >= int(worker.get("workercount", len(cores) + 1)):
        try:
            os.sched_setaffinity(0, {cores[int(worker["workerid"].removeprefix("gw")) % len(cores)]})
        except OSError:  # a machine that does not let a process choose its cores: both workers on all
            pass


def pytest_configure(config):
    worker = getattr(config, "workerinput", None)
    if worker is not None and _CACHE_KEY in worker:  # an xdist worker: the controller's folder
        _own_core(worker)
        _use_cache(worker[_CACHE_KEY])
        return
    config._tracklab_cache = tempfile.mkdtemp(prefix="tracklab-tests-jax-cache-")
    _use_cache(config._tracklab_cache)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):  # pytest-xdist: hand the folder to each worker
    node.workerinput[_CACHE_KEY] = node.config._tracklab_cache


def pytest_unconfigure(config):
    folder = getattr(config, "_tracklab_cache", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def xla_flags():
    """``suite_flags``: XLA_FLAGS for a subprocess that is to compile as the suite does."""
    return suite_flags
