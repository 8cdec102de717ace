"""Tracking in clutter: a PDAF-EKF on scans of up to 32 returns, against tracklab's own EKF on
clean measurements, a NumPy PDAF vectorised over the runs and a FilterPy EKF driven by a
Python PDAF loop; and 10⁵ runs x 200 steps in bounded memory.

    python benchmarks/bench_clutter.py            # writes benchmarks/clutter.md (~6 min on 2 cores)
    python benchmarks/bench_clutter.py --quick    # fewer runs, prints only

FilterPy is the ``bench`` extra (``pip install -e ".[bench]"``); without it its row says so.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_lidar import time_program
from written import write_run

ROOT = Path(__file__).resolve().parent.parent
ENVIRONMENT = dict(os.environ)  # before tracklab.configure() sets its XLA flags: what a fresh process starts from

# paper 000's crossing seen by its polar sensor (σ_r = 100 m, σ_β = 3 mrad), detected with P_D =
# 0.9 among false alarms uniform over ±600 m x ±0.03 rad about the target (λV = 12 a scan)
BASE = """
[experiment]
name = "bench_clutter"
runs = 1000
seed = 0
dt = 0.5
steps = 200

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003
{clutter}

[prior]
pos_sigma = 100.0
vel_sigma = 50.0
{loss}

[[filter]]
{filter}
label = "F"

[report]
window = [20, 200]
"""
CLUTTER = "p_detect = 0.9\nclutter_density = 0.16667\nclutter_window = [600.0, 0.03]\nmax_returns = 32\n"
LOSS = "[track_loss]\ndistance = 1000.0\nsteps = 5\n"


def load(clutter: bool, kind="ekf"):
    from tracklab.config import load_experiment

    text = BASE.format(clutter=CLUTTER if clutter else "", loss=LOSS if clutter else "",
                       filter=f'kind = "pdaf"\nbase = "{kind}"' if clutter else f'kind = "{kind}"')
    path = Path(tempfile.mkdtemp()) / "bench_clutter.toml"
    path.write_text(text)
    return load_experiment(path)


def tracklab_rate(exp, runs, chunk):
    from tracklab.worlds.tracking import scan

    structure = exp.structure(chunk=chunk)
    t = time_program(scan.world(structure), exp.params(), runs, seed=0, repeat=1)
    return runs * exp.steps / t["wall_s"], t


def scans_of(exp, runs):
    """The first ``runs`` runs' truths, scans (runs, T, K, m) and prior means, as tracklab draws them."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tracklab.worlds.tracking.scan import simulate_runs

    with jax.enable_x64(True):
        truth, z, prior = simulate_runs(exp.scenario, exp.sensor, jnp.asarray(exp.prior_covariance()),
                                        jax.random.key(0), jnp.arange(runs, dtype=jnp.uint32))
    return np.asarray(truth), np.asarray(z), np.asarray(prior)


def _matrices(exp):
    import numpy as np

    from tracklab.models import cv

    m = cv(2, exp.dt)
    p = exp.params().filters[0]
    return (np.asarray(m.F), np.asarray(m.Q(float(p["q"]))), np.diag(np.asarray(p["r"], float)), float(p["gate"]),
            float(p["p_detect"]), float(p["clutter_density"]))


