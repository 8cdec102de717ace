"""The Monte-Carlo runner: the one loop over runs, for every world.

A *world* is what one kind of experiment simulates (open-loop tracking, the
airborne closed loop, the servo). To the runner it is a pure function of one
chunk of runs, ``chunk(params, keys, live, exclude) -> sums``, plus a hashable
``structure`` that fixes everything that function compiles to:

* ``params`` is a pytree holding every number of the experiment (scenario,
  sensors, prior, filters, engagement, servo …). It is an argument of the
  compiled program, so editing a number and running again reuses the program
  (in this process from the runner's table, in a new one from JAX's persistent
  cache). The program depends on the structure, the pytree's shape, the chunk
  size, the precision and the devices — never on the run count, which only
  decides how many chunks run.
* ``keys[i]`` is run ``idx[i]``'s key, ``fold_in(key, idx[i])``: a run draws the
  same numbers whatever the chunk size, device count or padding.
* ``live`` (B,) marks real runs (the last chunk and the devices' shares are
  padded with dead ones); ``exclude`` (lanes, B) marks runs left out of a lane's
  sums (a lane: one compared filter, tracker or case).
* ``sums`` is a ``Sums`` record over the chunk's live runs, whose fields say how their
  parts (of the devices, the processes and the chunks) combine: ``add`` adds up,
  ``max`` keeps the largest, ``first`` is run 0's (kept from the first chunk),
  ``per_run`` holds per-run samples (``values`` (lanes, Q, B), ``ok`` (lanes, B),
  optionally ``kept`` (lanes, K, B)) streamed into ``samples.RunSamples``, and
  ``diverged`` (lanes, B) flags the runs that turned bad: the chunk is run again with
  them excluded from the start (a run drops out of the sums only from the step it
  turns bad otherwise). Each device keeps the sums of its share of a chunk (the
  program passes nothing between devices, so no device ever waits on another inside
  it); the host combines the devices' parts. ``add``, ``max`` and ``first`` are
  dictionaries whose keys do not collide; the caller gets them as one (``merged``).

Several processes (``tracklab.processes``: one per host or per GPU) share
every chunk: process p runs its slice of the chunk's runs on its own devices, and
the processes' combined parts are gathered once per chunk (one collective) and
combined by the same rules, so every process holds the same sums and a run's
numbers do not depend on the process count.

Sums are added on the host in float64, chunk by chunk: memory grows with
chunk × steps, never with runs × steps. ``compile_s`` is the time spent
tracing, lowering and compiling the program (or loading it from the persistent
cache); 0 when this process already holds it.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Hashable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.checks import check_key
from tracklab.montecarlo import programs
from tracklab.montecarlo.samples import RunSamples
from tracklab.runtime import not_in_xla_flags, xla_knows


class Sums(NamedTuple):
    """A chunk's sums over its live runs, each field combined over parts by its own rule (see the
    module's doc): ``add`` added, ``max`` the largest kept, ``first`` run 0's (the first part's),
    ``per_run`` the runs' samples side by side, ``diverged`` the runs' flags side by side."""

    add: Any = None
    max: Any = None
    first: Any = None
    per_run: Any = None
    diverged: Any = None


def merged(sums: Sums) -> dict:
    """``add``, ``max`` and ``first`` as one dictionary (nested dictionaries merged key by key)."""

    def union(a, b):
        if not isinstance(a, dict) or not isinstance(b, dict):
            return b if a is None else a
        return {k: union(a.get(k), b.get(k)) if k in a and k in b else (a[k] if k in a else b[k]) for k in {**a, **b}}

    out: dict = {}
    for part in (sums.add, sums.max, sums.first):
        if part is not None:
            out = union(out, part)
    return out


def lane_key(i: int) -> str:
    """The key of lane ``i``'s sums inside a chunk: lanes are numbered, not named, so that a label is
    no part of what a program is compiled for (a relabelled file runs the same program)."""
    return f"#{i}"


def labelled(sums: dict, labels) -> dict:
    """``sums`` with each lane's key (``lane_key``) replaced by its label; other keys as they are."""
    names = {lane_key(i): label for i, label in enumerate(labels)}
    return {names.get(k, k): v for k, v in sums.items()}


class World(NamedTuple):
    """What the runner needs of a world (see the module's doc)."""

    structure: Hashable  # all that ``chunk`` compiles to, besides the params' pytree structure and shapes
    chunk: Callable  # (params, keys (B,), live (B,), exclude (lanes, B)) -> Sums; pure
    lanes: int  # rows of ``exclude``
    chunk_size: int  # runs per chunk (a multiple of nothing in particular; padded for the devices)
    # XLA options its chunk programs compile with: (name, value) pairs; one that XLA_FLAGS names is
    # left to XLA_FLAGS (``runtime.not_in_xla_flags``, as ``configure`` leaves a flag the user set)
    compiler_options: tuple = ()


def world_compiler_options(world: World) -> dict | None:
    """The XLA options ``world``'s programs compile with (None: XLA's, as XLA_FLAGS set them);
    an option this XLA does not have is left out."""
    options = not_in_xla_flags(dict(world.compiler_options))
    return {k: v for k, v in options.items() if xla_knows(k, v)} or None


@dataclass
class Outcome:
    """What the runner hands back to the world that asked."""

    sums: Any  # the sums over all runs (``merged``: host, float64; ``first`` leaves from the first chunk)
    runs: int
    chunk: int
    wall_s: float  # the whole call
    compile_s: float  # tracing, lowering and compiling (or loading from the persistent cache)
    chunks: int
    samples: RunSamples | None = None  # the per-run samples' moments, when the world gives them


def combine_devices(parts: Sums, B, xp=np) -> Sums:
    """One chunk's sums from the devices' parts (leading axis: device), each field by its rule;
    ``xp``: numpy on the host, jax.numpy inside a traced function."""
    side_by_side = lambda v: xp.moveaxis(v, 0, -2).reshape(v.shape[1:-1] + (-1,))[..., :B]  # noqa: E731
    tree = jax.tree_util.tree_map
    return Sums(tree(lambda v: xp.sum(v, axis=0), parts.add), tree(lambda v: xp.max(v, axis=0), parts.max),
                tree(lambda v: v[0], parts.first), tree(side_by_side, parts.per_run), tree(side_by_side, parts.diverged))


def host_sums(parts, B, lead=0):
    """One chunk's sums on the host from a compiled program's output: the devices' parts
    (their device axis at position ``lead``: 1 behind a sweep's points) combined by
    ``combine_devices``."""
    parts = jax.tree_util.tree_map(lambda v: np.moveaxis(np.asarray(v), lead, 0), jax.device_get(parts))
    return combine_devices(parts, B)


def run_keys(key, idx):
    """Each run's key: run i draws from ``fold_in(key, i)``."""
    return jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)


