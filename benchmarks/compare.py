"""tracklab against dynamax, FilterPy and NumPy on the same simulated data.

    pip install -e ".[bench]"                  # dynamax, filterpy: benchmark-only extras
    python benchmarks/compare.py               # full comparison, writes benchmarks/results.md
    python benchmarks/compare.py --quick       # smoke version (fewer runs), prints only

Three cases: the lidar crossing (paper 000) with a Cartesian position sensor and a
linear KF; the lidar crossing with its polar sensor and an EKF; the α-β experiment
(laser_ir_alpha_beta, Kalata gains). tracklab is timed end to end (simulate +
filter + statistics, what ``tracklab run`` does per chunk); every other
implementation is timed on the measurements tracklab simulated, filtering only (no
simulation, no statistics charged to it). Every implementation's estimates are
checked against tracklab's on the same measurements before anything is timed, and
tracklab's per-step error sums against the ones computed from NumPy's and dynamax's estimates.
See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from written import write_run

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

KF_TOML = """
[experiment]
name = "compare_kf"
runs = 10000
dt = 0.5
steps = 200

[scenario]
kind = "crossing"            # the lidar experiment's truth
speed = 400.0
offset = 20000.0
start_x = -20000.0
accel_sigma = 1.0

[sensor]
kind = "cartesian"           # position measurements: a linear-Gaussian model
sigma = 100.0

[prior]
pos_sigma = 100.0
vel_sigma = 50.0

[[filter]]
kind = "kf"
label = "KF"

[report]
window = [20, 200]
"""

CASES = {
    # name -> (experiment file or TOML text, filter label kept)
    "lidar KF": (KF_TOML, "KF"),
    "lidar EKF": (ROOT / "experiments" / "lidar_crossing.toml", "EKF"),
    "alpha-beta": (ROOT / "experiments" / "laser_ir_alpha_beta.toml", "alpha-beta, known lambda"),
}
# batch sizes tried for every vectorised implementation, the best kept: 2 000 is what ``tracklab run``
# itself picks on two cores (1 000 runs per device, ``scan.default_chunk``)
CHUNKS = (1000, 2000, 10000)


# ----------------------------------------------------------------------------- setup


def load_case(name):
    from tracklab.config import load_experiment

    src, label = CASES[name]
    if isinstance(src, str):
        tmp = Path(tempfile.mkdtemp()) / "compare.toml"
        tmp.write_text(src)
        src = tmp
    exp = load_experiment(src)
    exp.filters = [f for f in exp.filters if f.label == label]
    assert len(exp.filters) == 1, (name, label)
    return exp


class Data:
    """The runs tracklab simulates (fold_in(key, i) for run i), on the host."""

    def __init__(self, exp, runs, seed=0):
        import jax
        import jax.numpy as jnp
        import numpy as np

        from tracklab.worlds.tracking.scan import simulate_runs

        P0 = np.asarray(exp.prior_covariance())
        sim = jax.jit(lambda key, idx: simulate_runs(exp.scenario, exp.sensor, jnp.asarray(P0), key, idx))
        parts = [sim(jax.random.key(seed), jnp.arange(a, min(a + 10000, runs), dtype=jnp.uint32))
                 for a in range(0, runs, 10000)]
        self.truth, self.z, self.prior = (np.concatenate([np.asarray(p[i]) for p in parts]) for i in range(3))
        self.P0 = P0
        self.dt = float(exp.dt)
        self.runs, self.steps = runs, exp.steps


def model_matrices(exp):
    import numpy as np

    spec = exp.filter_specs()[0]
    fc = exp.filters[0]
    m = spec.layout
    q = float(np.asarray(fc.params["q"]))
    r = np.broadcast_to(np.asarray(fc.params["r"], float), (exp.sensor.m,))
    return spec, np.asarray(m.F), np.asarray(m.Q(q)), np.diag(r)


# ----------------------------------------------------------------------------- tracklab


def _time_tracklab(exp, runs, chunk, repeat):
    """``bench_lidar.time_program`` on the tracking world of the experiment's structure at ``chunk``."""
    from bench_lidar import time_program
    from tracklab.worlds.tracking import scan

    structure = exp.structure(chunk=chunk)
    return structure, time_program(scan.world(structure), exp.params(), runs, seed=0, repeat=repeat)


def tracklab_e2e(exp, runs, chunk, repeat):
    """Simulate + filter + statistics, chunk by chunk, as ``runner.run`` does it, with the program
    ``runner.program`` compiled for the experiment's structure at this chunk size."""
    from tracklab.montecarlo import runner
    from tracklab.worlds.tracking import errors

    structure, t = _time_tracklab(exp, runs, chunk, repeat)
    assert not t["held"], "the program was already compiled in this process: its compile time would read 0"
    return {"wall_s": t["wall_s"], "compile_s": t["compile_s"], "chunk": chunk,
            "sums": errors.unpack(t["sums"], exp.dim)[runner.lane_key(0)]}


