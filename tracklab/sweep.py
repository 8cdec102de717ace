"""Parameter sweeps: a grid of scale factors evaluated in one vmapped call.

``--grid q=0.01:100:9`` multiplies every filter's process-noise variance by 9
log-spaced factors from 0.01 to 100 (``r`` likewise scales R): the noise-mismatch
study of paper 001. Any numeric filter parameter (``q``, ``r``, ``lam``,
``alpha``, ``beta``, ``gamma``, the STF's ``rho`` and ``b``, the error-space
``q_e``, ``r_e``, ``r_guide``) can be scaled. All grid points of a chunk of runs
are one call, ``vmap``-ped over the grid; grid points and runs are processed in
blocks so memory stays bounded. Run i uses the same random numbers at every grid
point (common random numbers), so differences between points are the
parameters', not the noise's.
"""

from __future__ import annotations

import csv
import io
import itertools
import re
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tracklab.engine import MonteCarloResult, Sums, make_chunk_fn, pcrlb
from tracklab.metrics import statistics
from tracklab.output import atomic_folder
from tracklab.report import _fmt, md_cell, write_json

GRID_RE = re.compile(r"^([a-z_]+)=([^:]+):([^:]+):(\d+)$")
SCALABLE = ("q", "r", "lam", "alpha", "beta", "gamma", "rho", "b", "q_e", "r_e", "r_guide")


@dataclass(frozen=True)
class Axis:
    name: str
    values: np.ndarray  # scale factors


def parse_grid(spec: str) -> Axis:
    """NAME=LO:HI:N -> N log-spaced factors from LO to HI."""
    m = GRID_RE.match(spec.strip())
    if not m:
        raise ValueError("must look like NAME=LO:HI:N, e.g. q=0.01:100:9")
    name, lo, hi, n = m.group(1), float(m.group(2)), float(m.group(3)), int(m.group(4))
    if name not in SCALABLE:
        raise ValueError(f"NAME must be one of {', '.join(SCALABLE)}")
    if not (0 < lo <= hi and np.isfinite(hi)) or not 1 <= n <= 1000:
        raise ValueError("needs 0 < LO <= HI and 1 <= N <= 1000")
    return Axis(name, np.geomspace(lo, hi, n))


def grid_points(axes: list[Axis]) -> int:
    return int(np.prod([len(a.values) for a in axes], dtype=float))


