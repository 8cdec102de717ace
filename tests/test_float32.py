"""Single precision: the same filters on the same measurements, and every bundled experiment."""

import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tracklab
from tracklab.config import load_experiment
from tracklab.filters import build, noise_params
from tracklab.montecarlo.statistics import statistics
from tracklab.models import ca, cv
from tracklab.sensors import Sensor

# the filter kinds test_float32_matches_float64_on_the_same_measurements runs in single precision
# on the polar sensor (CV model, the IMM on CV and CT)
ON_POLAR = [("ekf", {}), ("cmkf", {"debias": "unbiased"}), ("sequential_ekf", {}), ("polar_kf", {}), ("ukf", {}),
            ("alpha_beta", {"gains": "explicit"}), ("stf", {}), ("imm", {"models": ("cv", "ct")})]


def _distinct_experiments():
    """(file, filter labels to check) for the bundled experiments the Monte-Carlo engine runs: all
    but the files with a [servo] table (tests/test_servo.py) or an [airborne] table
    (tests/test_airborne*.py), which have their own float32 tests.

    A filter kind (with its motion model) is checked once per set of sensor kinds, and every
    scenario kind once: taking the files with the most filter kinds first, a file is checked for
    the filters of kinds it adds on its sensors (whole if all are new), and a file that adds none
    is checked only if its scenario kind is not yet, on its first filter. A filter kind checked
    again on the same sensors exercises nothing new (the scenario's truth is checked with the
    scenario) and would double the suite's compile time. The kinds that
    test_float32_matches_float64_on_the_same_measurements runs on the polar sensor count as
    checked on it."""
    import tomllib

    found = []
    for p in sorted(Path(__file__).resolve().parents[1].joinpath("experiments").glob("*.toml")):
        raw = tomllib.loads(p.read_text())
        if "servo" in raw or "airborne" in raw:
            continue
        if "track_loss" in raw:  # tracking in clutter: its kinds run in float32 in tests/test_clutter.py
            continue
        sensors = raw["sensor"] if isinstance(raw["sensor"], list) else [raw["sensor"]]
        filters = {f["label"]: (f["kind"], f.get("model", "cv")) for f in raw["filter"]}
        found.append((p, raw["scenario"]["kind"], tuple(s["kind"] for s in sensors), filters))
    # sensor kinds -> (filter kind, model) already checked (the IMM's models are not its "model" field)
    covered: dict = {("polar",): {(kind, "cv") for kind, _ in ON_POLAR if kind != "imm"}}
    scenarios = set()
    out = []
    for p, scenario, sensors, filters in sorted(found, key=lambda e: (-len(set(e[3].values())), e[0].name)):
        seen = covered.setdefault(sensors, set())
        labels = [label for label, kind in filters.items() if kind not in seen]
        if not labels and scenario not in scenarios:
            labels = list(filters)[:1]
        seen.update(filters.values())
        scenarios.add(scenario)
        if labels:
            out.append((p, None if len(labels) == len(filters) else labels))
    return sorted(out)


EXPERIMENTS = _distinct_experiments()


def _at_most(path, steps, tmp, labels=None):
    """The experiment cut to its first ``steps`` steps (long angle-tracking passes; the suite stays
    fast), with only the filters ``labels`` (all if None)."""
    import tomllib

    import tomlkit

    raw = tomllib.loads(path.read_text())
    if raw["experiment"]["steps"] <= steps and labels is None:
        return load_experiment(path)
    if raw["experiment"]["steps"] > steps:
        raw["experiment"]["steps"] = steps
        raw["report"] = {"window": [1, steps]}
    if labels is not None:
        raw["filter"] = [f for f in raw["filter"] if f["label"] in labels]
        raw.pop("study", None)
        if raw.get("report", {}).get("baseline") not in (None, *labels):  # its baseline filter cut away
            raw["report"].pop("baseline")
    if "path" in raw["scenario"]:
        raw["scenario"]["path"] = str((path.parent / raw["scenario"]["path"]).resolve())
    for module in path.parent.glob("*.py"):  # a filter of one's own the file names (kind = "module:factory")
        shutil.copy(module, tmp)
    out = tmp / f"{path.stem}.toml"
    out.write_text(tomlkit.dumps(raw))
    return load_experiment(out)