def tracklab_pass(exp, runs, chunk):
    """One timed pass over ``runs`` runs with the program ``tracklab_e2e`` compiled at ``chunk``: wall s."""
    return _time_tracklab(exp, runs, chunk, 1)[1]["wall_s"]


def tracklab_reference(exp, data, n):
    """tracklab's estimates (CV layout) of the first n runs, through run_filter."""
    import numpy as np

    import tracklab
    from tracklab.models import cv_index

    spec = exp.filter_specs()[0]
    x0, P0 = spec.layout.embed(data.prior[:n], data.P0, spec.prior_extra_var)
    res = tracklab.run_filter(spec.filter, data.z[:n], x0=np.asarray(x0), P0=np.asarray(P0[0] if P0.ndim == 3 else P0),
                              dt=data.dt)
    return np.asarray(res.x)[..., cv_index(spec.layout)]


# ----------------------------------------------------------------------------- dynamax


def _dynamax_one(case, exp):
    """dynamax's filter of one run: (prior mean (n,) one period before z[0], z (T, m)) -> filtered
    means (T, n) and covariances (T, n, n); None for a case dynamax has no filter for."""
    import jax.numpy as jnp
    import numpy as np

    spec, F, Q, R = model_matrices(exp)
    P0 = np.asarray(exp.prior_covariance())
    # tracklab's prior is one period before z[0]; dynamax's initial state is z[0]'s prior
    P1 = jnp.asarray(F @ P0 @ F.T + Q)
    F, Q, R = (jnp.asarray(a) for a in (F, Q, R))
    if case == "lidar KF":
        from dynamax.linear_gaussian_ssm import ParamsLGSSM, lgssm_filter
        from dynamax.linear_gaussian_ssm.inference import (
            ParamsLGSSMDynamics, ParamsLGSSMEmissions, ParamsLGSSMInitial)

        H = jnp.asarray(np.kron(np.eye(2), [[1.0, 0.0]]))

        def one(x0, z):
            p = ParamsLGSSM(
                initial=ParamsLGSSMInitial(mean=F @ x0, cov=P1),
                dynamics=ParamsLGSSMDynamics(weights=F, bias=jnp.zeros(4), input_weights=jnp.zeros((4, 0)), cov=Q),
                emissions=ParamsLGSSMEmissions(weights=H, bias=jnp.zeros(2), input_weights=jnp.zeros((2, 0)), cov=R))
            post = lgssm_filter(p, z)
            return post.filtered_means, post.filtered_covariances
    elif case == "lidar EKF":
        from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, extended_kalman_filter

        def one(x0, z):  # the pass stays within (-π, π): no innovation wrapping needed
            p = ParamsNLGSSM(initial_mean=F @ x0, initial_covariance=P1, dynamics_function=lambda x: F @ x,
                             dynamics_covariance=Q, emission_function=_polar_h, emission_covariance=R)
            post = extended_kalman_filter(p, z, output_fields=["filtered_means", "filtered_covariances"])
            return post.filtered_means, post.filtered_covariances
    else:
        return None
    return one


def _polar_h(x):
    import jax.numpy as jnp

    return jnp.stack([jnp.hypot(x[0], x[2]), jnp.arctan2(x[2], x[0])])


def with_jax_defaults(jitted):
    """``jitted``, compiled (once per argument shapes) with XLA's CPU fusion emitters on, as a
    dynamax user gets it: ``tracklab.configure()`` turns them off for the whole process, which
    compiles tracklab's programs faster and runs them as fast or faster, but runs dynamax's KF
    slower (one process, a chunk of 1 000 runs timed five times: 32.9 M against 38.3 M
    runs·steps/s, 2026-12-03)."""
    import jax

    compiled = {}

    def call(*args):
        shapes = tuple((a.shape, a.dtype) for a in jax.tree_util.tree_leaves(args))
        if shapes not in compiled:
            compiled[shapes] = jitted.lower(*args).compile(compiler_options={"xla_cpu_use_fusion_emitters": True})
        return compiled[shapes](*args)

    return call


def dynamax_fn(case, exp):
    """jit(vmap(filter)) over runs: (prior (B, n), z (B, T, m)) -> filtered means (B, T, n)."""
    import jax

    one = _dynamax_one(case, exp)
    return None if one is None else with_jax_defaults(jax.jit(jax.vmap(one)))