def numpy_pdaf(exp, z, prior):
    """PDAF-EKF vectorised over the runs (and the returns) with NumPy: the loop is over the steps."""
    import numpy as np
    from scipy.special import gammainc

    F, Q, R, gate, pd, lam = _matrices(exp)
    N, T, K, m = z.shape
    pg = gammainc(m / 2, gate / 2)
    x = prior.copy()  # the prior one period before z[0]
    P = np.broadcast_to(exp.prior_covariance(), (N, 4, 4)).copy()
    out = np.empty((N, T, 4))
    for k in range(T):
        x = x @ F.T
        P = F @ P @ F.T + Q
        px, py = x[:, 0], x[:, 2]
        r2 = px**2 + py**2
        r = np.sqrt(r2)
        H = np.zeros((N, 2, 4))
        H[:, 0, 0], H[:, 0, 2] = px / r, py / r
        H[:, 1, 0], H[:, 1, 2] = -py / r2, px / r2
        zp = np.stack([r, np.arctan2(py, px)], axis=1)
        S = H @ P @ H.transpose(0, 2, 1) + R
        Si = np.linalg.inv(S)
        Kg = P @ H.transpose(0, 2, 1) @ Si
        nu = z[:, k] - zp[:, None, :]
        nu[..., 1] = (nu[..., 1] + np.pi) % (2 * np.pi) - np.pi
        valid = np.all(np.isfinite(nu), axis=-1)
        nu = np.where(valid[..., None], nu, 0.0)
        d2 = np.einsum("nki,nij,nkj->nk", nu, Si, nu)
        gated = valid & (d2 <= gate)
        L = np.where(gated, pd * np.exp(-0.5 * d2) / np.sqrt(np.linalg.det(2 * np.pi * S))[:, None], 0.0)
        w0 = lam * (1 - pd * pg)
        denom = w0 + L.sum(axis=1)
        beta, b0 = L / denom[:, None], w0 / denom
        v = np.einsum("nk,nkm->nm", beta, nu)
        spread = np.einsum("nk,nki,nkj->nij", beta, nu, nu) - np.einsum("ni,nj->nij", v, v)
        x = x + np.einsum("nij,nj->ni", Kg, v)
        KSK = Kg @ S @ Kg.transpose(0, 2, 1)
        P = P - (1 - b0)[:, None, None] * KSK + Kg @ spread @ Kg.transpose(0, 2, 1)
        out[:, k] = x
    return out


