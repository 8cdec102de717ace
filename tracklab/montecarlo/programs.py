"""Compiled chunk programs kept on disk, found again by a new process before any tracing.

JAX's persistent compilation cache finds a compiled program by the hash of its lowered
module, so a new process still traces and lowers the world first — most of a warm start
(6 of 8 s for the lidar experiment's six filters). This store finds a program by what fixes
it before any tracing: the world's structure, the params' pytree structure and shapes, the
runs per chunk, the precision, the points of a sweep and the devices, together with what the
library's code and JAX make of them — the source of every ``tracklab`` module, the versions
of jax and jaxlib, the JAX settings that change a trace, ``XLA_FLAGS`` and the CPU. It keeps
the compiled executable (``jax.experimental.serialize_executable``).

A program is stored only when
  * all of it is known by the key: the library's own code, whose source is part of the key, and
    code of one's own (a filter, a truth, a sensor's h), which the structure and the params'
    pytree hold by what it traces to (its jaxprs and constants: ``pytree.Code``,
    ``worlds.tracking.lanes.program_key``). The structure's text and the params' pytree
    structure name no other Python object (one held by identity shows as ``<…>``: its code
    could change under the same name) and no elided array, and every pytree node type is
    tracklab's, JAX's or a built-in one;
  * XLA compiled it in this process: one that JAX loaded from its own persistent cache
    serialises without some of its kernels' code;
  * it runs on the CPU (where the only kernels outside XLA a program calls are LAPACK's, set
    up before loading) in a run of one process.

``keep_in(folder)`` turns the store on (the ``tracklab`` command does, beside JAX's cache);
nothing is stored before it is called. Files are written atomically (a temporary name, then a
rename) and only under the folder's own names (``*.program``); the least recently used beyond
``KEEP`` are removed. A file that cannot be read (truncated, another jaxlib) is ignored and
written anew.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import platform
import tempfile
from pathlib import Path

import jax

KEEP = 100  # programs kept in the folder (least recently used removed first; a program is 1–20 MB)
SUFFIX = ".program"
_FOLDER: Path | None = None
loaded = 0  # programs this process loaded from the folder


def keep_in(folder) -> None:
    """Keep compiled programs in ``folder`` (None: stop)."""
    global _FOLDER
    _FOLDER = None if folder is None else Path(folder)


def folder() -> Path | None:
    return _FOLDER


@functools.lru_cache(maxsize=1)
def _library_source() -> str:
    """A hash of every module of the library: a program is valid for this code only."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def _machine() -> str:
    """The CPU the programs are compiled for (a program built for one CPU's instructions may not
    run on another sharing the same home folder)."""
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "flags")):
                    cpu += line
                if line.strip() == "":
                    break
    except OSError:
        cpu = platform.processor()
    return f"{platform.machine()} {hashlib.sha256(cpu.encode()).hexdigest()}"


def _node_types(treedef):
    data = treedef.node_data()
    if data is not None:
        yield data[0]
    for child in treedef.children():
        yield from _node_types(child)


def _own_type(t) -> bool:
    module = getattr(t, "__module__", "") or ""
    return module == "builtins" or module.split(".")[0] in ("tracklab", "collections", "jax", "jaxlib")


def key(structure, treedef, shapes, chunk: int, precision: str, points) -> str | None:
    """The store's key of a program, or None when it must not be stored (see the module's doc)."""
    if _FOLDER is None or jax.process_count() != 1 or jax.default_backend() != "cpu":
        return None
    text = f"{structure!r}\n{treedef}"
    if "<" in text or "..." in text or not all(_own_type(t) for t in _node_types(treedef)):
        return None
    import jaxlib

    backend = jax.local_devices()[0].client
    settings = {name: getattr(jax.config, name, None) for name in (
        "jax_threefry_partitionable", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
        "jax_default_prng_impl")}
    return "\n".join([
        text, repr(shapes), f"chunk={chunk} precision={precision} points={points}",
        repr([str(d) for d in jax.local_devices()]), backend.platform_version,
        f"jax {jax.__version__} jaxlib {jaxlib.__version__}", repr(sorted(settings.items())),
        os.environ.get("XLA_FLAGS", ""), _machine(), _library_source(),
    ])


def _path(k: str) -> Path:
    return _FOLDER / (hashlib.sha256(k.encode()).hexdigest() + SUFFIX)


@functools.lru_cache(maxsize=1)
def _prepare_kernels() -> None:
    """Set up the library kernels a program may call (JAX sets up LAPACK's when it first lowers
    a linear-algebra operation; a loaded program has not been lowered in this process)."""
    import jax.numpy as jnp
    import numpy as np

    jax.jit(jnp.linalg.cholesky).lower(np.eye(2))


def load(k: str):
    """The program stored under ``k``, or None."""
    global loaded
    path = _path(k)
    try:
        with open(path, "rb") as f:
            stored_key, payload = pickle.load(f)
        if stored_key != k:
            return None
        from jax.experimental import serialize_executable

        _prepare_kernels()
        compiled = serialize_executable.deserialize_and_load(*payload, execution_devices=jax.local_devices())
    except Exception:  # missing, truncated, written by another jaxlib: compile it again
        return None
    try:
        os.utime(path)  # recently used
    except OSError:
        pass
    loaded += 1
    return compiled


_jax_cache_hits = 0


def _count_jax_cache_hits(event, **_):
    global _jax_cache_hits
    if event == "/jax/compilation_cache/cache_hits":
        _jax_cache_hits += 1


@functools.lru_cache(maxsize=1)
def _listen() -> None:
    jax.monitoring.register_event_listener(_count_jax_cache_hits)


def compile_here(lowered, compiler_options=None):
    """``lowered.compile(compiler_options)``, and whether XLA compiled it in this process (True)
    rather than JAX loading it from its persistent cache (an executable JAX loaded serialises
    without some of its kernels' code, so only the first may be stored)."""
    _listen()
    before = _jax_cache_hits
    compiled = lowered.compile(compiler_options=compiler_options)
    return compiled, _jax_cache_hits == before


def store(k: str, compiled) -> None:
    """Keep ``compiled`` under ``k`` (atomically); a folder that cannot be written is left alone."""
    from jax.experimental import serialize_executable

    try:
        payload = serialize_executable.serialize(compiled)
        _FOLDER.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=_FOLDER, prefix=".writing-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                pickle.dump((k, payload), f, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, _path(k))
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _evict()
    except Exception:  # a read-only or full disk, an executable that cannot be serialised: not kept
        return


def _evict() -> None:
    files = sorted(_FOLDER.glob("*" + SUFFIX), key=lambda p: p.stat().st_mtime)
    for p in files[:-KEEP]:
        p.unlink(missing_ok=True)
