"""Monte-Carlo uncertainty: intervals that cover, paired comparisons, runs = "auto", percentiles."""

import math

import numpy as np
import pytest

import tracklab
from tracklab.config import load_experiment
from tracklab.intervals import precision_reached, t_quantile, wilson
from tracklab.montecarlo.statistics import statistics
from tracklab.models import cv

import test_closed_loop_studies as studies  # the closed loops' tiny files
from tracklab.report.document import read_results

LINEAR = """
[experiment]
name = "linear_small"
runs = 20
chunk = 20
dt = 1.0
steps = 20

[scenario]
kind = "crossing"
speed = 100.0
offset = 2000.0
start_x = -5000.0
accel_sigma = 2.0

[sensor]
kind = "cartesian"
sigma = [30.0, 60.0]

[prior]
pos_sigma = 50.0
vel_sigma = 10.0

[[filter]]
kind = "kf"
label = "KF"
accel_sigma = 2.0
"""


def write(tmp_path, text, name="exp.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def riccati_rmse(steps, dt=1.0, q=2.0, sigma=(30.0, 60.0), p0=(50.0, 10.0)):
    """The matched KF's true time-averaged position RMSE: sqrt of the mean over the steps of
    tr(P_pos), its covariance from the Riccati recursion (NumPy)."""
    m = cv(2, dt)
    F, Q = np.asarray(m.F), np.asarray(m.Q(q**2))
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    R = np.diag(np.square(sigma))
    P = np.diag([p0[0] ** 2, p0[1] ** 2] * 2)
    mse = []
    for _ in range(steps):
        P = F @ P @ F.T + Q
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        P = (np.eye(4) - K @ H) @ P
        mse.append(P[0, 0] + P[2, 2])
    return math.sqrt(np.mean(mse))


def binomial_band(n, p, z=3.29):
    """p ± z binomial standard deviations of a fraction of n (z = 3.29: 99.9 %)."""
    sd = math.sqrt(p * (1 - p) / n)
    return p - z * sd, p + z * sd


def test_t_quantile_and_wilson_against_known_values():
    assert t_quantile(0.95, 1) == pytest.approx(12.7062047, rel=1e-6)
    assert t_quantile(0.95, 10) == pytest.approx(2.2281389, rel=1e-6)
    assert t_quantile(0.99, 30) == pytest.approx(2.7499957, rel=1e-6)
    assert t_quantile(0.95, 1e9) == pytest.approx(1.959964, rel=1e-6)
    lo, hi = wilson(0, 100)
    assert lo == 0.0 and hi == pytest.approx(0.036994, rel=1e-4)  # 1.96² / (100 + 1.96²)
    lo, hi = wilson(5, 10)
    assert lo == pytest.approx(1 - hi) and 0.2 < lo < 0.25


def test_rmse_interval_covers_the_riccati_value_95_percent_of_the_time(tmp_path):
    """200 independent 20-run Monte-Carlo runs of a matched linear KF: the true time-averaged
    RMSE (from the Riccati recursion) lies inside the 95 % interval 95 % ± a binomial margin
    of the time. The NEES's interval covers its true value (the state dimension, 4) too."""
    exp = load_experiment(write(tmp_path, LINEAR))
    truth = riccati_rmse(20)
    reps = 200
    covered = covered_nees = 0
    for seed in range(reps):
        st = statistics(exp.monte_carlo(seed=seed), exp.window)
        f = st["filters"]["KF"]
        v, hw = f["summary"]["rmse_pos"], f["half_width"]["rmse_pos"]
        covered += abs(v - truth) <= hw
        covered_nees += abs(f["summary"]["nees"] - 4.0) <= f["half_width"]["nees"]
    lo, hi = binomial_band(reps, 0.95)
    assert lo <= covered / reps <= hi, (covered, truth)
    assert lo <= covered_nees / reps <= hi, covered_nees


PAIRED = LINEAR.replace("runs = 20\nchunk = 20", "runs = 400\nchunk = 200") + """
[[filter]]
kind = "kf"
label = "KF again"
accel_sigma = 2.0

[[filter]]
kind = "kf"
label = "KF low q"
accel_sigma = 0.7
"""


def test_paired_interval_is_zero_against_itself_and_narrower_than_unpaired(tmp_path):
    exp = load_experiment(write(tmp_path, PAIRED))
    st = statistics(exp.monte_carlo(), exp.window)
    f = st["filters"]
    base = f["KF"]["paired"]
    assert base["baseline"] == "KF" and base["runs"] == 400
    for key in ("rmse_pos", "rmse_vel", "nees", "pred_err_rms"):
        assert base[key]["difference"] == 0.0 and base[key]["half_width"] == 0.0, key
        same = f["KF again"]["paired"][key]  # the same filter under another label: the same numbers
        assert same["difference"] == pytest.approx(0.0, abs=1e-9 * f["KF"]["summary"][key])
        assert same["half_width"] <= 1e-6 * f["KF"]["half_width"][key] and not same["significant"]
        other = f["KF low q"]["paired"][key]
        unpaired = math.hypot(f["KF low q"]["half_width"][key], f["KF"]["half_width"][key])
        assert 0 < other["half_width"] < unpaired, key
        # the difference is that of the two summaries (both filters healthy in every run)
        assert other["difference"] == pytest.approx(f["KF low q"]["summary"][key] - f["KF"]["summary"][key], rel=1e-9)
    # a baseline named in [report]
    exp = load_experiment(write(tmp_path, PAIRED + '\n[report]\nbaseline = "KF low q"\n', "b.toml"))
    st = statistics(exp.monte_carlo(), exp.window, level=exp.level, baseline=exp.baseline)
    assert st["filters"]["KF"]["paired"]["baseline"] == "KF low q"
    assert st["filters"]["KF low q"]["paired"]["rmse_pos"]["half_width"] == 0.0


def test_paired_moments_equal_numpy_on_the_runs_and_keep_a_tiny_difference():
    """Streamed in chunks of unequal size, with runs missing from one lane or the other: the means,
    covariances and paired half-width of ``RunSamples.pair`` equal NumPy's on the common runs.
    Three lanes: f, f plus 1e-9 of noise (samples that agree to 9 digits: the variance of the
    difference is 1e-18 of theirs, below the rounding of var f + var g − 2 cov(f, g), and must
    come from the differences) and f itself under another label (a half-width of exactly 0)."""
    from tracklab.intervals import paired_half_width, value_and_gradient
    from tracklab.montecarlo.samples import RunSamples

    rng = np.random.default_rng(5)
    B, Q = 230, 3
    f = 100.0 + rng.normal(size=(Q, B)) * [[1.0], [2.0], [0.5]]
    values = np.stack([f, f + 1e-9 * rng.normal(size=(Q, B)), f])
    ok = rng.random((3, B)) > 0.1
    values = np.where(ok[:, None, :], values, np.nan)  # a run left out may hold anything
    samples = RunSamples()
    for a, b in ((0, 17), (17, 120), (120, B)):
        samples.add(values[..., a:b], ok[:, a:b])
    stat = ("root", [0, 2])
    for lane, tol in ((1, 1e-5), (2, 0.0)):
        pair = samples.pair(lane, 0)
        both = ok[lane] & ok[0]
        vf, vb = values[lane][:, both], values[0][:, both]
        assert pair.n == both.sum()
        np.testing.assert_allclose(pair.mean_f, vf.mean(1), rtol=1e-13)
        np.testing.assert_allclose(pair.cov_ff, np.cov(vf), rtol=1e-9)
        np.testing.assert_allclose(pair.cov_dg, np.cov(vf - vb, vb)[:Q, Q:], rtol=1e-5, atol=1e-20)
        np.testing.assert_allclose(pair.cov_dd, np.cov(vf - vb), rtol=1e-5, atol=1e-30)
        gf, gb = value_and_gradient(stat, pair.mean_f)[1], value_and_gradient(stat, pair.mean_g)[1]
        # the t interval of the runs' differences of the linearised statistic
        d = gf @ (vf - vf.mean(1, keepdims=True)) - gb @ (vb - vb.mean(1, keepdims=True))
        want = t_quantile(0.95, both.sum() - 1) * d.std(ddof=1) / math.sqrt(both.sum())
        got = paired_half_width(gf, gb, pair.cov_dd, pair.cov_dg, pair.cov_gg, pair.n)
        if tol == 0.0:
            assert got == 0.0
        else:
            assert 0 < want < 1e-8 and got == pytest.approx(want, rel=tol)


def test_auto_runs_stop_once_the_target_is_met_and_equal_a_fixed_run(tmp_path):
    text = LINEAR.replace("runs = 20\nchunk = 20", 'runs = "auto"\ntarget_precision = 0.03\nmax_runs = 20000\nchunk = 50')
    exp = load_experiment(write(tmp_path, text))
    auto = exp.monte_carlo()
    n = auto.runs
    assert auto.auto == {"target": 0.03, "max_runs": 20000, "reached": True}
    assert 50 < n < 20000 and n % 50 == 0
    assert precision_reached(auto.samples, 0.03)
    fixed_before = load_experiment(write(tmp_path, LINEAR.replace("runs = 20\nchunk = 20", f"runs = {n - 50}\nchunk = 50"),
                                         "f.toml")).monte_carlo()
    assert not precision_reached(fixed_before.samples, 0.03)  # one chunk fewer was not enough
    fixed = load_experiment(write(tmp_path, LINEAR.replace("runs = 20\nchunk = 20", f"runs = {n}\nchunk = 50"),
                                  "g.toml")).monte_carlo()
    a, b = statistics(auto, exp.window), statistics(fixed, exp.window)
    assert a["filters"]["KF"]["summary"] == b["filters"]["KF"]["summary"]
    assert a["filters"]["KF"]["half_width"] == b["filters"]["KF"]["half_width"]
    for k, v in a["filters"]["KF"]["series"].items():
        np.testing.assert_array_equal(v, b["filters"]["KF"]["series"][k])
    rel = a["filters"]["KF"]["half_width"]["rmse_pos"] / a["filters"]["KF"]["summary"]["rmse_pos"]
    assert rel <= 0.03


def test_auto_runs_from_the_command_line(tmp_path, capsys):
    from tracklab.cli import main

    p = write(tmp_path, LINEAR.replace("chunk = 20", "chunk = 100"))
    assert main(["run", str(p), "--precision", "0.05", "--runs", "5000", "--no-figures", "--out", str(tmp_path / "o")]) == 0
    doc = read_results(tmp_path / "o")
    assert doc["auto"]["reached"] and doc["runs"] < 5000 and doc["runs"] % 100 == 0
    assert "Runs chosen automatically" in (tmp_path / "o" / "table.md").read_text()
    with pytest.raises(SystemExit) as e:
        main(["run", str(p), "--precision", "2"])
    assert e.value.code == 2
    assert "--precision" in capsys.readouterr().err


def test_percentiles_equal_numpy_on_each_runs_error():
    """evaluate() on recordings whose per-run errors are known: the runs' RMS position errors'
    percentiles equal NumPy's, and the distribution kept for the CDF runs from the least to the
    largest of them."""
    rng = np.random.default_rng(4)
    N, T = 37, 15
    truth = rng.normal(size=(N, T, 4)) * 10
    x = truth + rng.normal(size=(N, T, 4)) * rng.uniform(0.5, 3.0, size=(N, 1, 1))
    P = np.broadcast_to(np.eye(4) * 4.0, (N, T, 4, 4))
    res = tracklab.FilterResult(x=x, P=P, x_pred=None, nu=None, S=None, valid=None, dof=None)
    doc = tracklab.evaluate({"f": res}, truth, dt=1.0)
    e = x - truth
    per_run = np.sqrt(np.mean(e[..., 0] ** 2 + e[..., 2] ** 2, axis=1))
    s = doc["filters"]["f"]["summary"]
    np.testing.assert_allclose([s["err_pos_p50"], s["err_pos_p90"], s["err_pos_p99"]],
                               np.percentile(per_run, [50, 90, 99]), rtol=1e-12)
    cdf = doc["filters"]["f"]["cdf"]
    assert cdf["err_pos"][0] == pytest.approx(per_run.min()) and cdf["err_pos"][-1] == pytest.approx(per_run.max())
    # the RMSE interval is the delta-method t interval of these per-run values
    sq = per_run**2
    hw = t_quantile(0.95, N - 1) * sq.std(ddof=1) / math.sqrt(N) / (2 * math.sqrt(sq.mean()))
    assert s["rmse_pos"] == pytest.approx(math.sqrt(sq.mean()), rel=1e-12)
    assert doc["filters"]["f"]["half_width"]["rmse_pos"] == pytest.approx(hw, rel=1e-9)


AIRBORNE = studies.AIRBORNE.replace("runs = 4", "runs = 10") + '\n[[tracker]]\nlabel = "classical"\nkind = "classical"\n'
SERVO = studies.SERVO.replace("runs = 4", "runs = 10") + '\n[[case]]\nmode = "double_loop"\n'


def _t_half_width(v):
    return t_quantile(0.95, len(v) - 1) * np.std(v, ddof=1) / math.sqrt(len(v))


def test_closed_loop_intervals_equal_numpy_on_the_runs(tmp_path):
    """The closed loops' intervals, streamed over chunks (the last one padded), equal the t
    intervals NumPy computes from the runs' own values; the paired ones the t interval of the
    runs' differences (delta method for an RMS); the percentiles NumPy's."""
    exp = load_experiment(write(tmp_path, AIRBORNE, "a.toml"))
    out = exp.monte_carlo()
    doc = exp.document(out.sums, out.runs, out.wall_s, out.compile_s, "float64", out.samples)
    w = "acquisition"
    runs = {label: out.samples.kept(i, 0) for i, label in enumerate(("joint", "classical"))}  # RMS pointing (mrad)
    assert len(runs["joint"]) == len(runs["classical"]) == 10
    value = {}
    for label, r in runs.items():
        f = doc["filters"][label]
        sq = r**2
        value[label] = math.sqrt(sq.mean())
        assert f["summary"][f"pointing[{w}]"] == pytest.approx(value[label], rel=1e-9)
        assert f["half_width"][f"pointing[{w}]"] == pytest.approx(_t_half_width(sq) / (2 * value[label]), rel=1e-6)
        np.testing.assert_allclose([f["summary"][f"pointing_p{p}[{w}]"] for p in (50, 90, 99)],
                                   np.percentile(r, [50, 90, 99]), rtol=1e-12)
    d = runs["classical"] ** 2 / (2 * value["classical"]) - runs["joint"] ** 2 / (2 * value["joint"])
    paired = doc["filters"]["classical"]["paired"][f"pointing[{w}]"]
    assert paired["difference"] == pytest.approx(value["classical"] - value["joint"], rel=1e-9)
    assert paired["half_width"] == pytest.approx(_t_half_width(d), rel=1e-6)
    assert doc["filters"]["joint"]["paired"][f"pointing[{w}]"] == {"difference": 0.0, "half_width": 0.0,
                                                                   "significant": False}

    exp = load_experiment(write(tmp_path, SERVO, "s.toml"))
    doc = exp.simulate(exp.runs, exp.seed)
    from tracklab.montecarlo import runner
    from tracklab.worlds.servo.world import world

    out = runner.run(world(exp.structure()), exp.params(), exp.runs, exp.seed)
    kf, loop = (out.samples.kept(i, 0) for i in range(2))  # each run's maximum tracking error (′)
    for label, r in (("on_axis, KF", kf), ("double_loop", loop)):
        f = doc["filters"][label]
        assert f["summary"]["max_track_err"] == pytest.approx(r.mean(), rel=1e-9)
        assert f["half_width"]["max_track_err"] == pytest.approx(_t_half_width(r), rel=1e-6)
        np.testing.assert_allclose([f["summary"][f"max_track_err_p{p}"] for p in (50, 90, 99)],
                                   np.percentile(r, [50, 90, 99]), rtol=1e-12)
        assert f["intervals"]["diverged_fraction"] == [0.0, pytest.approx(wilson(0, 10)[1])]
    paired = doc["filters"]["double_loop"]["paired"]["max_track_err"]
    assert paired["difference"] == pytest.approx(loop.mean() - kf.mean(), rel=1e-9)
    assert paired["half_width"] == pytest.approx(_t_half_width(loop - kf), rel=1e-6)
    assert math.isnan(doc["filters"]["double_loop"]["summary"]["max_rate_err"])  # no estimator, no rate error


def test_auto_runs_on_a_closed_loop_stop_once_the_target_is_met(tmp_path):
    """runs = "auto" in a servo file: chunks run until every case's maximum-tracking-error interval
    is within the target; the result is a fixed run of that many runs, and one chunk fewer was
    not enough."""
    auto = load_experiment(write(tmp_path, SERVO.replace("runs = 10", 'runs = "auto"\ntarget_precision = 0.08\n'
                                                         "max_runs = 400"), "auto.toml"))
    doc = auto.simulate(auto.runs, auto.seed)
    n = doc["runs"]
    assert doc["auto"]["reached"] and doc["auto"]["max_runs"] == 400 and n < 400 and n % 4 == 0
    for f in doc["filters"].values():
        assert f["half_width"]["max_track_err"] <= 0.08 * f["summary"]["max_track_err"]
    fixed = load_experiment(write(tmp_path, SERVO.replace("runs = 10", f"runs = {n}"), "fixed.toml"))
    same = fixed.simulate(fixed.runs, fixed.seed)
    for label, f in doc["filters"].items():
        np.testing.assert_equal(f["summary"], same["filters"][label]["summary"])  # NaN: no rate estimate
        np.testing.assert_equal(f["half_width"], same["filters"][label]["half_width"])
    fewer = fixed.simulate(n - 4, fixed.seed)
    assert any(f["half_width"]["max_track_err"] > 0.08 * f["summary"]["max_track_err"]
               for f in fewer["filters"].values())


def test_a_value_and_its_half_width_are_shown_to_the_half_widths_two_digits():
    """Every place a value is shown with its interval (tables, legends, the servo figures' panel
    titles) writes the half-width to two significant digits and the value to the same decimal: a
    half-width below the column's last decimal is not shown as 0.000; one that is exactly zero (a
    deterministic case) is 0; a missing value is a dash."""
    from tracklab.report.servo import _run0_panels
    from tracklab.report.figures import pyplot
    from tracklab.intervals import with_half_width

    assert with_half_width(12.1946972, 0.009588753814, "{:.3f}") == "12.1947 ± 0.0096"
    assert with_half_width(0.3016276549, 0.00055) == "0.30163 ± 0.00055"
    assert with_half_width(-0.5, 0.25, sign=True) == "-0.50 ± 0.25"
    assert with_half_width(0.02838605798, 0.0, "{:.3f}") == "0.028 ± 0"
    assert with_half_width(0.5, None, "{:.3f}") == "0.500"
    assert with_half_width(float("nan"), 0.1) == "—"
    doc = {"filters": {"a": {"summary": {"e": 0.02838605798}, "half_width": {"e": 0.0}},
                       "b": {"summary": {"e": 2.820456407}, "half_width": {"e": 0.0004}}}}
    t = np.linspace(0.0, 1.0, 11)
    plt = pyplot()
    fig = _run0_panels(plt, doc, {"a": np.sin(t), "b": np.cos(t)}, t, 0.5, "error", "e", "′", shared_scale=False)
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    plt.close(fig)
    assert titles[0].endswith("mean over the runs 0.028 ± 0 ′")
    assert titles[1].endswith("mean over the runs 2.82046 ± 0.00040 ′")


def test_a_percentage_is_shown_plainly_and_a_fraction_below_one_never_as_100():
    """A fraction as a percentage: two significant digits, no exponent; 0 and 100 only for exactly
    0 and 1 (the Wilson interval of the diverged runs reaches 100 % only when all diverged); the
    diverged cell, the NEES-in-band column and the combined table use it."""
    from tracklab.intervals import format_value, percent
    from tracklab.report.tables import diverged_cell
    from tracklab.reproduce import _cell

    assert [percent(v) for v in (0, 1e-4, 0.0012, 0.12, 0.5, 1)] == ["0 %", "0.01 %", "0.12 %", "12 %", "50 %", "100 %"]
    assert [percent(v) for v in (0.99, 0.995, 0.9997, 1 - 1e-6)] == ["99 %", "99.5 %", "99.97 %", "99.9999 %"]
    for v in (1 - 1e-3, 1 - 1e-7, 1 - 1e-12, 0.99999, np.float64(0.9999)):
        assert float(percent(v, sign=False)) < 100, v
    for v in (1e-3, 1e-7, 1e-12):
        assert 0 < float(percent(v, sign=False)), v
    assert percent(None) == percent(float("nan")) == "—" and percent(0.5, sign=False) == "50"
    assert not any("e" in percent(10.0 ** -k) for k in range(12))
    wilson_all = {"summary": {"diverged": 8}, "intervals": {"diverged_fraction": list(wilson(8, 8))}}
    assert diverged_cell(wilson_all) == "8 (68–100 %)"
    assert diverged_cell({"summary": {"diverged": 0}, "intervals": {"diverged_fraction": [0.0, 0.0012]}}) == "0 (0–0.12 %)"
    assert format_value(0.996, "{:.0%}") == "99.6" and _cell(1.0, "{:.0%}") == "100 %"
