"""Paper 003's servo: the discretised loops against the continuous transfer functions."""

import jax
import numpy as np
import pytest
from jax.scipy.linalg import expm

from tracklab.worlds.servo import AzimuthAxis, TransferFunction, closed_position_loop, discretise, sine_target, track
from tracklab.report.document import read_results

AXIS = AzimuthAxis()
L = AXIS.open_position_loop()
CLOSED = L.feedback()  # θ / θ_ref of the position loop, continuous


def test_transfer_function_algebra_and_discretisation():
    g = TransferFunction.lead_lag(2.0, (0.5,), (0.1, 0.2))
    s = 1j * np.array([0.3, 3.0, 30.0])
    np.testing.assert_allclose(g(s), 2.0 * (0.5 * s + 1) / ((0.1 * s + 1) * (0.2 * s + 1)), rtol=1e-12)
    np.testing.assert_allclose(g.feedback()(s), g(s) / (1 + g(s)), rtol=1e-12)
    A, B, C, D = g.state_space()
    np.testing.assert_allclose([(C @ np.linalg.solve(si * np.eye(2) - A, B))[0, 0] + D[0, 0] for si in s], g(s), rtol=1e-12)
    # Tustin: H(e^{jωT}) = G(j (2/T) tan(ωT/2)) exactly
    T = 1e-3
    w = np.array([1.0, 50.0, 500.0])
    np.testing.assert_allclose(discretise(g, T, "bilinear").response(w), g(1j * 2 / T * np.tan(w * T / 2)), rtol=1e-9)


@pytest.mark.parametrize("w", [0.6, 5.0, 19.0, 35.0, 50.0])
def test_closed_position_loop_frequency_response_matches_the_continuous_one(w):
    """Sine in, the steady-state sine out: within 1 % (complex) of L/(1 + L) below 50 rad/s."""
    T = AXIS.dt
    periods = max(8, int(np.ceil(8 * w / (2 * np.pi) * 2)))
    n = int(np.ceil((periods * 2 * np.pi / w + 15.0) / T))  # 15 s for the slow lags to die out
    t = T * np.arange(n)
    y = np.asarray(closed_position_loop(AXIS, np.sin(w * t)))
    last = t > t[-1] - 4 * 2 * np.pi / w
    basis = np.stack([np.sin(w * t[last]), np.cos(w * t[last]), np.ones(last.sum())], -1)
    a, b, _ = np.linalg.lstsq(basis, y[last], rcond=None)[0]
    got = a + 1j * b  # θ read at tick i against the reference at tick i
    want = CLOSED(1j * w)
    assert abs(got - want) / abs(want) < 0.01, (w, got, want)


def _continuous_position_loop():
    """(A, B, C) of the continuous closed position loop, built from the blocks (well scaled)."""
    Av, Bv, Cv, _ = AXIS.velocity_subsystem()
    Ap, Bp, Cp, Dp = AXIS.position_corrector.state_space()
    nv, n_p = Av.shape[0], Ap.shape[0]
    theta = Cv[1:2]  # θ = theta @ x_v
    A = np.zeros((nv + n_p, nv + n_p))
    A[:nv, :nv] = Av - Bv @ Dp @ theta  # v = C_p x_p + D_p (r − θ)
    A[:nv, nv:] = Bv @ Cp
    A[nv:, :nv] = -Bp @ theta
    A[nv:, nv:] = Ap
    B = np.vstack([Bv @ Dp, Bp])
    C = np.hstack([theta, np.zeros((1, n_p))])
    return A, B, C