def _call_shape(exp, points, runs, chunk=None, block_points=None):
    """(runs, grid points) of one call: memory per call grows with grid points × runs × steps,
    kept near 10⁶ run-steps."""
    budget = 1_000_000
    chunk = int(min(chunk or exp.chunk or 1000, runs, max(16, budget // exp.steps)))
    return chunk, int(block_points or max(1, min(points, budget // (chunk * exp.steps))))


def memory_bytes(exp, axes: list[Axis], runs=None) -> float:
    """A lower bound: every grid point's per-step statistics of every filter (kept until the
    sweep is written) and its PCRLB information, and one call's random draws."""
    P = grid_points(axes)
    chunk, block = _call_shape(exp, P, runs or exp.runs)
    width = 2 * exp.dim + exp.sensor.m
    per_point = exp.steps * (len(exp.filters) * 64 + exp.dim**2) * 8.0
    return P * per_point + block * chunk * exp.steps * width * 4.0


def check_sweep(exp, axes: list[Axis], runs=None, limit=None):
    """Refuse (ConfigError) a grid naming a parameter no filter has, or one too large to hold."""
    from tracklab.errors import ConfigError
    from tracklab.memory import check

    for a in axes:
        if not any(a.name in fc.params for fc in exp.filters):
            raise ConfigError(exp.path, "--grid", a.name, f"no filter of this experiment has the parameter {a.name!r}")
    check(exp.path, memory_bytes(exp, axes, runs), limit, f"a sweep of {grid_points(axes):.3g} grid points",
          "fewer grid points (N in NAME=LO:HI:N), or fewer experiment.steps")


def scaled(params: dict, factors: dict) -> dict:
    return {k: (v * factors[k] if k in factors else v) for k, v in params.items()}


def sweep(exp, axes: list[Axis], runs=None, seed=None, block_points=None, chunk=None, progress=None, max_memory=None):
    """Statistics of every filter at every grid point: {"points": [...], "stats": [statistics, ...]}."""
    check_sweep(exp, axes, runs, max_memory)
    specs = exp.filter_specs()
    fn = make_chunk_fn(exp.scenario, exp.sensor, specs, exp.prior_covariance(), exp.dt, exp.pred_windows)
    base = [s.filter.params for s in specs]
    runs = runs or exp.runs
    key = jax.random.key(exp.seed if seed is None else seed)
    points = list(itertools.product(*[a.values for a in axes]))
    names = [a.name for a in axes]
    P = len(points)
    chunk, block = _call_shape(exp, P, runs, chunk, block_points)

    def point_params(f):
        factors = dict(zip(names, f))
        return [scaled(p, factors) for p in base]

    def many(factors, key, idx, live, exclude):  # vmapped over the grid points of a block
        return jax.vmap(lambda f, ex: fn(point_params(f), key, idx, live, ex))(factors, exclude)

    many = jax.jit(many)
    grid = jnp.asarray(np.array(points, float).reshape(P, len(axes)))
    acc = [{s.label: Sums() for s in specs} for _ in range(P)]
    info = [np.zeros((exp.steps, exp.dim, exp.dim)) for _ in range(P)]
    t0 = time.perf_counter()
    n_chunks = -(-runs // chunk)
    for b0 in range(0, P, block):
        fb = grid[b0:b0 + block]
        pad = block - fb.shape[0]
        if pad:
            fb = jnp.concatenate([fb, jnp.repeat(fb[-1:], pad, axis=0)])
        for c in range(n_chunks):
            idx = np.arange(c * chunk, (c + 1) * chunk, dtype=np.uint32)
            args = (fb, key, jnp.asarray(idx), jnp.asarray(idx < runs))
            out = jax.device_get(many(*args, jnp.zeros((block, len(specs), chunk), bool)))
            masks = np.stack([out[s.label].pop("diverged_runs") for s in specs], axis=1)  # (block, filters, chunk)
            if masks.any():  # leave every diverged run out from its first step (see engine.rerun_without_diverged)
                out = jax.device_get(many(*args, jnp.asarray(masks)))
                for s in specs:
                    out[s.label].pop("diverged_runs")
            for j in range(block - pad):
                info[b0 + j] += out["_info"][j]
                for s in specs:
                    acc[b0 + j][s.label].add({k: v[j] for k, v in out[s.label].items() if k != "example_x"})
            if progress:
                progress((b0 // block) * n_chunks + c + 1, -(-P // block) * n_chunks)
    wall = time.perf_counter() - t0

    results = []
    for j, f in enumerate(points):
        res = MonteCarloResult(
            runs=runs, steps=exp.steps, dt=exp.dt, dim=exp.dim,
            sums={l: a.data for l, a in acc[j].items()},
            pcrlb=pcrlb(exp.scenario, exp.prior_covariance(), info[j] / runs),
            wall_s=wall, compile_s=0.0, labels=[s.label for s in specs], kinds={s.label: s.kind for s in specs},
            axes=tuple(getattr(exp.scenario, "axes", ("x", "y", "z")[: exp.dim])),
            units=tuple(getattr(exp.scenario, "units", ("m", "m/s"))),
        )
        results.append({"factors": dict(zip(names, map(float, f))), "stats": statistics(res, exp.window, exp.pred_windows)})
    return {"axes": {a.name: a.values.tolist() for a in axes}, "points": results, "wall_s": wall, "runs": runs,
            "units": list(getattr(exp.scenario, "units", ("m", "m/s")))}


def write_sweep(exp, doc, out, figures=True):
    """sweep.json, table.md, table.csv and heatmaps (1-D: curves) of RMSE and NEES per filter."""
    with atomic_folder(Path(out), exp.path) as tmp:
        return _write_sweep(exp, doc, tmp, figures)


def _csv(v):
    return v if v is not None and np.isfinite(v) else ""


def _write_sweep(exp, doc, tmp, figures):
    names = list(doc["axes"])
    labels = list(doc["points"][0]["stats"]["filters"])
    first = doc["points"][0]["stats"]["filters"][labels[0]]["summary"]
    metrics = ["rmse_pos", "rmse_vel", "pred_err_rms"] + [k for k in first if k.startswith("pred_err_max[")]
    metrics += ["nees", "nees_in_bounds"]
    rows = []
    for p in doc["points"]:
        for l in labels:
            s = p["stats"]["filters"][l]["summary"]
            rows.append([*(p["factors"][n] for n in names), l, *(s.get(m) for m in metrics), s["diverged"]])
    header = [*(f"{n} x" for n in names), "filter", *metrics, "diverged"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    for r in rows:
        cells = [f"{v:.4g}" for v in r[:len(names)]] + [md_cell(r[len(names)])] + [_fmt(v, "{:.4g}") for v in r[len(names) + 1:-1]] + [str(int(r[-1]))]
        lines.append("| " + " | ".join(cells) + " |")
    (tmp / "table.md").write_text("\n".join(lines) + "\n")
    buf = io.StringIO()
    csv.writer(buf).writerows([header, *([*r[:len(names) + 1], *map(_csv, r[len(names) + 1:-1]), r[-1]] for r in rows)])
    (tmp / "table.csv").write_text(buf.getvalue())
    summary_only = {
        "name": exp.name, "runs": doc["runs"], "window": list(exp.window), "axes": doc["axes"], "wall_s": doc["wall_s"],
        "points": [{"factors": p["factors"], "filters": {l: {"kind": f["kind"], "summary": f["summary"]}
                                                           for l, f in p["stats"]["filters"].items()}}
                   for p in doc["points"]],
        "experiment": exp.raw,
    }
    write_json(tmp / "sweep.json", summary_only)
    if figures and len(names) <= 2:
        _plot(doc, names, labels, tmp)
    return rows


def _log_edges(values):
    """Cell edges for values on a log axis: geometric midpoints, the end cells as wide as their
    neighbours (a single value: a factor 2 either side)."""
    v = np.log(np.asarray(values, float))
    if len(v) == 1:
        return np.exp(v[0] + np.array([-np.log(2), np.log(2)]))
    mid = 0.5 * (v[1:] + v[:-1])
    return np.exp(np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]]))


def _plot(doc, names, labels, folder):
    from tracklab.report import pyplot

    plt = pyplot()

    axes_vals = [np.asarray(doc["axes"][n]) for n in names]
    unit = doc.get("units", ("m",))[0]
    for metric, title in (("rmse_pos", f"time-averaged position RMSE ({unit})"), ("nees", "average NEES"),
                          ("pred_err_rms", f"RMS one-step prediction error ({unit})")):
        # None (no healthy run at a point) -> NaN -> masked: left blank
        values = {l: np.ma.masked_invalid(np.array([p["stats"]["filters"][l]["summary"].get(metric)
                                                    for p in doc["points"]], float)) for l in labels}
        if any(np.ma.is_masked(v) for v in values.values()):
            title += " — blank: no run without divergence"
        fig, axs = plt.subplots(1, len(labels), figsize=(4.2 * len(labels), 3.6), squeeze=False)
        for ax, l in zip(axs[0], labels):
            vals = values[l]
            if len(names) == 1:
                ax.loglog(axes_vals[0], vals, "o-")
                ax.set_xlabel(f"{names[0]} scale factor")
                ax.grid(True, which="both", alpha=0.3)
            else:
                grid = vals.reshape(len(axes_vals[0]), len(axes_vals[1]))
                im = ax.pcolormesh(_log_edges(axes_vals[1]), _log_edges(axes_vals[0]), np.ma.log10(grid))
                ax.set_xscale("log")
                ax.set_yscale("log")
                ax.set_xlabel(f"{names[1]} scale factor")
                ax.set_ylabel(f"{names[0]} scale factor")
                fig.colorbar(im, ax=ax, label=f"log10 {metric}")
            ax.set_title(l, fontsize=9)
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(folder / f"sweep_{metric}.png", dpi=110)
        plt.close(fig)