def dynamax_pipeline(case, exp):
    """The whole job as a dynamax user would write it: ``jit((key, idx) -> per-step sums)``.

    Run i draws from ``fold_in(key, i)`` with ``jax.random`` (float64): the truth's white
    accelerations (x_{k+1} = F x_k + G w_k, paper 000 eqs. 1-4), the measurement noise and the
    prior mean; dynamax's filter runs under ``vmap`` over the runs; the errors are reduced over
    the runs with ``jnp``: per step, the sums of the position and velocity errors and of their
    squares (bias and RMSE), of the NEES, and the largest position error. tracklab's chunk
    computes these and more (NIS, prediction errors, per-run samples, the PCRLB's information)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    one_filter = _dynamax_one(case, exp)
    if one_filter is None:
        return None
    scenario = exp.scenario
    model = scenario.model
    F, G = jnp.asarray(model.F), jnp.asarray(model.G)
    x_init = jnp.asarray(np.asarray(scenario.initial_state(), float))
    L0 = jnp.asarray(np.linalg.cholesky(np.asarray(exp.prior_covariance())))
    _, _, _, R = model_matrices(exp)
    sigma = jnp.asarray(np.sqrt(np.diag(R)))
    h = (lambda x: x[jnp.array([0, 2])]) if case == "lidar KF" else _polar_h
    T, d = exp.steps, scenario.dim

    def one(key):
        k_truth, k_meas, k_prior = jax.random.split(key, 3)
        w = scenario.accel_sigma * jax.random.normal(k_truth, (T, d))

        def advance(x, w_k):
            x = F @ x + G @ w_k
            return x, x

        _, truth = jax.lax.scan(advance, x_init, w)
        z = jax.vmap(h)(truth) + sigma * jax.random.normal(k_meas, (T, sigma.shape[0]))
        prior = x_init + L0 @ jax.random.normal(k_prior, (2 * d,))
        means, covs = one_filter(prior, z)
        e = means - truth
        nees = jax.vmap(lambda e_k, P_k: e_k @ jnp.linalg.solve(P_k, e_k))(e, covs)
        return e, nees

    def pipeline(key, idx):
        keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)
        e, nees = jax.vmap(one)(keys)  # (B, T, 2d), (B, T)
        ep, ev = e[..., 0::2], e[..., 1::2]
        return {"sum_pos": ep.sum(0), "sum_vel": ev.sum(0), "sumsq_pos": (ep**2).sum(0), "sumsq_vel": (ev**2).sum(0),
                "sum_nees": nees.sum(0), "max_err_pos": jnp.linalg.norm(ep, axis=-1).max(0)}

    return with_jax_defaults(jax.jit(pipeline))


def draws_alone(exp):
    """The ceiling of a case whose filter costs next to nothing: ``jit((key, idx) -> sums)`` making
    exactly the random draws tracklab's chunk makes for the runs ``idx`` (each run's key split as
    the tracking world splits it; the truth's accelerations and every sensor's noise, float32,
    ``tracklab.random``), summed over the runs so that none is left out."""
    import jax
    import jax.numpy as jnp

    from tracklab.montecarlo import runner
    from tracklab.worlds.tracking.scan import split_keys

    scenario, sensor, T = exp.scenario, exp.sensor, exp.steps

    def fn(key, idx):
        k_truth, k_meas, _ = split_keys(runner.run_keys(key, idx))
        meas = jax.vmap(lambda k: sensor.draws(k, T))(k_meas)
        total = sum(jnp.sum(a.astype(jnp.float32), axis=0) for a in jax.tree_util.tree_leaves(meas))
        if scenario.per_run:
            total = total + jnp.sum(jax.vmap(scenario.draws)(k_truth).astype(jnp.float32))
        return total

    return jax.jit(fn)


def _best_pass(call, parts, repeat):
    """``call(part)`` over every part, ``repeat`` timed passes after a first call: (fastest pass s,
    compile s = first call minus a steady one, outputs of the fastest pass)."""
    import jax

    t0 = time.perf_counter()
    first_out = jax.block_until_ready(call(parts[0]))
    first = time.perf_counter() - t0
    best, outs = float("inf"), [first_out]
    for _ in range(repeat):
        t0 = time.perf_counter()
        outs_i = jax.block_until_ready([call(p) for p in parts])
        wall = time.perf_counter() - t0
        if wall < best:
            best, outs = wall, outs_i
    return best, max(first - best / len(parts), 0.0), outs


def time_jax(fn, prior, z, chunk, repeat):
    """(best wall over all runs in chunks, compile s, outputs of the first chunk)."""
    import jax.numpy as jnp

    parts = [(jnp.asarray(prior[a:a + chunk]), jnp.asarray(z[a:a + chunk])) for a in range(0, len(z), chunk)]
    best, compile_s, outs = _best_pass(lambda p: fn(*p), parts, repeat)
    return best, compile_s, outs[0]


def time_keyed(fn, runs, chunk, repeat):
    """A ``(key, idx) -> sums`` function over ``runs`` runs in chunks: (best wall, compile s, sums of all runs)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    key = jax.random.key(0)
    parts = [jnp.arange(a, a + chunk, dtype=jnp.uint32) for a in range(0, runs, chunk)]
    best, compile_s, outs = _best_pass(lambda idx: fn(key, idx), parts, repeat)
    return best, compile_s, jax.tree_util.tree_map(lambda *a: np.sum([np.asarray(x) for x in a], axis=0), *outs)


