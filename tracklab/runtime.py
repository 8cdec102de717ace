"""The process-wide settings tracklab runs best with, as one call: ``configure()``.

Importing tracklab changes nothing: another JAX program in the same process sees JAX as
it was. ``tracklab`` (the command) calls ``configure()`` first thing; a Python user calls
it before anything touches JAX, as the documentation shows (docs/python.md). It sets:

* **One CPU device per core** (``--xla_force_host_platform_device_count``): the
  Monte-Carlo runner splits every chunk of runs over the devices, each share in its own
  thread with no synchronisation until the chunk's sums are added, which on the CPU is
  faster than XLA's splitting of each small kernel over threads.
* **Single-threaded Eigen kernels** (``--xla_cpu_multi_thread_eigen=false``): with the
  multi-threaded Eigen pool, long vmapped scans of small matrix products (the airborne
  trackers) intermittently never finish, every thread idle in the pool.
* **XLA's CPU fusion emitters off** (``--xla_cpu_use_fusion_emitters=false``): XLA then
  writes each fused kernel with its older element-by-element emitter. The lidar crossing's
  six-filter program compiles in about 3.3 s instead of 5.1 s and runs as fast or faster
  (``benchmarks/compile.md``). A world whose programs do better with them declares so
  (``runner.World.compiler_options``): the airborne closed loops turn them back on when two
  trackers share their code.
* **JAX's 64-bit mode** (``jax_enable_x64``), so that arrays a user builds (a filter's
  parameters, its constants) are float64 like the engine's.

The XLA flags are read when JAX starts its CPU backend, so they can only be set before
the first computation; a flag XLA_FLAGS already names is left as it is, and it also wins over a
world's own compiler options, which only the flags ``configure`` added give way to.

A run of several processes (``tracklab.processes``) must also start before the first
computation.

What float64 needs: the runner traces and runs every experiment in the precision asked
for (``float64`` by default, inside ``jax.enable_x64``), whatever the global mode, and
casts the parameters to it. Only arrays built outside it follow JAX's global mode: with
64-bit mode off, ``jnp.asarray(1e-3)`` in a user's filter factory is float32. Call
``configure()`` (or ``jax.config.update("jax_enable_x64", True)``) before building them.
"""

from __future__ import annotations

import functools
import os


def usable_cores() -> int:
    """The CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover - JAX moved it
        return False
    return bool(xla_bridge.backends_are_initialized())


_USER_FLAGS: str | None = None  # XLA_FLAGS as the user set them, before ``configure`` added its own


def _user_flags() -> str:
    """XLA_FLAGS as the user set them: without the flags ``configure`` added in this process."""
    return os.environ.get("XLA_FLAGS", "") if _USER_FLAGS is None else _USER_FLAGS


def _not_named(options: dict, flags: str) -> dict:
    return {k: v for k, v in options.items() if k not in flags}


def not_in_xla_flags(options: dict) -> dict:
    """The XLA options of ``options`` that the user's XLA_FLAGS do not name: a flag the user set is theirs."""
    return _not_named(options, _user_flags())


@functools.lru_cache(maxsize=32)
def xla_knows(name: str, value) -> bool:
    """Whether this XLA takes the compile option ``name`` (options come and go between releases):
    a trivial program compiled with it, once per process."""
    import jax

    try:
        jax.jit(lambda: 0).lower().compile(compiler_options={name: value})
    except Exception:  # noqa: BLE001 - XLA's error for an option it does not have
        return False
    return True


def configure(*, cpu_devices: int | None = None, eigen_threads: bool = False, fusion_emitters: bool = False,
              float64: bool = True) -> dict:
    """Set the process-wide JAX settings tracklab is measured with (see the module's doc).

    ``cpu_devices``: CPU devices to create (default: one per usable core); ``eigen_threads``:
    keep XLA's multi-threaded Eigen pool; ``fusion_emitters``: keep XLA's CPU fusion emitters;
    ``float64``: turn on JAX's 64-bit mode. A flag that XLA_FLAGS already names is kept.
    Returns the settings in force. Raises ``RuntimeError`` when JAX's backend has already
    started with a different device count (call it first).
    """
    want = {}
    if not eigen_threads:
        want["xla_cpu_multi_thread_eigen"] = "false"
    if not fusion_emitters:
        want["xla_cpu_use_fusion_emitters"] = "false"
    want["xla_force_host_platform_device_count"] = int(cpu_devices or usable_cores())
    global _USER_FLAGS
    if _USER_FLAGS is None:
        _USER_FLAGS = os.environ.get("XLA_FLAGS", "")
    want = _not_named(want, os.environ.get("XLA_FLAGS", ""))  # a flag already set is kept
    started = _backend_started()
    if want and not started:
        flags = [os.environ.get("XLA_FLAGS", "")] + [f"--{k}={v}" for k, v in want.items()]
        os.environ["XLA_FLAGS"] = " ".join(flags).strip()

    import jax

    if float64:
        jax.config.update("jax_enable_x64", True)
    if started and cpu_devices is not None and jax.default_backend() == "cpu" and jax.local_device_count() != cpu_devices:
        raise RuntimeError(f"JAX started with {jax.local_device_count()} CPU devices before tracklab.configure() was "
                           f"called: call it before any JAX computation to get {cpu_devices}")
    return {"xla_flags": os.environ.get("XLA_FLAGS", ""), "float64": bool(jax.config.jax_enable_x64),
            "backend_started": started}
