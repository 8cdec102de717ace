"""Monte-Carlo engine: simulate -> measure -> filter -> streaming statistics.

One jitted function handles a chunk of runs: truth, measurements and the prior
of run i come from ``fold_in(key, i)``; every filter runs over the chunk with
``vmap`` inside a time-major ``lax.scan``; the per-run errors are reduced over
the chunk to per-step sums (and maxima). Chunks are added up on the host, so
memory grows with ``chunk × steps``, never with ``runs × steps``, and the
statistics do not depend on the chunk size or on how many devices share a
chunk (the run axis is sharded over all devices when there are several).

A run in which a filter produces NaN/inf or a covariance that is not positive
definite is *diverged* for that filter: it is counted and left out of that
filter's averages; it never stops the batch.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from tracklab.filters.core import Filter, Meas, Prior
from tracklab.linalg import mahalanobis2, mahalanobis2_logdet
from tracklab.models import Kinematic
from tracklab.sensors import SensorSuite


@dataclass(frozen=True)
class FilterSpec:
    """A filter as the engine runs it: the filter, its label and its reporting layout."""

    label: str
    kind: str
    filter: Filter
    model: Kinematic  # the reporting frame's layout (pos_idx, vel_idx, embed)
    prior_extra_var: float = 0.0  # prior variance of states beyond position/velocity
    view: Callable | None = None  # what the filter sees of the sensors' z (T, M) -> (T, m)

    @property
    def pv_index(self) -> np.ndarray:
        """Indices of [x, ẋ, y, ẏ, ...] (the truth's CV layout) in the filter's report."""
        m = self.model
        return np.array([i for a in range(m.dim) for i in (m.pos_idx[a], m.vel_idx[a])])


@dataclass
class Sums:
    """Per-step sums over runs for one filter (host-side accumulator)."""

    data: dict[str, np.ndarray] = field(default_factory=dict)

    def add(self, chunk: dict[str, np.ndarray]):
        for k, v in chunk.items():
            v = np.asarray(v, dtype=np.float64)
            if k not in self.data:
                self.data[k] = v.copy()
            elif k.startswith("max_"):
                self.data[k] = np.fmax(self.data[k], v)
            else:
                self.data[k] = self.data[k] + v


@dataclass
class MonteCarloResult:
    runs: int
    steps: int
    dt: float
    dim: int
    sums: dict[str, dict[str, np.ndarray]]  # label -> name -> (T, ...)
    pcrlb: np.ndarray | None  # (T, 2·dim, 2·dim) bound on the CV-layout state, or None
    wall_s: float
    compile_s: float
    labels: list[str]
    kinds: dict[str, str]
    example: dict = field(default_factory=dict)  # run 0: truth, z, and each filter's estimates
    axes: tuple[str, ...] = ("x", "y", "z")  # names of the reporting frame's position axes
    units: tuple[str, str] = ("m", "m/s")  # of position and velocity
    windows: list[str] = field(default_factory=list)  # named windows of the prediction-error maxima


def _run_keys(key, idx):
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)
    split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
    return split[:, 0], split[:, 1], split[:, 2]


def _filter_chunk(spec: FilterSpec, params, truth, z, prior_cv, P0_cv, live, dt, pattern=None, detect_all=True,
                  windows=None):
    """Run one filter over a chunk; reduce to per-step sums over healthy runs.

    ``pattern`` (T, M) bool: which measurement components the sensors report at
    each step (before missed detections); None: every component at every step.
    ``detect_all``: no sensor misses a report, so which components are present is
    the same in every run. ``windows``: name -> (T,) bool mask of steps, for the
    per-run maxima of the one-step prediction error.

    When some of the filter's state depends on neither a run's prior mean nor its
    measurements (a linear KF's covariance and gain, the α-β filters' covariance,
    with the same report pattern in every run), the filter runs as ``vmap`` over
    runs of a ``lax.scan`` over steps: ``vmap`` batches only what depends on a
    run's own data, so that state is computed once per step for the whole chunk,
    not once per run. Otherwise it runs as a scan over steps of a vmap over runs.
    """
    flt = spec.filter
    T = z.shape[1]
    M = z.shape[2]
    if pattern is None:
        pattern = np.ones((T, M), bool)
    pattern = np.asarray(pattern, bool)
    if spec.view is not None:  # the view's report pattern: NaN where the sensors have nothing
        with jax.ensure_compile_time_eval():
            template = jnp.where(jnp.asarray(pattern), jnp.ones((), z.dtype), jnp.nan)
            pattern = np.isfinite(np.asarray(spec.view(template)))
        z = jax.vmap(spec.view)(z)
    pv = spec.pv_index
    present = jnp.asarray(pattern) if detect_all else None
    reports = pattern.any(axis=-1)  # steps where some component may be there
    coast = flt.coast if (flt.coast is not None and not reports.all()) else None
    t = dt * jnp.arange(1, T + 1, dtype=z.dtype)
    P0_cv = jnp.asarray(P0_cv, z.dtype)

    def init(prior_r):
        x0, P0 = spec.model.embed(prior_r, P0_cv, spec.prior_extra_var)
        return flt.init(params, Prior(x0, P0))

    def body(state, inp):  # one run, one step: filter, then that run's errors
        z_k, truth_k, t_k, present_k, reports_k = inp
        meas = Meas(z_k, t_k, jnp.asarray(True), present_k)
        if coast is None:
            state, out = flt.step(params, state, meas)
        else:  # no sensor reports at this step (between reports): predict only
            state, out = jax.lax.cond(reports_k, flt.step, coast, params, state, meas)
        e = out.x[pv] - truth_k  # (2d,) CV layout
        Pe = out.P[pv[:, None], pv[None, :]]
        nees = mahalanobis2(Pe, e)  # NaN when P is not positive definite
        nis, logdet_s = mahalanobis2_logdet(out.S, out.nu)
        nis = jnp.where(out.valid, nis, 0.0)
        logdet_s = jnp.where(out.valid, logdet_s, 0.0)
        e_pred = out.x_pred[pv[0::2]] - truth_k[0::2]  # one-step prediction error of the position
        bad = ~(jnp.isfinite(nees) & jnp.all(jnp.isfinite(out.x)))
        bad = bad | (out.valid & ~jnp.isfinite(nis))
        return state, (e, nees, nis, out.valid, out.dof, bad, logdet_s, e_pred)

    fixed = (t, present, jnp.asarray(reports))  # the same in every run
    if present is not None and _has_shared_state(init, body, prior_cv[0], z[0, 0], truth[0, 1], fixed):
        # vmap over runs of a scan over steps: the state the runs share stays unbatched
        def one_run(prior_r, z_r, truth_r):
            return jax.lax.scan(body, init(prior_r), (z_r, truth_r) + fixed)[1]

        outs = jax.vmap(one_run, out_axes=1)(prior_cv, z, truth[:, 1:])
    else:  # a scan over steps of a vmap over runs (time-major: each step's runs side by side)
        step = jax.vmap(body, in_axes=(0, (0, 0, None, None, None)))
        xs = (jnp.swapaxes(z, 0, 1), jnp.swapaxes(truth[:, 1:], 0, 1)) + fixed
        outs = jax.lax.scan(step, jax.vmap(init)(prior_cv), xs)[1]
    e, nees, nis, upd, dof, bad, logdet_s, e_pred = outs
    x_first = e[:, 0] + truth[0, 1:]  # the chunk's first run: estimates (T, 2d) in CV layout

    diverged = jnp.any(bad, axis=0)  # (B,)
    ok = live & ~diverged
    okf = ok.astype(z.dtype)
    e = jnp.where(ok[None, :, None], e, 0.0)
    ep, ev = e[..., 0::2], e[..., 1::2]  # positions, velocities (T, B, d)
    updf = (upd & ok[None, :]).astype(z.dtype)
    neg = -jnp.inf
    e_pred = jnp.where(ok[None, :, None], e_pred, 0.0)
    a_pred = jnp.concatenate([jnp.abs(e_pred), jnp.linalg.norm(e_pred, axis=-1, keepdims=True)], axis=-1)
    runmax = {  # per window: sum over runs of each run's largest |error| (per axis, then the norm)
        f"runmax_pred@{name}": jnp.sum(jnp.max(jnp.where(jnp.asarray(mask)[:, None, None], a_pred, 0.0), axis=0), axis=0)
        for name, mask in (windows or {}).items()
    }
    return runmax | {
        "count": jnp.broadcast_to(jnp.sum(okf), (T,)),
        "diverged": jnp.sum((live & diverged).astype(z.dtype)),
        "sum_pos": jnp.sum(ep, axis=1),
        "sum_vel": jnp.sum(ev, axis=1),
        "sumsq_pos": jnp.sum(ep**2, axis=1),
        "sumsq_vel": jnp.sum(ev**2, axis=1),
        "max_abs_pos": jnp.max(jnp.where(ok[None, :, None], jnp.abs(ep), neg), axis=1),
        "max_abs_vel": jnp.max(jnp.where(ok[None, :, None], jnp.abs(ev), neg), axis=1),
        "max_err_pos": jnp.max(jnp.where(ok[None, :], jnp.linalg.norm(ep, axis=-1), neg), axis=1),
        "max_err_vel": jnp.max(jnp.where(ok[None, :], jnp.linalg.norm(ev, axis=-1), neg), axis=1),
        "sum_nees": jnp.sum(jnp.where(ok[None, :], nees, 0.0), axis=1),
        "sum_nis": jnp.sum(jnp.where(ok[None, :], nis, 0.0) * updf, axis=1),
        "count_nis": jnp.sum(updf, axis=1),
        "dof_nis": jnp.sum(dof * updf, axis=1),
        "sum_logdet_s": jnp.sum(jnp.where(ok[None, :], logdet_s, 0.0) * updf, axis=1),
        "sum_pred": jnp.sum(e_pred, axis=1),  # one-step prediction error, per axis
        "sumsq_pred": jnp.sum(e_pred**2, axis=1),
        "example_x": x_first,  # the chunk's first run: estimates (T, 2d) in CV layout
    }


def simulate_runs(scenario, sensor, L0, key, idx):
    """Runs ``idx`` as the engine simulates them: (truth (B, T+1, 2d), z (B, T, M), prior (B, 2d)).

    Run i's truth, measurements and prior mean come from ``fold_in(key, i)``;
    ``L0`` is the Cholesky factor of the prior covariance (CV layout).
    """
    d = scenario.dim
    k_truth, k_meas, k_prior = _run_keys(key, idx)
    truth = jax.vmap(scenario.simulate)(k_truth)  # (B, T+1, 2d)
    z = jax.vmap(sensor.measure)(k_meas, truth[:, 1:, 0::2])  # (B, T, M)
    w = jax.vmap(lambda k: jax.random.normal(k, (2 * d,), truth.dtype))(k_prior)
    return truth, z, truth[:, 0] + w @ L0.T


def _tainted(fn, args, flags):
    """Which outputs of ``fn(*args)`` depend on the inputs flagged in ``flags`` (one per leaf).

    A conservative reading of the jaxpr: an equation with any dependent input makes
    all its outputs dependent (nested jaxprs included).
    """
    args = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)), args)
    closed = jax.make_jaxpr(fn)(*args)
    jaxpr = closed.jaxpr
    dep = {v for v, f in zip(jaxpr.invars, flags) if f}
    for eqn in jaxpr.eqns:
        if any(not isinstance(v, jax.extend.core.Literal) and v in dep for v in eqn.invars):
            dep.update(eqn.outvars)
    return [not isinstance(v, jax.extend.core.Literal) and v in dep for v in jaxpr.outvars]


def _has_shared_state(init, body, prior, z_k, truth_k, fixed):
    """Whether some of a filter's state depends neither on a run's prior mean nor on its
    measurements (a linear KF's covariance when the report pattern is the same in every run)."""
    fixed_k = jax.tree_util.tree_map(lambda a: a[0], fixed)
    n_fixed = len(jax.tree_util.tree_leaves(fixed_k))
    state_flags = _tainted(init, (prior,), [True] * len(jax.tree_util.tree_leaves(prior)))
    state = jax.eval_shape(init, prior)
    n_state = len(state_flags)

    def step(state, z_k, truth_k, fixed_k):
        return body(state, (z_k, truth_k) + tuple(fixed_k))[0]

    for _ in range(n_state + 1):  # to the fixed point: a dependent leaf stays dependent
        flags = state_flags + [True] * (len(jax.tree_util.tree_leaves(z_k)) + len(jax.tree_util.tree_leaves(truth_k)))
        flags += [False] * n_fixed
        new = _tainted(step, (state, z_k, truth_k, fixed_k), flags)
        new = [a or b for a, b in zip(new, state_flags)]
        if new == state_flags:
            break
        state_flags = new
    return not all(state_flags)


def make_chunk_fn(scenario, sensor, specs: Sequence[FilterSpec], P0_cv, dt, windows=None):
    """The jitted per-chunk computation: (params_list, key, idx, live) -> sums.

    ``windows``: name -> (steps,) bool mask, the report windows of the one-step
    prediction error's per-run maxima.
    """
    d = scenario.dim
    P0_cv = jnp.asarray(P0_cv)
    L0 = jnp.linalg.cholesky(P0_cv)
    if not isinstance(sensor, SensorSuite):
        sensor = SensorSuite((sensor,))
    pattern = np.concatenate([np.repeat(s.report_mask(scenario.steps)[:, None], s.m, axis=1) for s in sensor.sensors],
                             axis=1)  # (steps, M): which components each sensor reports at each step
    detect_all = all(s.p_detect >= 1.0 for s in sensor.sensors)
    with_bound = scenario.linear_gaussian() is not None  # no PCRLB, no information to gather

    def chunk(params_list, key, idx, live):
        truth, z, prior = simulate_runs(scenario, sensor, L0, key, idx)
        pos = truth[:, 1:, 0::2]
        if with_bound:  # expected measurement information at the true positions, for the PCRLB
            info = jnp.sum(jnp.where(live[:, None, None, None], jax.vmap(sensor.information)(pos), 0.0), axis=0)
        else:
            info = jnp.zeros((pos.shape[1], d, d), truth.dtype)
        out = {
            "_info": info,
            "_example": {"truth": truth[0], "z": z[0]},
        }
        for spec, params in zip(specs, params_list):
            out[spec.label] = _filter_chunk(spec, params, truth, z, prior, P0_cv, live, dt, pattern, detect_all,
                                            windows)
        return out

    return jax.jit(chunk)


def _run_sharding():
    devices = jax.devices()
    if len(devices) == 1:
        return None, 1
    mesh = jax.sharding.Mesh(np.array(devices), ("runs",))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("runs")), len(devices)


def monte_carlo(
    scenario,
    sensor,
    specs: Sequence[FilterSpec],
    runs: int,
    key,
    P0_cv,
    *,
    chunk: int | None = None,
    params: Sequence[Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    precision: str = "float64",
    windows: dict[str, np.ndarray] | None = None,
) -> MonteCarloResult:
    """Per-step error statistics of several filters over ``runs`` Monte-Carlo runs.

    ``P0_cv`` is the prior covariance in CV layout: run i's prior mean is the
    truth one period before the first measurement plus a N(0, P0) draw, shared
    by all filters in that run. ``precision = "float32"`` traces and runs the
    simulation and the filters in single precision (JAX's 64-bit mode off for
    them); sums are accumulated on the host in float64 either way, and the
    random draws differ from the float64 ones. ``windows`` (name -> (steps,)
    bool mask) are where each run's largest one-step prediction error is taken.
    """
    with jax.enable_x64(precision == "float64"):
        return _monte_carlo(scenario, sensor, specs, runs, key, P0_cv, chunk, params, progress, precision, windows)


def _monte_carlo(scenario, sensor, specs, runs, key, P0_cv, chunk, params, progress, precision, windows):
    dt = float(scenario.dt)
    sharding, n_dev = _run_sharding()
    chunk = int(min(chunk or 1000, runs))
    chunk = -(-chunk // n_dev) * n_dev  # a multiple of the device count
    fn = make_chunk_fn(scenario, sensor, specs, P0_cv, dt, windows)
    params_list = list(params) if params is not None else [s.filter.params for s in specs]
    if precision == "float32":
        params_list = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), params_list)
    if isinstance(key, int):
        key = jax.random.key(key)

    acc = {s.label: Sums() for s in specs}
    info = np.zeros((scenario.steps, scenario.dim, scenario.dim))
    example = {}
    t_start = time.perf_counter()
    compile_s = 0.0
    n_chunks = -(-runs // chunk)
    for c in range(n_chunks):
        idx = np.arange(c * chunk, (c + 1) * chunk, dtype=np.uint32)
        live = idx < runs
        idx_j, live_j = jnp.asarray(idx), jnp.asarray(live)
        if sharding is not None:
            idx_j, live_j = jax.device_put(idx_j, sharding), jax.device_put(live_j, sharding)
        t0 = time.perf_counter()
        out = jax.device_get(fn(params_list, key, idx_j, live_j))
        if c == 0:
            compile_s = time.perf_counter() - t0
        info += out.pop("_info")
        ex = out.pop("_example")
        if c == 0:  # run 0, for trajectory figures
            example = {"truth": np.asarray(ex["truth"]), "z": np.asarray(ex["z"])}
            example["x"] = {s.label: np.asarray(out[s.label]["example_x"]) for s in specs}
        for label, sums in out.items():
            sums.pop("example_x")
            acc[label].add(sums)
        if progress:
            progress(min((c + 1) * chunk, runs), runs)
    wall = time.perf_counter() - t_start

    return MonteCarloResult(
        runs=runs,
        steps=scenario.steps,
        dt=dt,
        dim=scenario.dim,
        sums={label: a.data for label, a in acc.items()},
        pcrlb=_pcrlb64(scenario, np.asarray(P0_cv, np.float64), info / runs),
        wall_s=wall,
        compile_s=compile_s,
        labels=[s.label for s in specs],
        kinds={s.label: s.kind for s in specs},
        example=example,
        axes=tuple(getattr(scenario, "axes", ("x", "y", "z")[: scenario.dim])),
        units=tuple(getattr(scenario, "units", ("m", "m/s"))),
        windows=list(windows or {}),
    )


def _pcrlb64(scenario, P0_cv, info_pos):
    with jax.enable_x64(True):
        return pcrlb(scenario, P0_cv, info_pos)


def pcrlb(scenario, P0_cv, info_pos):
    """Tichavský et al. recursion (REFERENCE_MATH §5) for linear-Gaussian dynamics.

    J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + E[H̃ᵀ R⁻¹ H̃], the expectation averaged over
    the simulated truths (``info_pos``, (T, dim, dim), position block); J_0 = P0⁻¹.
    Returns J⁻¹ per measurement step, or None when the truth has no Gaussian model.
    """
    lg = scenario.linear_gaussian()
    if lg is None:
        return None
    F, Q = (jnp.asarray(a) for a in lg)
    pos = np.arange(scenario.dim) * 2
    Jz = jnp.zeros((len(info_pos),) + P0_cv.shape).at[:, pos[:, None], pos[None, :]].set(jnp.asarray(info_pos))

    def step(Jinv, Jz_k):
        Jinv = jnp.linalg.inv(jnp.linalg.inv(Q + F @ Jinv @ F.T) + Jz_k)
        return Jinv, Jinv

    _, out = jax.lax.scan(step, jnp.asarray(P0_cv), Jz)
    return np.asarray(out)


# ------------------------------------------------------------------ user measurements


@dataclass(frozen=True)
class FilterResult:
    x: jax.Array  # (..., T, n) filtered means
    P: jax.Array  # (..., T, n, n) filtered covariances
    x_pred: jax.Array  # (..., T, n) one-step predictions
    nu: jax.Array  # (..., T, m) innovations (0 where not used)
    S: jax.Array  # (..., T, m, m) innovation covariances
    valid: jax.Array  # (..., T) update happened
    dof: jax.Array  # (..., T) innovation components used
    aux: Any = None  # what the filter family adds (e.g. the STF's fading factor), per step


def run_filter(flt: Filter, z, *, x0, P0, params=None, dt: float = 1.0) -> FilterResult:
    """Run a filter over a user's measurements.

    ``z`` is (T, m) or (N, T, m); a row of NaN is a missed detection
    (predict-only). ``x0, P0`` is the prior one sample period before ``z[0]``;
    each step predicts, then updates with ``z[k]``. For single precision, build
    the filter and call this inside ``with jax.enable_x64(False):`` with float32 inputs.
    """
    params = flt.params if params is None else params
    z = jnp.asarray(z)
    batched = z.ndim == 3
    zb = z if batched else z[None]
    N, T = zb.shape[0], zb.shape[1]
    x0 = jnp.broadcast_to(jnp.asarray(x0, zb.dtype), (N,) + np.shape(x0)[-1:])
    P0 = jnp.broadcast_to(jnp.asarray(P0, zb.dtype), (N,) + np.shape(P0)[-2:])
    out = _run_filter_jit(flt.init, flt.step, params, zb, x0, P0, float(dt))
    if not batched:
        out = jax.tree_util.tree_map(lambda a: a[0], out)
    return FilterResult(*out)


def _run_filter_impl(init, step, params, z, x0, P0, dt):
    N, T = z.shape[0], z.shape[1]
    state = jax.vmap(init, in_axes=(None, 0))(params, Prior(x0, P0))
    step = jax.vmap(step, in_axes=(None, 0, 0))
    t = dt * jnp.arange(1, T + 1, dtype=z.dtype)

    def body(s, inp):
        z_k, t_k = inp
        s, out = step(params, s, Meas(z_k, jnp.full((N,), t_k), jnp.ones((N,), bool)))
        return s, out

    _, out = jax.lax.scan(body, state, (jnp.swapaxes(z, 0, 1), t))
    return tuple(jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), out))


_run_filter_jit = jax.jit(_run_filter_impl, static_argnums=(0, 1, 6))
