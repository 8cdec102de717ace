"""Tracking in clutter: the cluttered sensor's scans, the association filters against NumPy
references written from the papers' equations, and the statistics of track loss."""

from __future__ import annotations

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab import run_filter
from tracklab.filters import ipda, kf, nearest_neighbour, pdaf, strongest_neighbour
from tracklab.filters.association import chi2_gate, gate_probability
from tracklab.sensors import Cluttered, Sensor
from tracklab.sensors.clutter import information_reduction_factor, poisson_count

DT = 1.0
F = np.array([[1, DT, 0, 0], [0, 1, 0, 0], [0, 0, 1, DT], [0, 0, 0, 1.0]])
H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
Q = 0.5**2 * np.kron(np.eye(2), np.array([[DT**4 / 4, DT**3 / 2], [DT**3 / 2, DT**2]]))
R = 5.0**2 * np.eye(2)


def _scans(sensor, steps, seed, truth):
    """The sensor's scans of a truth sequence (steps, 2) from one key."""
    with jax.enable_x64(True):
        return np.asarray(sensor.measure(jax.random.key(seed), jnp.asarray(truth)))


def _truth(steps):
    k = np.arange(1, steps + 1)
    return np.stack([10.0 * k, 5.0 * k], axis=1)


def test_poisson_count_inverts_the_distribution_function():
    with jax.enable_x64(True):
        for mean in (0.0, 0.3, 3.0, 12.0):
            pk = np.array([math.exp(-mean) * mean**k / math.factorial(k) for k in range(9)])
            cdf = np.cumsum(pk)
            for u in (0.0005, 0.2, 0.5, 0.9, 0.9999):
                n = int(poisson_count(jnp.asarray(u), jnp.asarray(mean), 8))
                assert n == int(np.sum(u > cdf)), (mean, u)


def test_scan_false_alarm_count_and_positions_follow_their_laws():
    """The number of returns per scan: Poisson (χ² goodness of fit, 10 000 scans); the false
    alarms uniform over their window (mean and variance); the detection among them."""
    lam_v = 3.0
    half = (60.0, 40.0)
    # σ = 1 cm: the target's return is the one within 5 cm of the truth
    sensor = Cluttered(Sensor("cartesian", 2, (0.01, 0.01), 1.0, dt=DT), lam_v / (4 * 60.0 * 40.0), half, None, 16)
    steps = 10_000
    truth = np.zeros((steps, 2))
    scans = _scans(sensor, steps, 1, truth)
    returns = np.all(np.isfinite(scans), axis=-1)
    n_false = returns.sum(axis=1) - 1  # p_detect = 1: one return is the target's
    counts = np.bincount(n_false, minlength=9)[:9].astype(float)
    counts[8] = np.sum(n_false >= 8)
    p = np.array([math.exp(-lam_v) * lam_v**k / math.factorial(k) for k in range(8)])
    p = np.append(p, 1 - p.sum())
    chi2 = float(np.sum((counts - steps * p) ** 2 / (steps * p)))
    assert chi2 < 26.1, chi2  # χ²₈ at 0.999
    pts = scans[returns]
    far = np.any(np.abs(pts) > 0.05, axis=1)  # leave out the target's return
    clutter = pts[far]
    assert np.all(np.abs(clutter) <= np.array(half) + 1e-9)
    assert len(clutter) == n_false.sum()
    # uniform on the window: mean 0 and variance w²/3 per axis (30 000 false alarms)
    np.testing.assert_allclose(clutter.mean(axis=0), 0.0, atol=1.5)
    np.testing.assert_allclose(clutter.var(axis=0), np.square(half) / 3, rtol=0.03)
    # the target's return sits at any row of the scan, not at a fixed one
    near = np.all(np.abs(scans) < 0.05, axis=-1)  # (steps, rows)
    rows = np.argmax(near, axis=1)[near.any(axis=1)]
    assert len(np.unique(rows)) == 16 and np.max(np.bincount(rows)) < 0.1 * len(rows)
    # with an amplitude model (SNR 0 dB: 1 + SNR = 2) the rows are in order of amplitude: the
    # target's row is the number of false alarms stronger than it, P(s = k | n) = C(n, k) ∫ pᵏ
    # (1 − p)ⁿ⁻ᵏ du with p = u², i.e. C(n, k) B(k + 1/2, n − k + 1) / 2; over n ~ Poisson(λV)
    ranked = Cluttered(sensor.sensor, sensor.density, half, None, 16, 0.0)
    scans = _scans(ranked, steps, 2, truth)
    near = np.all(np.abs(scans) < 0.05, axis=-1)
    s = np.argmax(near, axis=1)
    beta = lambda a, b: math.exp(math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b))  # noqa: E731
    pois = [math.exp(-lam_v) * lam_v**n / math.factorial(n) for n in range(16)]
    p = np.array([sum(pois[n] * math.comb(n, k) * beta(k + 0.5, n - k + 1) / 2 for n in range(k, 16))
                  for k in range(5)])
    p = np.append(p, 1 - p.sum())
    counts = np.append(np.bincount(s, minlength=5)[:5], np.sum(s >= 5)).astype(float)
    chi2 = float(np.sum((counts - steps * p) ** 2 / (steps * p)))
    assert chi2 < 20.5, (chi2, counts, steps * p)  # χ²₅ at 0.999