# ----------------------------------------------------------------------------- NumPy, vectorised over runs


def numpy_filter(case, exp, prior, z):
    """The filter in NumPy, every step one batched operation over the runs: means (B, T, n)."""
    import numpy as np

    spec, F, Q, R = model_matrices(exp)
    B, T, m = z.shape
    if case == "alpha-beta":
        from tracklab.filters import kalata_alpha_beta

        lam = float(np.asarray(exp.filters[0].params["lam"]).ravel()[0])
        a, b = (float(v) for v in kalata_alpha_beta(lam))
        dt = float(exp.dt)
        x, v = prior[:, 0].copy(), prior[:, 1].copy()
        out = np.empty((B, T, 2))
        for k in range(T):
            xp = x + dt * v
            nu = z[:, k, 0] - xp
            x = xp + a * nu
            v = v + (b / dt) * nu
            out[:, k, 0], out[:, k, 1] = x, v
        return out
    x = prior.copy()
    P = np.broadcast_to(np.asarray(exp.prior_covariance()), (B, 4, 4)).copy()
    out = np.empty((B, T, 4))
    eye = np.eye(4)
    for k in range(T):
        x = x @ F.T
        P = F @ P @ F.T + Q
        if case == "lidar KF":
            H = np.broadcast_to(np.kron(np.eye(2), [[1.0, 0.0]]), (B, 2, 4))
            nu = z[:, k] - x[:, [0, 2]]
        else:
            px, py = x[:, 0], x[:, 2]
            r2 = px**2 + py**2
            r = np.sqrt(r2)
            H = np.zeros((B, 2, 4))
            H[:, 0, 0], H[:, 0, 2] = px / r, py / r
            H[:, 1, 0], H[:, 1, 2] = -py / r2, px / r2
            nu = z[:, k] - np.stack([r, np.arctan2(py, px)], axis=-1)
            nu[:, 1] = np.pi - np.mod(np.pi - nu[:, 1], 2 * np.pi)
        PHt = P @ np.swapaxes(H, 1, 2)
        S = H @ PHt + R
        K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, 1, 2)), 1, 2)
        x = x + np.einsum("bij,bj->bi", K, nu)
        IKH = eye - K @ H
        P = IKH @ P @ np.swapaxes(IKH, 1, 2) + K @ R @ np.swapaxes(K, 1, 2)
        out[:, k] = x
    return out