def per_device(world: World, devices=None) -> Callable:
    """``(params, key, idx, live, exclude) -> parts``: each of ``devices`` (default: this process's)
    runs its share of the runs ``idx`` and keeps its own sums (every leaf gains a leading device
    axis). Nothing passes between the devices, so no device ever waits for another inside the program."""
    devices = jax.local_devices() if devices is None else devices
    n_dev = len(devices)

    def local(params, key, idx, live, exclude):
        parts = world.chunk(params, run_keys(key, idx), live, exclude)
        return jax.tree_util.tree_map(lambda v: v[None], parts)

    if n_dev == 1:
        return local
    mesh = jax.sharding.Mesh(np.array(devices), ("runs",))
    rep, runs_axis = jax.sharding.PartitionSpec(), jax.sharding.PartitionSpec("runs")
    shares = jax.shard_map(local, mesh=mesh, in_specs=(rep, rep, runs_axis, runs_axis,
                                                         jax.sharding.PartitionSpec(None, "runs")),
                           out_specs=runs_axis, check_vma=False)

    def split(params, key, idx, live, exclude):
        pad = -idx.shape[0] % n_dev  # dead runs to fill the last device
        if pad:
            idx = jnp.concatenate([idx, jnp.zeros((pad,), idx.dtype)])
            live = jnp.concatenate([live, jnp.zeros((pad,), bool)])
            exclude = jnp.concatenate([exclude, jnp.ones(exclude.shape[:-1] + (pad,), bool)], axis=-1)
        return shares(params, key, idx, live, exclude)

    return split