def _numpy_pdaf(zs, x0, P0, gate, pd, lam, *, rule="pdaf", p_survive=0.98, psi0=0.9):
    """The PDAF (Bar-Shalom, Daum & Huang 2009, parametric clutter), the nearest and strongest
    neighbours and the IPDA's existence (Mušicki et al. 1994) for a linear model, from their
    equations."""
    x, P, psi = x0.copy(), P0.copy(), psi0
    m = H.shape[0]
    pg = float(gate_probability(gate, m))
    xs, Ps, psis, gated = [], [], [], []
    for Z in zs:
        xp, Pp = F @ x, F @ P @ F.T + Q
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        Z = Z[np.all(np.isfinite(Z), axis=1)]
        nus = Z - H @ xp
        d2 = np.einsum("ki,ij,kj->k", nus, np.linalg.inv(S), nus)
        nus = nus[d2 <= gate]
        d2 = d2[d2 <= gate]
        gated.append(len(nus))
        if rule in ("nn", "snf"):  # the least d², or the first validated row (the strongest)
            if len(nus):
                nu = nus[np.argmin(d2)] if rule == "nn" else nus[0]
                x, P = xp + K @ nu, Pp - K @ S @ K.T
            else:
                x, P = xp, Pp
        else:
            L = pd * np.exp(-0.5 * d2) / math.sqrt(np.linalg.det(2 * np.pi * S)) / lam
            denom = 1 - pd * pg + L.sum()
            b0, b = (1 - pd * pg) / denom, L / denom
            nu = b @ nus if len(nus) else np.zeros(m)
            spread = np.einsum("k,ki,kj->ij", b, nus, nus) - np.outer(nu, nu) if len(nus) else np.zeros((m, m))
            x = xp + K @ nu
            P = b0 * Pp + (1 - b0) * (Pp - K @ S @ K.T) + K @ spread @ K.T
            psi_p = p_survive * psi
            delta = pd * pg - L.sum()
            psi = (1 - delta) * psi_p / (1 - delta * psi_p)
        xs.append(x)
        Ps.append(P)
        psis.append(psi)
    return np.array(xs), np.array(Ps), np.array(psis), np.array(gated)


def _run(flt, zs, x0, P0, scans=True):
    """``tracklab.run_filter`` over the scans (or measurements): (x, P, existence or None) per step."""
    r = run_filter(flt, zs, x0=x0, P0=P0, dt=DT, scans=scans)
    return np.asarray(r.x), np.asarray(r.P), None if r.aux is None else np.asarray(r.aux["existence"])