def _lidar_measurements(seed=0, T=200):
    rng = np.random.default_rng(seed)
    m = cv(2, 0.5)
    s = np.array([-20000.0, 400.0, 20000.0, 0.0])
    truth = []
    for _ in range(T):
        s = m.F @ s + m.G @ rng.normal(size=2)
        truth.append(s)
    truth = np.array(truth)
    z = np.stack([np.hypot(truth[:, 0], truth[:, 2]), np.arctan2(truth[:, 2], truth[:, 0])], 1)
    return truth, z + rng.normal(size=z.shape) * [100.0, 0.003]


@pytest.mark.parametrize("kind,opts", ON_POLAR)
def test_float32_matches_float64_on_the_same_measurements(kind, opts):
    """Joseph-form updates keep single precision within centimetres of double at 20 km."""
    truth, z = _lidar_measurements()
    sensor = Sensor("polar", 2, (100.0, 0.003))
    p = noise_params(1.0, np.array([100.0**2, 0.003**2]))
    if kind == "alpha_beta":
        p.update(alpha=np.array(0.3), beta=np.array(0.05))
    if kind == "stf":
        p.update(rho=np.array(0.95), b=np.array(1.0))
    if kind == "imm":
        from tracklab.filters import imm_params

        p = imm_params(("cv", "ct"), [1.0, 1.0], 1e-6, np.array([100.0**2, 0.003**2]))
    x0 = np.linalg.solve(cv(2, 0.5).F, truth[0]) + [50.0, 5.0, -50.0, 5.0]
    P0 = np.diag([100.0, 50.0, 100.0, 50.0]) ** 2
    make, pos = (lambda: cv(2, 0.5)), [0, 2]
    if kind == "imm":  # its common state is the CA layout
        make, pos = (lambda: ca(2, 0.5)), [0, 3]
        x0, P0 = (np.asarray(a) for a in make().embed(jnp.asarray(x0), jnp.asarray(P0), 1.0))
    d = tracklab.run_filter(build(kind, make(), sensor, p, opts), z, x0=x0, P0=P0)
    with jax.enable_x64(False):  # the filter built and run in single precision
        f32 = lambda a: jnp.asarray(np.asarray(a), jnp.float32)
        flt = build(kind, make(), sensor, {k: f32(v) for k, v in p.items()}, opts)
        s = tracklab.run_filter(flt, f32(z), x0=f32(x0), P0=f32(P0), precision="float32")
    assert s.x.dtype == np.float32 and d.x.dtype == np.float64
    # m, against errors of ~35 m; the IMM's mixture weights are exponentials of log-likelihood
    # differences, whose float32 rounding moves its estimate by up to a few metres while the modes settle
    tol = 5.0 if kind == "imm" else 0.5
    assert np.max(np.abs(np.asarray(s.x)[:, pos] - np.asarray(d.x)[:, pos])) < tol
    sd = np.sqrt(np.asarray(d.P)[:, pos, pos])
    # standard deviations within 0.5 %: the unbiased conversion's covariance is the most sensitive
    # (it adds r²-sized terms to get an r²σ²-sized result), at about 0.2 % in float32
    np.testing.assert_allclose(np.sqrt(np.asarray(s.P)[:, pos, pos]), sd, rtol=2e-2 if kind == "imm" else 5e-3)


@pytest.mark.parametrize("path,labels", EXPERIMENTS, ids=[p.stem for p, _ in EXPERIMENTS])
def test_every_bundled_experiment_runs_in_float32(path, labels, tmp_path):
    """Stated tolerance: with 8 runs, on the same random draws (made in float32 in both
    precisions), the time-averaged position RMSE of every filter agrees within 0.1 % and no
    filter diverges."""
    exp = _at_most(path, 2000, tmp_path, labels)
    runs = 8
    s64 = statistics(exp.monte_carlo(runs=runs, chunk=runs), exp.window)
    s32 = statistics(exp.monte_carlo(runs=runs, chunk=runs, precision="float32"), exp.window)
    for label, f in s64["filters"].items():
        a, b = f["summary"], s32["filters"][label]["summary"]
        assert b["diverged"] == 0, (label, b)
        assert abs(b["rmse_pos"] / a["rmse_pos"] - 1) < 1e-3, (label, a["rmse_pos"], b["rmse_pos"])