def sharded(world: World) -> Callable:
    """``(params, key, idx, live, exclude) -> sums`` (``merged``) of the runs ``idx``: traceable (jit, grad,
    vmap over params), the devices' parts combined inside the function (tuning differentiates
    through the combined sums). The runs are split over every process's devices: in a run of
    several processes, each runs its share and the combined sums (and so the gradients) are
    the same in all of them."""
    parts = per_device(world, jax.devices())

    def combined(params, key, idx, live, exclude):
        return merged(combine_devices(parts(params, key, idx, live, exclude), idx.shape[0], jnp))

    return combined


def in_precision(params, precision: str):
    """``params`` with every floating leaf in the working precision ("float32": single)."""
    dtype = jnp.float32 if precision == "float32" else jnp.float64

    def cast(a):
        a = np.asarray(a) if not isinstance(a, jax.Array) else a
        return jnp.asarray(a, dtype) if jnp.issubdtype(a.dtype, jnp.floating) else jnp.asarray(a)

    return jax.tree_util.tree_map(cast, params)


_PROGRAMS: OrderedDict = OrderedDict()  # (structure, shapes, chunk, precision, devices) -> compiled program
_KEEP = 32
compiles = 0  # programs compiled (or loaded from disk) by this process


# on an accelerator, the share of a device's memory that a chunk's per-run arrays may fill (the
# rest holds XLA's temporaries: every filter's per-run intermediates of a step), and the most runs
# a device's share of a chunk holds: far past the runs that keep all of a GPU's cores busy
ACCELERATOR_SHARE = 1 / 8
ACCELERATOR_RUNS = 2**18


def accelerator_memory() -> int | None:
    """Bytes of memory of each device on an accelerator (a GPU's ``memory_stats()["bytes_limit"]``,
    the smallest over this process's devices); None on the CPU, where a chunk is sized for the
    cache instead."""
    devices = jax.local_devices()
    if devices[0].platform == "cpu":
        return None
    limits = [(d.memory_stats() or {}).get("bytes_limit") for d in devices]
    return int(min(limits)) if all(limits) else None