def test_closed_position_loop_step_response_matches_the_continuous_one():
    """Unit step: the continuous response, exact at the ticks (a held input), within 1 % of the final value."""
    T = AXIS.dt
    n = 3000
    y = np.asarray(closed_position_loop(AXIS, np.ones(n)))
    A, B, C = _continuous_position_loop()
    k = A.shape[0]
    M = np.zeros((k + 1, k + 1))
    M[:k, :k], M[:k, k:] = A, B
    E = np.asarray(expm(M * T))
    Ad, Bd = E[:k, :k], E[:k, k:]
    x, exact = np.zeros((k, 1)), []
    for _ in range(n):
        exact.append((C @ x)[0, 0])
        x = Ad @ x + Bd
    exact = np.array(exact)
    np.testing.assert_allclose(CLOSED(1e-9), 1.0, rtol=1e-6)
    assert np.max(np.abs(y - exact)) < 0.01, np.max(np.abs(y - exact))
    assert exact.max() > 1.1  # an overshoot worth matching


def test_double_loop_error_on_the_sine_target_is_the_closed_loops():
    """83.33° sin 0.6t: max error = A/|1 + L(j0.6)| ≈ 12′, whatever estimator runs beside the loop."""
    target = sine_target(83.33, 0.6)
    analytic = 83.33 * 60 / abs(1 + L(0.6j))
    plain = track(AXIS, "double_loop", target, 3000, jax.random.key(0))
    with_perfect = track(AXIS, "double_loop", target, 3000, jax.random.key(0), perfect=True)
    late = np.asarray(plain["t"]) > 15.0
    got = 60 * np.abs(np.asarray(plain["error"])[late]).max()
    assert abs(analytic - 12.0) < 0.1 and abs(got / analytic - 1) < 0.01
    np.testing.assert_array_equal(plain["error"], with_perfect["error"])


def test_perfect_feed_forward_collapses_the_on_axis_error():
    """Exact rate fed forward: the error is (1 − Φ_v)/(1 + L)·θ, 1.7″ instead of 12′; adding the
    acceleration times the velocity loop's lag d(1/Φ_v)/ds at 0 takes it below an arc-second."""
    target = sine_target(83.33, 0.6)
    phi_v = (AXIS.velocity_corrector * AXIS.plant).feedback()
    analytic = 83.33 * 3600 * abs((1 - phi_v(0.6j)) / (1 + L(0.6j)))
    rate = track(AXIS, "on_axis", target, 3000, jax.random.key(0), perfect=True)
    late = np.asarray(rate["t"]) > 15.0
    got = 3600 * np.abs(np.asarray(rate["error"])[late]).max()
    assert abs(got / analytic - 1) < 0.02 and got < 2.0
    eps = 1e-6
    lag = ((1 / phi_v(eps) - 1 / phi_v(-eps)) / (2 * eps)).real
    both = track(AXIS, "on_axis", target, 3000, jax.random.key(0), perfect=True, accel_ff=lag)
    assert 3600 * np.abs(np.asarray(both["error"])[late]).max() < 1.0