def filterpy_pdaf(exp, z, prior):
    """FilterPy's ExtendedKalmanFilter for the prediction and the gain, a Python PDAF around it, one
    run at a time."""
    import numpy as np
    from filterpy.kalman import ExtendedKalmanFilter
    from scipy.special import gammainc

    F, Q, R, gate, pd, lam = _matrices(exp)
    N, T, K, m = z.shape
    pg = gammainc(m / 2, gate / 2)
    out = np.empty((N, T, 4))
    for n in range(N):
        ekf = ExtendedKalmanFilter(dim_x=4, dim_z=2)
        ekf.x, ekf.P, ekf.F, ekf.Q, ekf.R = prior[n].copy(), np.asarray(exp.prior_covariance()).copy(), F, Q, R
        for k in range(T):
            ekf.predict()
            px, py = ekf.x[0], ekf.x[2]
            r2 = px * px + py * py
            r = math.sqrt(r2)
            H = np.array([[px / r, 0, py / r, 0], [-py / r2, 0, px / r2, 0]])
            S = H @ ekf.P @ H.T + R
            Si = np.linalg.inv(S)
            Kg = ekf.P @ H.T @ Si
            zp = np.array([r, math.atan2(py, px)])
            nus, Ls = [], []
            for ret in z[n, k]:
                if not np.all(np.isfinite(ret)):
                    continue
                nu = ret - zp
                nu[1] = (nu[1] + math.pi) % (2 * math.pi) - math.pi
                d2 = float(nu @ Si @ nu)
                if d2 <= gate:
                    nus.append(nu)
                    Ls.append(pd * math.exp(-0.5 * d2) / math.sqrt(np.linalg.det(2 * math.pi * S)))
            w0 = lam * (1 - pd * pg)
            denom = w0 + sum(Ls)
            v, spread = np.zeros(2), np.zeros((2, 2))
            for nu, L in zip(nus, Ls):
                v += L / denom * nu
                spread += L / denom * np.outer(nu, nu)
            spread -= np.outer(v, v)
            ekf.x = ekf.x + Kg @ v
            ekf.P = ekf.P - (1 - w0 / denom) * Kg @ S @ Kg.T + Kg @ spread @ Kg.T
            out[n, k] = ekf.x
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "clutter.md"))
    a = ap.parse_args(argv)
    import jax
    import numpy as np

    import tracklab

    tracklab.configure()  # one CPU device per core, Eigen single-threaded, 64-bit mode

    runs = 2000 if a.quick else 10_000
    rows = []
    clean = load(False)
    rate_clean, t_clean = tracklab_rate(clean, runs, 1000)
    rows.append(("tracklab EKF, clean measurements", rate_clean, t_clean["compile_s"], ""))
    pdaf = load(True)
    rate_pdaf, t_pdaf = tracklab_rate(pdaf, runs, 1000)
    rows.append(("tracklab PDAF-EKF, 32 returns", rate_pdaf, t_pdaf["compile_s"],
                 f"{rate_pdaf / rate_clean:.2f} x the clean EKF"))
    n_np = 1000 if a.quick else 2000
    truth, z, prior = scans_of(pdaf, n_np)
    t0 = time.perf_counter()
    est = numpy_pdaf(pdaf, z, prior)
    rate_np = n_np * pdaf.steps / (time.perf_counter() - t0)
    rows.append(("NumPy PDAF-EKF, vectorised over the runs", rate_np, None, f"{n_np} runs"))
    try:
        import filterpy  # noqa: F401
        n_fp = 10 if a.quick else 30
        t0 = time.perf_counter()
        est_fp = filterpy_pdaf(pdaf, z[:n_fp], prior[:n_fp])
        rate_fp = n_fp * pdaf.steps / (time.perf_counter() - t0)
        agree = float(np.max(np.abs(est_fp - est[:n_fp])))
        rows.append(("FilterPy EKF + Python PDAF loop", rate_fp, None, f"{n_fp} runs; max |Δx| to NumPy {agree:.1e}"))
    except ImportError:
        rows.append(("FilterPy EKF + Python PDAF loop", None, None, "FilterPy not installed (the bench extra)"))
    big = 20_000 if a.quick else 100_000

    def alone(runs):
        """``simulate`` of ``runs`` runs in a process of its own: (wall s, its peak resident MiB, lost, RMSE)."""
        code = ("import sys, time, resource, json; sys.path.insert(0, %r); import tracklab; tracklab.configure(); "
                "import bench_clutter as b; e = b.load(True); t = time.perf_counter(); d = e.simulate(runs=%d); "
                "w = time.perf_counter() - t; s = d['filters']['F']['summary']; "
                "print(json.dumps([w, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, s['lost'], "
                "s['rmse_pos']]))") % (str(Path(__file__).resolve().parent), runs)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=ENVIRONMENT)
        return json.loads(out.stdout.strip().splitlines()[-1])

    small_peak = alone(big // 10)[1]
    wall, peak, lost, rmse = alone(big)
    text = ["# Tracking in clutter: a PDAF-EKF's throughput and memory", f"Run {_dt.date.today()} on {platform.processor() or platform.machine()}, {jax.device_count()} CPU devices, "
            f"jax {jax.__version__}, float64; `python benchmarks/bench_clutter.py{' --quick' if a.quick else ''}`.",
            "", f"Throughput over {runs} runs x 200 steps (the tracklab rows: simulation, filter and statistics):", "",
            "| implementation | runs·steps/s | compile (s) | note |", "|---|---|---|---|"]
    for name, rate, comp, note in rows:
        text.append(f"| {name} | {'—' if rate is None else f'{rate:,.0f}'} | {'—' if comp is None else f'{comp:.1f}'} "
                    f"| {note} |")
    text += ["", f"{big:,} runs x 200 steps of the PDAF-EKF (`tracklab`'s `simulate`, in a process of its own): "
             f"{wall:.0f} s ({big * 200 / wall:,.0f} runs·steps/s, compile included), peak resident memory "
             f"{peak:.0f} MiB ({small_peak:.0f} MiB for {big // 10:,} runs: the sums are streamed chunk by chunk, "
             f"never runs x steps); "
             f"{lost} tracks lost, RMSE {rmse:.1f} m over the runs on track.", ""]
    out = "\n".join(text)
    print(out)
    if not a.quick:
        write_run(Path(a.out), out, "bench_clutter.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