def accelerator_runs(per_run_bytes: float) -> int | None:
    """Runs per device of a chunk on an accelerator, for per-run arrays of ``per_run_bytes``: as
    many as fill ``ACCELERATOR_SHARE`` of its memory, a power of two, at most
    ``ACCELERATOR_RUNS`` and at least 1; None on the CPU."""
    memory = accelerator_memory()
    if memory is None:
        return None
    fit = int(memory * ACCELERATOR_SHARE // max(per_run_bytes, 1.0))
    return min(1 << (max(fit, 1).bit_length() - 1), ACCELERATOR_RUNS)


def sized_chunk(per_run_bytes: float, budget: int, smallest: int, cpu_per_device: int) -> int:
    """Runs per chunk, for per-run arrays of ``per_run_bytes``, when the file does not say: on an
    accelerator ``accelerator_runs`` per device; on the CPU as many as keep them within ``budget``
    bytes, at least ``smallest`` and at most ``cpu_per_device`` per device (a world's share that
    still stays in the cache)."""
    devices = jax.device_count()
    per_device = accelerator_runs(per_run_bytes)
    if per_device is not None:
        return per_device * devices
    return int(np.clip(budget // max(per_run_bytes, 1.0), smallest, cpu_per_device * devices))


def budget_chunk(per_run_bytes: float, runs: int | None = None, budget: int = 2**28) -> int:
    """Runs per chunk of a closed-loop world when the file does not say: as many as keep a chunk's
    per-run arrays (``per_run_bytes`` each) within ``budget`` bytes (256 MiB), at most 128 per
    device (larger shares run no faster on the CPU: each tracker's per-tick state leaves the cache;
    ``benchmarks/bench_closed_loop.py``) and at least one; on an accelerator as many as its memory
    holds (``accelerator_runs``); no more than ``runs`` need (rounded up to the devices): a
    closed-loop run is thousands of ticks, so dead runs padding a chunk cost."""
    devices = jax.device_count()
    chunk = sized_chunk(per_run_bytes, budget, devices, 128)
    return chunk if not runs else min(chunk, -(-int(runs) // devices) * devices)


def share(world: World) -> int:
    """Runs of every chunk this process runs: the chunk split evenly over the processes (a
    chunk then holds ``share × processes`` runs, the last ones dead)."""
    return -(-world.chunk_size // jax.process_count())


def program(world: World, params, precision: str = "float64", points: int | None = None):
    """The compiled chunk program of ``world`` for params shaped like ``params`` (in ``precision``):
    (callable, seconds spent tracing, lowering and compiling; 0 if this process already held it).
    It runs this process's ``share`` of a chunk on its own devices. A program kept on disk by an
    earlier process (``programs``, when the store is on) is loaded instead of traced and compiled.

    ``points``: the params hold that many parameter sets along a leading axis (a sweep's grid
    points), evaluated on the same runs (common random numbers) by one program."""
    global compiles
    B = share(world)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    shapes = tuple((np.shape(a), jnp.result_type(a).name) for a in leaves)
    key = (world.structure, treedef, shapes, B, precision, points, tuple(str(d) for d in jax.local_devices()))
    if key in _PROGRAMS:
        _PROGRAMS.move_to_end(key)
        return _PROGRAMS[key], 0.0
    t0 = time.perf_counter()
    stored = programs.key(world.structure, treedef, shapes, B, precision, points)
    compiled = programs.load(stored) if stored else None
    if compiled is None:
        fn = per_device(world)
        lead = ()
        if points is not None:  # parts (points, devices, …)
            fn = jax.vmap(fn, in_axes=(0, None, None, None, 0))
            lead = (points,)
        args = (params, jax.random.key(0), np.zeros((B,), np.uint32), np.zeros((B,), bool),
                np.zeros(lead + (world.lanes, B), bool))
        lowered = jax.jit(fn).lower(*args)
        compiled, here = programs.compile_here(lowered, world_compiler_options(world))
        if stored and here:  # XLA compiled it in this process (not loaded by JAX from its own cache)
            programs.store(stored, compiled)
    compile_s = time.perf_counter() - t0
    compiles += 1
    _PROGRAMS[key] = compiled
    while len(_PROGRAMS) > _KEEP:
        _PROGRAMS.popitem(last=False)
    return compiled, compile_s


class Accumulator:
    """Host-side sums over chunks, in float64, each field by its rule; per-run samples streamed into
    ``samples``."""

    def __init__(self):
        self.total = None
        self.samples = None

    def add(self, sums: Sums):
        sums = jax.tree_util.tree_map(np.asarray, sums)
        if sums.per_run is not None:
            self.samples = self.samples or RunSamples()
            self.samples.add(sums.per_run["values"], sums.per_run["ok"], sums.per_run.get("kept"))
        wide = lambda v: np.asarray(v, np.float64)  # noqa: E731
        tree = jax.tree_util.tree_map
        if self.total is None:
            self.total = Sums(tree(wide, sums.add), tree(wide, sums.max), sums.first)
            return
        self.total = Sums(tree(lambda a, b: a + wide(b), self.total.add, sums.add),
                          tree(np.fmax, self.total.max, sums.max), self.total.first)


def gather_processes(tree):
    """Every process's ``tree`` (numpy leaves, the same structure and shapes everywhere), stacked
    along a new leading process axis: one collective for the whole tree, exact for any dtype
    (the leaves travel as float64, which holds every float32, int32 and bool value)."""
    from jax.experimental import multihost_utils

    leaves, treedef = jax.tree_util.tree_flatten(tree)
    leaves = [np.asarray(v) for v in leaves]
    flat = np.concatenate([v.astype(np.float64).ravel() for v in leaves]) if leaves else np.zeros(0)
    with jax.enable_x64(True):
        every = np.asarray(multihost_utils.process_allgather(flat))  # (processes, size)
    out, i = [], 0
    for v in leaves:
        out.append(every[:, i:i + v.size].reshape((every.shape[0],) + v.shape).astype(v.dtype))
        i += v.size
    return jax.tree_util.tree_unflatten(treedef, out)


def pick(tree, j):
    """Parameter set (or its sums) ``j`` of a tree stacked along a leading axis (``points``)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[j], tree)


def run(world: World, params, runs: int, key, *, precision: str = "float64", points: int | None = None,
        progress: Callable[[int, int], None] | None = None,
        enough: Callable[[Any, RunSamples | None, int], bool] | None = None) -> Outcome:
    """Run ``runs`` Monte-Carlo runs of ``world`` with ``params``, chunk by chunk; the sums of all runs.

    ``key``: an integer seed, a JAX key or a raw uint32[2] key, one and the same key
    (``checks.check_key``). ``precision = "float32"`` traces and runs the world in single
    precision (JAX's 64-bit mode off for it); the sums are added on the host in float64 either
    way. ``points``: ``params`` holds that many parameter sets along a leading axis, and every
    sum has that leading axis. ``progress(done, runs)`` is called after every chunk.
    ``enough(sums, samples, done)``, when given, is asked after every chunk: the run stops as soon
    as it says yes (``runs`` is then the most it may take), and ``Outcome.runs`` is what ran.
    """
    t_start = time.perf_counter()
    with jax.enable_x64(precision == "float64"):
        key = check_key("runner.run", "key", key)
        params = in_precision(params, precision)
        fn, compile_s = program(world, params, precision, points)
        B = share(world)  # this process's runs of every chunk
        n_proc, me = jax.process_count(), jax.process_index()
        acc = Accumulator()
        n_chunks = -(-runs // (B * n_proc))
        lead = 1 if points is not None else 0

        def combined(parts):
            return host_sums(parts, B, lead)

        no_exclusion = jnp.asarray(np.zeros(((points,) if points is not None else ()) + (world.lanes, B), bool))
        for c in range(n_chunks):
            idx = np.arange((c * n_proc + me) * B, (c * n_proc + me + 1) * B, dtype=np.uint32)
            args = (params, key, jnp.asarray(idx), jnp.asarray(idx < runs))
            sums = combined(fn(*args, no_exclusion))
            if sums.diverged is not None and sums.diverged.any():  # the chunk again, those runs left out from their first step
                sums = combined(fn(*args, jnp.asarray(sums.diverged)))
            if n_proc > 1:  # every process's part of the chunk, in run order
                sums = combine_devices(gather_processes(sums), B * n_proc)
            acc.add(sums)
            done = min((c + 1) * B * n_proc, runs)
            if progress:
                progress(done, runs)
            if enough is not None and done < runs and enough(acc.total, acc.samples, done):
                runs, n_chunks = done, c + 1
                break
    return Outcome(merged(acc.total), runs, B * n_proc, time.perf_counter() - t_start, compile_s, n_chunks, acc.samples)