def time_numpy(case, exp, prior, z, chunk, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for a in range(0, len(z), chunk):
            numpy_filter(case, exp, prior[a:a + chunk], z[a:a + chunk])
        best = min(best, time.perf_counter() - t0)
    return best


# ----------------------------------------------------------------------------- FilterPy, one run at a time


def filterpy_runs(case, exp, prior, z):
    """FilterPy's filters in a Python loop over runs and steps: means (n_runs, T, n)."""
    import numpy as np

    spec, F, Q, R = model_matrices(exp)
    n, T, m = z.shape
    out = np.empty((n, T, 2 if case == "alpha-beta" else 4))
    if case == "alpha-beta":
        from filterpy.gh import GHFilter

        from tracklab.filters import kalata_alpha_beta

        lam = float(np.asarray(exp.filters[0].params["lam"]).ravel()[0])
        a, b = (float(v) for v in kalata_alpha_beta(lam))
        for i in range(n):
            f = GHFilter(x=float(prior[i, 0]), dx=float(prior[i, 1]), dt=float(exp.dt), g=a, h=b)
            for k in range(T):
                out[i, k] = f.update(float(z[i, k, 0]))
        return out
    from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

    P0 = np.asarray(exp.prior_covariance())
    for i in range(n):
        if case == "lidar KF":
            f = KalmanFilter(dim_x=4, dim_z=2)
            f.H = np.kron(np.eye(2), [[1.0, 0.0]])
        else:
            f = ExtendedKalmanFilter(dim_x=4, dim_z=2)
        f.x, f.P, f.F, f.Q, f.R = prior[i].reshape(4, 1).copy(), P0.copy(), F, Q, R
        for k in range(T):
            f.predict()
            if case == "lidar KF":
                f.update(z[i, k].reshape(2, 1))
            else:
                f.update(z[i, k].reshape(2, 1), _ekf_H, _ekf_h, residual=_angle_residual)
            out[i, k] = f.x[:, 0]
    return out


def _ekf_h(x):
    import numpy as np

    px, py = x[0, 0], x[2, 0]
    return np.array([[np.hypot(px, py)], [np.arctan2(py, px)]])


def _ekf_H(x):
    import numpy as np

    px, py = x[0, 0], x[2, 0]
    r2 = px * px + py * py
    r = np.sqrt(r2)
    return np.array([[px / r, 0.0, py / r, 0.0], [-py / r2, 0.0, px / r2, 0.0]])


def _angle_residual(a, b):
    import numpy as np

    d = a - b
    d[1] = np.pi - np.mod(np.pi - d[1], 2 * np.pi)
    return d


# ----------------------------------------------------------------------------- memory (fresh processes)


def _maxrss_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child_memory(case, impl, runs):
    """In a fresh process: peak RSS of one implementation over ``runs`` runs."""
    import jax

    import tracklab

    tracklab.configure()  # one CPU device per core, Eigen single-threaded, 64-bit mode

    exp = load_case(case)
    if impl == "tracklab":
        jax.block_until_ready(jax.numpy.zeros(1))
        base = _maxrss_mib()
        exp.monte_carlo(runs=runs, chunk=min(runs, 1000))
    else:
        data = Data(exp, runs)  # the measurements are held in memory; the baseline includes them
        base = _maxrss_mib()
        if impl == "dynamax":
            fn = dynamax_fn(case, exp)
            for a in range(0, runs, 1000):
                jax.block_until_ready(fn(jax.numpy.asarray(data.prior[a:a + 1000]), jax.numpy.asarray(data.z[a:a + 1000])))
        elif impl == "numpy":
            for a in range(0, runs, 1000):
                numpy_filter(case, exp, data.prior[a:a + 1000], data.z[a:a + 1000])
        else:
            filterpy_runs(case, exp, data.prior[:runs], data.z[:runs])
    print(json.dumps({"baseline_mib": base, "peak_mib": _maxrss_mib()}))


def bench_memory(case, impl, runs):
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child-memory", case, impl, str(runs)]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"memory child {case}/{impl} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- one case


def fastest(label, runs, time_one, log, rate):
    """``time_one(chunk)`` -> (wall s, compile s or None, payload) for each batch size in CHUNKS up to ``runs``;
    the fastest as {wall, compile_s, chunk, payload}. ``rate(runs, wall)``: runs·steps per second."""
    best = None
    for chunk in CHUNKS:
        if chunk > runs:
            continue
        wall, compile_s, payload = time_one(chunk)
        note = "" if compile_s is None else f", compile {compile_s:.2f} s"
        log(f"  {label} chunk {chunk}: {rate(runs, wall) / 1e6:.2f} M runs*steps/s{note}")
        if best is None or wall < best["wall"]:
            best = {"wall": wall, "compile_s": compile_s or 0.0, "chunk": chunk, "payload": payload}
    return best


def interleaved(turns, rounds, rows, rate, runs, log):
    """``rounds`` rounds in which each implementation (name -> one timed pass at its best batch
    size, wall s) runs once in turn: a slower spell of the machine falls on all of them alike.
    Each row keeps the fastest of its passes, the batch-size scan's and these."""
    for _ in range(rounds):
        for name, one in turns.items():
            rows[name]["rate"] = max(rows[name]["rate"], rate(runs, one()))
    log("  interleaved (" + f"{rounds} rounds): " + ", ".join(f"{NAMES[n]} {rows[n]['rate'] / 1e6:.2f} M" for n in turns))


def run_case(case, runs, fp_runs, repeat, log, rounds=5):
    import numpy as np

    exp = load_case(case)
    T = exp.steps
    data = Data(exp, runs)
    rate = lambda n, s: n * T / s  # noqa: E731
    rows = {}

    # correctness first: every implementation on the same measurements as tracklab
    n_check = min(fp_runs, 20)
    ref = tracklab_reference(exp, data, n_check)
    tol = dict(rtol=1e-7, atol=1e-6)  # m and m/s at 20 km: float rounding, different summation order
    np.testing.assert_allclose(numpy_filter(case, exp, data.prior[:n_check], data.z[:n_check]), ref, **tol,
                               err_msg=f"{case}: NumPy")
    np.testing.assert_allclose(filterpy_runs(case, exp, data.prior[:n_check], data.z[:n_check]), ref, **tol,
                               err_msg=f"{case}: FilterPy")
    dyn = dynamax_fn(case, exp)
    # dynamax adds 1e-9 to the diagonal of S before it solves (psd_solve's diagonal_boost); on the bearing
    # (σ² = 9e-6 rad²) that moves the EKF's estimates by millimetres, millimetres per second
    dyn_tol = dict(rtol=1e-7, atol=5e-2) if case == "lidar EKF" else tol
    if dyn is not None:
        np.testing.assert_allclose(np.asarray(dyn(data.prior[:n_check], data.z[:n_check])[0]), ref, **dyn_tol,
                                   err_msg=f"{case}: dynamax")
    log(f"{case}: estimates agree on {n_check} runs (NumPy, FilterPy{', dynamax' if dyn else ''} vs tracklab)")

    # tracklab, end to end
    def e2e(chunk):
        r = tracklab_e2e(exp, runs, chunk, repeat)
        return r["wall_s"], r["compile_s"], r

    best = fastest("tracklab e2e", runs, e2e, log, rate)
    rows["tracklab"] = {"rate": rate(runs, best["wall"]), "compile_s": best["compile_s"], "chunk": best["chunk"],
                        "what": "simulate + filter + statistics"}

    # tracklab's per-step sums of squared position error against the same sums from NumPy's estimates
    # (checked against run_filter above) over all runs: the world's in-scan simulation is the one compared
    means_n = np.concatenate([numpy_filter(case, exp, data.prior[a:a + 1000], data.z[a:a + 1000])
                              for a in range(0, runs, 1000)])
    e_n = means_n[..., 0::2] - data.truth[:, 1:, 0::2]
    np.testing.assert_allclose(best["payload"]["sums"]["sumsq_pos"], np.sum(e_n**2, axis=0), rtol=1e-7 * 1e3,
                               err_msg=f"{case}: tracklab's error sums vs NumPy's estimates")
    log(f"  {case}: tracklab's per-step sums of squared position error = those of NumPy's estimates")

    if dyn is not None:
        best_d = fastest("dynamax", runs, lambda chunk: time_jax(dyn, data.prior, data.z, chunk, repeat), log, rate)
        rows["dynamax"] = {"rate": rate(runs, best_d["wall"]), "compile_s": best_d["compile_s"], "chunk": best_d["chunk"],
                           "what": "filter only (jit + vmap)"}
        # tracklab's per-step sums against the same sums from dynamax's estimates
        means = np.concatenate([np.asarray(dyn(data.prior[a:a + 1000], data.z[a:a + 1000])[0])
                                for a in range(0, runs, 1000)])
        e = means[..., 0::2] - data.truth[:, 1:, 0::2]
        np.testing.assert_allclose(best["payload"]["sums"]["sumsq_pos"], np.sum(e**2, axis=0), rtol=dyn_tol["rtol"] * 1e3,
                                   err_msg=f"{case}: tracklab's error sums vs dynamax's estimates")
        log(f"  {case}: tracklab's per-step sums of squared position error = those of dynamax's estimates")

    pipe = dynamax_pipeline(case, exp)
    if pipe is not None:
        best_p = fastest("dynamax pipeline", runs, lambda chunk: time_keyed(pipe, runs, chunk, repeat), log, rate)
        rows["dynamax_pipeline"] = {"rate": rate(runs, best_p["wall"]), "compile_s": best_p["compile_s"],
                                    "chunk": best_p["chunk"],
                                    "what": "jax.random draws + filter (vmap) + jnp statistics, one jit"}
        # the same job: its RMS position error over all runs and steps is tracklab's, within Monte-Carlo noise
        sq_t = float(np.sum(best["payload"]["sums"]["sumsq_pos"]))
        sq_p = float(np.sum(best_p["payload"]["sumsq_pos"]))
        assert abs(np.sqrt(sq_p / sq_t) - 1) < 0.03, (case, sq_p, sq_t)
        log(f"  {case}: the pipeline's RMS position error is tracklab's within 3 % "
            f"({np.sqrt(sq_p / (runs * T * exp.dim)):.2f} m against {np.sqrt(sq_t / (runs * T * exp.dim)):.2f} m)")

    draws = draws_alone(exp)
    best_r = fastest("draws alone", runs, lambda chunk: time_keyed(draws, runs, chunk, repeat), log, rate)
    rows["draws"] = {"rate": rate(runs, best_r["wall"]), "compile_s": best_r["compile_s"], "chunk": best_r["chunk"],
                     "what": "tracklab's random draws alone (the ceiling)"}

    turns = {"tracklab": lambda: tracklab_pass(exp, runs, best["chunk"])}
    if dyn is not None:
        turns["dynamax"] = lambda: time_jax(dyn, data.prior, data.z, best_d["chunk"], 1)[0]
    if pipe is not None:
        turns["dynamax_pipeline"] = lambda: time_keyed(pipe, runs, best_p["chunk"], 1)[0]
    turns["draws"] = lambda: time_keyed(draws, runs, best_r["chunk"], 1)[0]
    interleaved(turns, rounds, rows, rate, runs, log)

    best_n = fastest("NumPy", runs, lambda chunk: (time_numpy(case, exp, data.prior, data.z, chunk, repeat), None, None),
                     log, rate)
    rows["numpy"] = {"rate": rate(runs, best_n["wall"]), "compile_s": 0.0, "chunk": best_n["chunk"],
                     "what": "filter only, vectorised over runs"}

    t0 = time.perf_counter()
    filterpy_runs(case, exp, data.prior[:fp_runs], data.z[:fp_runs])
    wall = time.perf_counter() - t0
    rows["filterpy"] = {"rate": rate(fp_runs, wall), "compile_s": 0.0, "chunk": fp_runs,
                        "what": f"filter only, Python loop; {fp_runs} runs timed, scaled"}
    log(f"  FilterPy ({fp_runs} runs): {rows['filterpy']['rate'] / 1e6:.3f} M runs*steps/s")
    return rows


# ----------------------------------------------------------------------------- report


NAMES = {"tracklab": "tracklab", "dynamax": "dynamax", "dynamax_pipeline": "dynamax, whole job", "draws": "draws alone",
         "numpy": "NumPy", "filterpy": "FilterPy"}


def render(info, cmd, cfg, results, mems, total_s, load_end):
    from bench_lidar import fmt_rate

    L = ["# tracklab against dynamax, FilterPy and NumPy", ""]
    L.append(f"- Date: {info['date']}")
    L.append(f"- Machine: nproc = {info['nproc']}, CPU = {info['cpu']}")
    L.append(f"- Load average (1/5/15 min) at start: {info['loadavg']}; at end: {load_end}")
    L.append(f"- Python {info['python']}, jax {info['jax']}, jaxlib {info['jaxlib']}, backend {info['backend']}, "
             f"float64; {info['versions']}")
    L.append(f"- Command: `{cmd}`")
    L.append(f"- Runs: {cfg['runs']} per case (FilterPy: {cfg['fp_runs']} runs timed and scaled); "
             f"best of {cfg['repeat']} timed passes; batch sizes tried {', '.join(map(str, CHUNKS))} (best kept); "
             f"then {cfg['rounds']} rounds in which tracklab, dynamax, the dynamax pipeline and the draws each run "
             "one pass in turn at their best batch size, so that a slower spell of the machine falls on all alike "
             "(each keeps its fastest pass)")
    L.append(f"- Total benchmark time: {total_s:.0f} s")
    L.append("")
    L.append("tracklab is timed end to end: simulation of truth, measurements and priors, the filter, and "
             "the per-step statistics (RMSE, bias, maxima, NEES, NIS, prediction errors), as `tracklab run` does "
             "per chunk. The others are timed on the measurements tracklab simulated, filtering only. Before "
             "timing, each one's estimates are checked against tracklab's on the same runs (`assert_allclose`, "
             "rtol 1e-7, atol 1e-6 m or m/s; dynamax's EKF within 5 cm: it adds 1e-9 to the diagonal of the "
             "innovation covariance before solving, which on the bearing (σ² = 9e-6 rad²) moves its estimates "
             "by millimetres), and tracklab's per-step sums of squared position error against those computed "
             "from NumPy's and dynamax's estimates over all runs (rtol 1e-4). tracklab's compile time is "
             "`runner.program`'s (tracing, lowering, XLA compilation); dynamax's is its first call minus a "
             "steady one. tracklab's programs compile with XLA's CPU fusion emitters off (`tracklab.configure()`), "
             "dynamax's with them on, as JAX has them (`with_jax_defaults`): off, dynamax's KF runs slower.")
    L.append("")
    L.append("| Case | Implementation | What is timed | Batch | Throughput (runs·steps/s) | tracklab ÷ this | Compile (s) | Peak RSS (MiB) |")
    L.append("|---|---|---|---:|---:|---:|---:|---:|")
    for case, rows in results.items():
        t = rows["tracklab"]["rate"]
        for impl, r in rows.items():
            m = mems.get((case, impl))
            mem = f"{m['peak_mib']:.0f}" if m else "–"
            ratio = "1" if impl == "tracklab" else f"{t / r['rate']:.2f}×"
            comp = f"{r['compile_s']:.2f}" if impl in ("tracklab", "dynamax", "dynamax_pipeline", "draws") else "–"
            L.append(f"| {case} | {NAMES[impl]} | {r['what']} | {r['chunk']} | {fmt_rate(r['rate'])} | {ratio} | "
                     f"{comp} | {mem} |")
    L.append("")
    L.append("`dynamax, whole job` is what a dynamax user writes for tracklab's job (`dynamax_pipeline`): "
             "`jax.random` draws (float64) for the truth, the measurements and the prior, dynamax's filter "
             "under `vmap`, and per-step sums of the errors, their squares and the NEES and the largest "
             "position error reduced with `jnp`, all in one `jit`; its RMS position error over all runs is "
             "checked to be tracklab's within 3 %. `draws alone` makes exactly the random draws tracklab's "
             "chunk makes for the same runs and steps (`draws_alone`): no filter can run faster than them.")
    L.append("")
    L.append("| Case | tracklab (runs·steps/s) | ÷ dynamax filter alone | ÷ dynamax whole job | draws alone (runs·steps/s) | tracklab ÷ draws alone |")
    L.append("|---|---:|---:|---:|---:|---:|")
    for case, rows in results.items():
        t = rows["tracklab"]["rate"]
        ratio = lambda k: f"{t / rows[k]['rate']:.2f}×" if k in rows else "–"  # noqa: E731
        L.append(f"| {case} | {fmt_rate(t)} | {ratio('dynamax')} | {ratio('dynamax_pipeline')} | "
                 f"{fmt_rate(rows['draws']['rate'])} | {ratio('draws')} |")
    L.append("")
    L.append(f"Peak RSS: `ru_maxrss` of a fresh process running {cfg['mem_runs']} runs of the case "
             "(FilterPy: its timed subset), after importing jax and tracklab; for the others it includes the "
             "simulated measurements they are given.")
    L.append("")
    return "\n".join(L)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke version: fewer runs, does not write the results file")
    ap.add_argument("--runs", type=int, default=None, help="runs per case (default 10000; 2000 with --quick)")
    ap.add_argument("--repeat", type=int, default=None, help="timed passes, fastest kept (default 3; 1 with --quick)")
    ap.add_argument("--rounds", type=int, default=None,
                    help="interleaved rounds of the JAX implementations (default 5; 1 with --quick)")
    ap.add_argument("--out", type=Path, default=None, help="Markdown output (default benchmarks/results.md)")
    ap.add_argument("--child-memory", nargs=3, metavar=("CASE", "IMPL", "RUNS"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child_memory:
        child_memory(a.child_memory[0], a.child_memory[1], int(a.child_memory[2]))
        return

    import importlib.util

    missing = [m for m in ("dynamax", "filterpy") if importlib.util.find_spec(m) is None]
    if missing:
        sys.exit(f"compare.py needs the benchmark extra (pip install -e \".[bench]\", in its own virtualenv): "
                 f"{', '.join(missing)} not installed")

    t_all = time.perf_counter()
    load_start = os.getloadavg()
    runs = a.runs or (2000 if a.quick else 10_000)
    repeat = a.repeat or (1 if a.quick else 3)
    rounds = a.rounds or (1 if a.quick else 5)
    fp_runs = 5 if a.quick else 50
    cmd = "python benchmarks/compare.py" + (" --quick" if a.quick else "")
    cmd += f" --runs {a.runs}" if a.runs else ""
    cmd += f" --repeat {a.repeat}" if a.repeat else ""
    cmd += f" --rounds {a.rounds}" if a.rounds else ""

    # memory first, in fresh processes, before this one imports jax (see bench_lidar.py)
    mems = {}
    mem_runs = min(runs, 10_000)
    for case in CASES:
        for impl in ("tracklab", "dynamax", "numpy", "filterpy"):
            if impl == "dynamax" and case == "alpha-beta":
                continue
            mems[(case, impl)] = bench_memory(case, impl, fp_runs if impl == "filterpy" else mem_runs)
            print(f"memory {case} / {impl}: peak {mems[(case, impl)]['peak_mib']:.0f} MiB", flush=True)

    import dynamax
    import filterpy

    import tracklab

    tracklab.configure()  # one CPU device per core, Eigen single-threaded, 64-bit mode
    from bench_lidar import machine_info

    info = machine_info()
    info["loadavg"] = " ".join(f"{x:.2f}" for x in load_start)
    info["versions"] = f"dynamax {dynamax.__version__}, FilterPy {filterpy.__version__}, NumPy {__import__('numpy').__version__}"
    print(f"# {info}", flush=True)
    results = {case: run_case(case, runs, fp_runs, repeat, lambda s: print(s, flush=True), rounds) for case in CASES}
    cfg = {"runs": runs, "repeat": repeat, "rounds": rounds, "fp_runs": fp_runs, "mem_runs": mem_runs}
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())
    md = render(info, cmd, cfg, results, mems, time.perf_counter() - t_all, load_end)
    print()
    print(md)
    out = a.out if a.out is not None else (None if a.quick else ROOT / "benchmarks" / "results.md")
    if out is not None:
        write_run(out, md, "compare.py")
        print(f"written {out}")


if __name__ == "__main__":
    main()