@pytest.mark.parametrize("rule", ["pdaf", "nn", "snf", "ipda"])
def test_association_against_numpy_reference_on_the_same_returns(rule):
    steps = 40
    lam = 4.0 / (4 * 80.0 * 80.0)
    # the returns in order of amplitude (SNR 3 dB: the target is often, not always, the strongest)
    sensor = Cluttered(Sensor("cartesian", 2, (5.0, 5.0), 0.8, dt=DT), lam, (80.0, 80.0), None, 16, 3.0)
    zs = _scans(sensor, steps, 7, _truth(steps))
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([25.0, 4.0, 25.0, 4.0])
    gate = chi2_gate(0.99, 2)
    with jax.enable_x64(True):
        base = kf(F, H, Q, R)
        flt = {"pdaf": lambda: pdaf(base, 2, clutter_density=lam, p_detect=0.8, gate=gate),
               "nn": lambda: nearest_neighbour(base, 2, gate=gate),
               "snf": lambda: strongest_neighbour(base, 2, gate=gate),
               "ipda": lambda: ipda(base, 2, clutter_density=lam, p_detect=0.8, gate=gate)}[rule]()
    xs, Ps, psi = _run(flt, zs, x0, P0)
    rx, rP, rpsi, gated = _numpy_pdaf(zs, x0, P0, gate, 0.8, lam, rule=rule)
    np.testing.assert_allclose(xs, rx, rtol=1e-9, atol=1e-7)
    np.testing.assert_allclose(Ps, rP, rtol=1e-8, atol=1e-7)
    if rule == "ipda":
        np.testing.assert_allclose(psi, rpsi, rtol=1e-9)
    # the association mattered: steps with several returns in the gate, and with none; the
    # strongest and the nearest neighbour are different trackers on these scans
    assert np.max(gated) >= 2 and np.min(gated) == 0, gated
    if rule == "snf":
        assert np.max(np.abs(rx - _numpy_pdaf(zs, x0, P0, gate, 0.8, lam, rule="nn")[0])) > 1.0