def test_servo_experiment_file_runs_and_reports_the_paper_metrics(tmp_path):
    """A [servo] experiment: one table row per case; the perfect estimator bounds the on-axis error."""
    import subprocess
    import sys

    (tmp_path / "s.toml").write_text("""
[experiment]
name = "servo"
runs = 3
chunk = 3

[servo]
frames = 1200
noise = 10.0
settle = 6.0

[target]
kind = "cone"                # the dynamic-target rig: 13.5 deg cone about an axis at 26 deg, 4.5 s

[[estimator]]
label = "KF"
kind = "kf"
q = 1.0

[[case]]
mode = "double_loop"

[[case]]
mode = "on_axis"
estimator = "KF"

[[case]]
mode = "on_axis"
estimator = "perfect"
""")
    proc = subprocess.run([sys.executable, "-m", "tracklab.cli", "run", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    doc = read_results(tmp_path / "out")
    s = {k: v["summary"] for k, v in doc["filters"].items()}
    assert s["on_axis, perfect"]["max_track_err"] < s["on_axis, KF"]["max_track_err"] < s["double_loop"]["max_track_err"]
    assert 0 < s["on_axis, KF"]["max_rate_err"] < 2.0
    assert (tmp_path / "out" / "tracking_error.png").exists() and (tmp_path / "out" / "rate_error.png").exists()
    assert "max tracking error (′)" in proc.stdout


def test_cone_target_rates():
    """The rig's azimuth: rates from autodiff agree with finite differences; peak rate and acceleration
    near the paper's 24.2 °/s and 30.7 °/s²."""
    from tracklab.worlds.servo.world import cone_target

    f = jax.jit(jax.vmap(cone_target(13.5, 26.0, 4.5)))
    t = np.linspace(0, 4.5, 4501)
    v = np.asarray(f(t))[::10]
    fd = np.gradient(np.asarray(f(t))[:, 0], t)[::10]
    np.testing.assert_allclose(v[5:-5, 1], fd[5:-5], atol=0.05)
    assert 20.0 < np.abs(v[:, 1]).max() < 28.0 and 25.0 < np.abs(v[:, 2]).max() < 36.0


def test_servo_experiment_in_float32_agrees_with_float64(tmp_path):
    """precision = "float32": the experiment traced in single precision. Its noise draws differ from the
    float64 ones (JAX draws normals from 32 or 64 random bits), so the runs are other realisations:
    the arc-minute maximum errors agree within 2 %, the arc-second random error (0.02″ is float32's
    resolution at 83°) within 5 % over 16 runs."""
    from tracklab.config import load_experiment

    (tmp_path / "s.toml").write_text("""
[experiment]
name = "servo32"
runs = 16
precision = "float32"

[servo]
frames = 1000
settle = 5.0

[target]
kind = "cone"

[[estimator]]
label = "KF"
kind = "kf"

[[case]]
mode = "double_loop"

[[case]]
mode = "on_axis"
estimator = "KF"
""")
    exp = load_experiment(tmp_path / "s.toml")
    single = exp.run(out=tmp_path / "f32", figures=False)
    double = exp.run(out=tmp_path / "f64", figures=False, precision="float64")
    assert single["precision"] == "float32" and double["precision"] == "float64"
    for label in ("double_loop", "on_axis, KF"):
        a, b = double["filters"][label]["summary"], single["filters"][label]["summary"]
        assert b["max_track_err"] == pytest.approx(a["max_track_err"], rel=0.02)
        assert b["random_err"] == pytest.approx(a["random_err"], rel=0.05)


def test_a_dekf_trained_first_is_announced_and_its_training_timed(tmp_path, monkeypatch, capsys):
    """A DEKF with ``train_steps`` is trained before the runs: the command says so on stderr before
    anything runs (minutes on a real file, with no run finished to report) and prints the training's
    steps, seconds and held-out loss after the runs' line, whose wall time is the runs' alone;
    stats.json keeps them."""
    from test_cli import in_process

    (tmp_path / "s.toml").write_text("""
[experiment]
name = "servo_trained"
runs = 2

[servo]
frames = 300
settle = 1.5

[target]
kind = "cone"

[[estimator]]
label = "DEKF"
kind = "dekf"
hidden = 2
train_steps = 3
train_runs = 2

[[case]]
mode = "on_axis"
estimator = "DEKF"
""")
    proc = in_process("run", tmp_path / "s.toml", "--no-figures", "--out", tmp_path / "out", cwd=tmp_path,
                      monkeypatch=monkeypatch, capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.startswith("servo_trained: DEKF: training w0 and λ first (3 Adam steps of 2 runs each)\n")
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("# servo_trained: 2 runs x 300 steps") and lines[1].startswith(
        "# DEKF: trained first, 3 Adam steps in ")
    info = read_results(tmp_path / "out")["training"]["DEKF"]
    assert info["steps"] == 3 and len(info["loss_history"]) == 3 and info["wall_s"] > 0
    assert f"held-out loss {info['heldout_before']:.4g} -> {info['heldout_after']:.4g}" in lines[1]