def test_pdaf_without_clutter_and_with_certain_detection_is_its_base_filter():
    steps = 30
    sensor = Sensor("cartesian", 2, (5.0, 5.0), 1.0, dt=DT)
    with jax.enable_x64(True):
        zs = np.asarray(sensor.measure(jax.random.key(3), jnp.asarray(_truth(steps))))
        base = kf(F, H, Q, R)
        flt = pdaf(base, 2, clutter_density=1e-300, p_detect=1.0, gate=1e4)
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([25.0, 4.0, 25.0, 4.0])
    xs, Ps, _ = _run(flt, zs[:, None, :], x0, P0)  # scans of one return
    bx, bP, _ = _run(base, zs, x0, P0, scans=False)
    np.testing.assert_allclose(xs, bx, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(Ps, bP, rtol=1e-12, atol=1e-9)


def test_information_reduction_factor_limits():
    """q = P_D without clutter; it falls as the clutter grows and never passes P_D."""
    for pd in (0.5, 0.9, 1.0):
        q0 = information_reduction_factor(0.0, pd, (10.0, 10.0), 64, scans=100_000)
        assert abs(q0 - pd) < 0.02 * pd, (pd, q0)
    qs = [information_reduction_factor(lam, 0.9, (10.0, 10.0), 64, scans=50_000) for lam in (0.001, 0.01, 0.05)]
    assert qs[0] > qs[1] > qs[2] > 0.0
    assert qs[0] <= 0.9 + 0.02


CLUTTER_FILE = """
[experiment]
name = "clutter_small"
runs = 128
seed = 3
dt = 1.0
steps = 60

[scenario]
kind = "constant_velocity"
initial = [0.0, 10.0, 0.0, 5.0]
accel_sigma = 0.5

[sensor]
kind = "cartesian"
sigma = 10.0
p_detect = 0.9
clutter_density = 1e-4
clutter_window = [120.0, 120.0]
max_returns = 16

[prior]
pos_sigma = 10.0
vel_sigma = 2.0

[track_loss]
distance = 60.0
steps = 5

[[filter]]
kind = "nn"
base = "kf"
label = "NN"

[[filter]]
kind = "pdaf"
base = "kf"
label = "PDAF"

[report]
window = [21, 60]
"""


def _clutter_file(tmp_path, text=CLUTTER_FILE, name="clutter_small.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# the IPDA beside the PDAF, its track also lost when its existence stays below 0.6: what
# test_clutter_statistics_match_the_modified_riccati_equation runs, and tests/test_processes.py
# runs in two processes against one process at another chunk size
CLUTTER_IPDA = (CLUTTER_FILE.replace("steps = 5\n", "steps = 5\nexistence = 0.6\n")
                .replace('kind = "nn"\nbase = "kf"\nlabel = "NN"', 'kind = "ipda"\nbase = "kf"\nlabel = "IPDA"'))


def test_clutter_statistics_match_the_modified_riccati_equation(tmp_path):
    """The PDAF's position RMSE over its runs on track is within 8 % of the steady state of
    Fortmann et al.'s modified Riccati equation (an approximation: it averages the covariance over
    the returns); the PCRLB with the information reduction factor lies below both; with [track_loss]
    existence the IPDA (the PDAF's estimates) loses the PDAF's tracks and those whose existence
    probability stays low; in float32, on the same draws, nearly the same. (The same statistics for
    any chunk size and process count: tests/test_processes.py.)"""
    from tracklab.config import load_experiment
    from tracklab.montecarlo.riccati import pdaf_steady_state

    exp = load_experiment(_clutter_file(tmp_path, CLUTTER_IPDA))
    a = exp.simulate(runs=128, seed=3)
    # in single precision, on the same draws: the same tracks lost but for a gating decision or two
    # that rounding flips, the RMSE within 1 %, nothing diverged
    s32 = exp.simulate(runs=128, seed=3, precision="float32")
    for label, f in a["filters"].items():
        g = s32["filters"][label]["summary"]
        assert g["diverged"] == 0 and abs(g["lost"] - f["summary"]["lost"]) <= 2, (label, g["lost"])
        assert abs(g["rmse_pos"] / f["summary"]["rmse_pos"] - 1) < 1e-2, (label, g["rmse_pos"])
    ipda, pdaf_ = a["filters"]["IPDA"]["summary"], a["filters"]["PDAF"]["summary"]
    assert ipda["lost"] > pdaf_["lost"], (ipda["lost"], pdaf_["lost"])
    assert a["filters"]["PDAF"]["paired"]["p_lost"]["difference"] < 0  # paired to the IPDA, the baseline
    pd = a["filters"]["PDAF"]["summary"]
    lo, hi = a["filters"]["PDAF"]["intervals"]["p_lost"]
    assert lo <= pd["p_lost"] <= hi
    F = np.array([[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1.0]])
    Qd = np.kron(np.eye(2), 0.25 * np.array([[0.25, 0.5], [0.5, 1.0]]))
    P, _, q2 = pdaf_steady_state(F, Qd, H, 100.0 * np.eye(2), 0.9, 1e-4, chi2_gate(0.99, 2))
    mre = math.sqrt(P[0, 0] + P[2, 2])
    assert abs(pd["rmse_pos"] / mre - 1) < 0.08, (pd["rmse_pos"], mre, q2)
    assert pd["pcrlb_pos"] < mre
    assert 1.0 < pd["validated_per_scan"] < 3.0


@pytest.mark.parametrize("change, field", [
    (('kind = "nn"\nbase = "kf"', 'kind = "kf"'), "filter[1].kind"),
    (("[track_loss]\ndistance = 60.0\nsteps = 5\n", ""), "[track_loss]"),
    (("max_returns = 16", "max_returns = 16\nclutter_coverage = [[0.0, 1.0], [0.0, 1.0]]"), "sensor.clutter_window"),
    (("clutter_window = [120.0, 120.0]", "clutter_window = [120.0]"), "sensor.clutter_window"),
    (('kind = "pdaf"\nbase = "kf"', 'kind = "pdaf"\nbase = "stf"'), "filter[2].base"),
    (('kind = "nn"\nbase = "kf"', 'kind = "snf"\nbase = "kf"'), "filter[1].kind"),  # no amplitude: no strongest
    (("max_returns = 16", "max_returns = 16\nsnr = 99.0"), "sensor.snr"),
])
def test_a_bad_clutter_file_is_refused_in_one_line(tmp_path, change, field):
    from tracklab.config import load_experiment
    from tracklab.errors import ConfigError

    old, new = change
    assert old in CLUTTER_FILE
    with pytest.raises(ConfigError) as info:
        load_experiment(_clutter_file(tmp_path, CLUTTER_FILE.replace(old, new)))
    assert info.value.field == field and "\n" not in str(info.value), str(info.value)


def test_the_pdaf_tuning_loss_has_the_gradient_of_its_finite_differences(tmp_path):
    """PDAF's update is smooth in its numbers: the tuning loss's derivative in the unconstrained
    coordinates of the gate and of q (along a direction mixing both) agrees with central finite
    differences on the same runs."""
    from tracklab.config import load_experiment
    from tracklab.studies.tune import objective

    text = CLUTTER_FILE.replace('[[filter]]\nkind = "nn"\nbase = "kf"\nlabel = "NN"\n', "")
    text = text.replace("steps = 60", "steps = 30").replace("window = [21, 60]", "window = [1, 30]")
    exp = load_experiment(_clutter_file(tmp_path, text))
    assert [f.label for f in exp.filters] == ["PDAF"]
    obj = objective(exp, {"PDAF": ["gate", "q"]})
    idx = jnp.arange(16, dtype=jnp.uint32)
    with jax.enable_x64(True):
        key = jax.random.key(0)
        live = jnp.ones(16, bool)
        theta = jax.tree_util.tree_map(jnp.asarray, obj.theta0)
        v = {"PDAF": {"gate": jnp.asarray(0.6), "q": jnp.asarray(-0.8)}}  # a direction mixing both
        # one program: the loss and its derivative along v (forward mode), the loss alone for the differences
        along = jax.jit(lambda th: jax.jvp(lambda t: obj.losses(t, key, idx, live)["PDAF"], (th,), (v,)))
        _, slope = along(theta)
        h = 1e-5
        moved = lambda s: jax.tree_util.tree_map(lambda t, d: t + s * d, theta, v)  # noqa: E731
        fd = (along(moved(h))[0] - along(moved(-h))[0]) / (2 * h)
        assert abs(float(fd)) > 1e-6, fd  # the loss does depend on them
        assert abs(float(slope) - float(fd)) <= 1e-4 * max(1.0, abs(float(fd))), (slope, fd)


def test_ones_own_pdaf_from_python_is_the_built_in_one():
    """tracklab.experiment with a Cluttered sensor: the built-in kind (kind = "pdaf", base = "kf")
    is, step for step on the same scans, the PDAF over one's own KF (tracklab.filters.pdaf); a plain
    filter on scans is refused in one line before anything compiles."""
    import tracklab
    from tracklab.errors import ConfigError
    from tracklab.scenarios import ConstantVelocity

    sc = ConstantVelocity(dt=1.0, steps=25, initial=(0.0, 10.0, 0.0, 5.0), accel_sigma=0.5)
    sen = Cluttered(Sensor("cartesian", 2, (10.0, 10.0), 0.9), 2e-4, (120.0, 120.0), None, 32)
    with pytest.raises(ConfigError, match="max_returns = 16: must be at least 24"):  # 11.5 false alarms a scan
        tracklab.experiment(sc, Cluttered(sen.sensor, 2e-4, (120.0, 120.0), None, 16), [{"kind": "pdaf"}],
                            track_loss=(60.0, 5))
    Qd = np.kron(np.eye(2), 0.25 * np.array([[0.25, 0.5], [0.5, 1.0]]))
    with jax.enable_x64(True):
        mine = pdaf(kf(F, H, Qd, 100.0 * np.eye(2)), 2, clutter_density=2e-4, p_detect=0.9)
    exp = tracklab.experiment(sc, sen, [{"kind": "pdaf", "base": "kf", "label": "PDAF"},
                                        tracklab.FilterSpec("mine", mine)],
                              runs=64, prior={"pos_sigma": 10.0, "vel_sigma": 2.0}, track_loss=(60.0, 5))
    built_in = exp.filter_specs()[0].filter
    zs = _scans(exp.sensor.sensors[0], 25, 4, _truth(25))
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([100.0, 4.0, 100.0, 4.0])
    (xa, Pa, _), (xb, Pb, _) = _run(built_in, zs, x0, P0), _run(mine, zs, x0, P0)
    np.testing.assert_allclose(xa, xb, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(Pa, Pb, rtol=1e-10, atol=1e-8)
    with pytest.raises(ConfigError) as info:
        tracklab.experiment(sc, sen, [tracklab.FilterSpec("plain", kf(F, H, Qd, 100.0 * np.eye(2)))],
                            track_loss=(60.0, 5))
    assert "\n" not in str(info.value) and "scan" in str(info.value)


def test_the_track_loss_intervals_cover_the_truth_95_percent_of_the_time():
    """The lost fraction's Wilson interval and the paired difference's interval between two trackers
    on the same runs (``paired_loss``), over 2 000 simulated batches of 300 runs each with known
    loss probabilities (0.07 and 0.40, correlated: a run one tracker loses the other is likelier to
    lose), cover the truth 95 % of the time within a binomial margin."""
    from tracklab.intervals import wilson
    from tracklab.montecarlo.statistics import paired_loss

    rng = np.random.default_rng(5)
    reps, n = 2000, 300
    p_a, p_b_given = 0.07, (0.33, 1.0)  # P(B lost | A not lost), P(B lost | A lost)
    p_b = (1 - p_a) * p_b_given[0] + p_a * p_b_given[1]
    cover = cover_diff = 0
    for _ in range(reps):
        a = rng.random(n) < p_a
        b = rng.random(n) < np.where(a, p_b_given[1], p_b_given[0])
        lo, hi = wilson(a.sum(), n)
        cover += lo <= p_a <= hi
        pairs = np.array([[0, np.sum(a & ~b)], [np.sum(b & ~a), 0]], float)
        d = paired_loss(pairs, ["A", "B"], "A", n)["B"]
        cover_diff += abs(d["difference"] - (p_b - p_a)) <= d["half_width"]
    margin = 3.29 * math.sqrt(0.95 * 0.05 / reps)
    assert abs(cover / reps - 0.95) < margin + 0.01, cover / reps  # Wilson is slightly conservative
    assert abs(cover_diff / reps - 0.95) < margin + 0.01, cover_diff / reps


def test_a_pdaf_over_ones_own_filter_named_in_a_file_is_the_built_in_one(tmp_path):
    """kind = "pdaf" with base = "own_filter:converted_kf" (the bundled CMKF of one's own, whose
    covariance depends on the measurement: the mixture reduction) gives the built-in PDAF-CMKF's
    numbers on the same runs; a factory that is not there is refused in one line."""
    import shutil

    from tracklab.config import load_experiment
    from tracklab.errors import ConfigError

    shutil.copy(Path(__file__).resolve().parents[1] / "experiments" / "own_filter.py", tmp_path)
    text = """
[experiment]
name = "own_base"
runs = 16
dt = 0.5
steps = 30

[scenario]
kind = "crossing"

[sensor]
kind = "polar"
sigma_r = 100.0
sigma_angle = 0.003
p_detect = 0.9
clutter_density = 0.01
clutter_window = [600.0, 0.03]

[prior]
pos_sigma = 100.0
vel_sigma = 50.0

[track_loss]
distance = 1000.0

[[filter]]
kind = "pdaf"
base = "cmkf"
label = "built in"

[[filter]]
kind = "pdaf"
base = "own_filter:converted_kf"
label = "own"
accel_var = 1.0
"""
    doc = load_experiment(_clutter_file(tmp_path, text, "own_base.toml")).simulate()
    a, b = doc["filters"]["built in"]["summary"], doc["filters"]["own"]["summary"]
    assert a["lost"] == b["lost"] and b["rmse_pos"] == pytest.approx(a["rmse_pos"], rel=1e-7)
    with pytest.raises(ConfigError) as info:
        load_experiment(_clutter_file(tmp_path, text.replace("own_filter:converted_kf", "own_filter:nothing"), "bad.toml"))
    assert info.value.field == "filter[2].base" and "\n" not in str(info.value)
