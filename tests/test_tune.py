"""Differentiable tuning: gradients through the Monte-Carlo simulation, and what tuning finds."""

import json
import subprocess
import sys
import textwrap
import tomllib

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

from tracklab.config import load_experiment
from tracklab.filters import kalata_alpha_beta
from tracklab.studies.tune import FORWARD_UP_TO, gradient, numbers, objective, tune, tuned_numbers

from test_cli import in_process

GRAD = """
[experiment]
name = "grad"
runs = 64
dt = 1.0
steps = 40

[scenario]
kind = "constant_velocity"
initial = [10.0, 88.0, 0.0, -20.0]
accel_sigma = 3.0

[sensor]
kind = "cartesian"
sigma = [100.0, 50.0]

[[filter]]
kind = "kf"
label = "KF"
accel_sigma = 2.0
sigma = [80.0, 70.0]

[[filter]]
kind = "alpha_beta"
label = "explicit"
alpha = 0.3
beta = 0.05
accel_sigma = 3.0

[[filter]]
kind = "alpha_beta"
label = "kalata"
accel_sigma = 3.0

[report]
window = [5, 40]
"""


def write(tmp_path, text, name="exp.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


@pytest.mark.parametrize("names,loss", [(["q", "r"], "mse_pos"), (["q", "r"], "nll"), (["q", "r"], "pred_mse"),
                                        (["alpha", "beta"], "mse_pos"), (["lam"], "mse_pos")])
def test_gradient_matches_central_differences(tmp_path, names, loss):
    """d(loss)/d(theta) by autodiff through simulate -> filter -> statistics equals central differences,
    in the mode tune takes for the selection (forward for alpha, beta and lam, reverse for q, r).
    For q, r with the nll loss, the forward-mode gradient too (as if the selection were one number)
    equals the reverse-mode one: the loss, each filter's term and every component, on three filters
    of three kinds."""
    exp = load_experiment(write(tmp_path, GRAD))
    obj = objective(exp, names, loss)
    key, idx, live = jax.random.key(0), jnp.arange(64, dtype=jnp.uint32), jnp.ones(64, bool)

    def total(*a):
        per = obj.losses(*a)
        return sum(per.values()), per

    n = numbers(obj.theta0)
    assert tuned_numbers(exp, obj.chosen) == n  # as the memory check counts them, before tracing
    value_and_grad = jax.jit(gradient(total, n))
    f = lambda *a: value_and_grad(*a)[0][0]  # the loss, from the same program (one compile, not two)
    (value, per), grad = value_and_grad(obj.theta0, key, idx, live)
    g, _ = jax.flatten_util.ravel_pytree(grad)
    flat, unravel = jax.flatten_util.ravel_pytree(obj.theta0)
    checked = 0
    for i in range(len(flat)):
        e = jnp.zeros_like(flat).at[i].set(1e-5)
        fd = (f(unravel(flat + e), key, idx, live) - f(unravel(flat - e), key, idx, live)) / 2e-5
        if abs(float(fd)) < 1e-8 and abs(float(g[i])) < 1e-8:
            continue  # a parameter this loss does not depend on (an alpha-beta filter's q in its MSE)
        np.testing.assert_allclose(float(g[i]), float(fd), rtol=1e-4)
        checked += 1
    assert checked >= 1
    if loss != "nll":
        return
    assert n > FORWARD_UP_TO  # this selection alone takes reverse mode
    (v_fwd, per_fwd), g_fwd = jax.jit(gradient(total, 1))(obj.theta0, key, idx, live)  # forward mode
    np.testing.assert_allclose(float(v_fwd), float(value), rtol=1e-12)
    assert per.keys() == per_fwd.keys() == {"KF", "explicit", "kalata"}
    for l in per:
        np.testing.assert_allclose(float(per_fwd[l]), float(per[l]), rtol=1e-12)
    flat_fwd, _ = jax.flatten_util.ravel_pytree(g_fwd)
    assert flat_fwd.shape == g.shape == (n,) and np.all(np.abs(g) > 0)
    np.testing.assert_allclose(np.asarray(flat_fwd), np.asarray(g), rtol=1e-9)


AB = """
[experiment]
name = "ab"
runs = 512
dt = 1.0
steps = 120

[scenario]
kind = "constant_velocity"
initial = [0.0, 10.0]
accel_sigma = 10.0

[sensor]
kind = "cartesian"
sigma = 10.0

[prior]
pos_sigma = 10.0
vel_sigma = 10.0

[[filter]]
kind = "alpha_beta"
label = "ab"
alpha = ALPHA
beta = BETA
accel_sigma = 10.0

[report]
window = [40, 120]
"""


def test_tuned_alpha_beta_gains_reach_the_kalata_optimum(tmp_path):
    """From gains 3x off, Adam on the position MSE lands on Kalata's gains for the true λ (= 1 here)."""
    a, b = (float(v) for v in kalata_alpha_beta(1.0))
    exp = load_experiment(write(tmp_path, AB.replace("ALPHA", str(a / 3)).replace("BETA", str(b * 3))))
    res = tune(exp, ["alpha", "beta"], steps=150, lr=0.1, runs_per_step=512)
    got = res.params["ab"]
    assert abs(got["alpha"] / a - 1) < 0.02, (got, a, b)
    assert abs(got["beta"] / b - 1) < 0.02, (got, a, b)
    assert res.eval_tuned["ab"] < res.eval_initial["ab"]


QR = """
[experiment]
name = "qr"
runs = 256
dt = 1.0
steps = 100

[scenario]
kind = "constant_velocity"
initial = [0.0, 10.0, 0.0, -5.0]
accel_sigma = 3.0

[sensor]
kind = "cartesian"
sigma = 20.0

[prior]
pos_sigma = 20.0
vel_sigma = 5.0

[[filter]]
kind = "kf"
label = "KF"
accel_sigma = 1.0
sigma = 60.0
"""


def test_tuned_kf_recovers_true_noise_from_innovations(tmp_path):
    """Q 9x too small and R 9x too large: the innovation likelihood (no truth needed) recovers both within 10 %."""
    exp = load_experiment(write(tmp_path, QR))
    res = tune(exp, ["q", "r"], steps=120, lr=0.1, loss="nll", runs_per_step=256)
    got = res.params["KF"]
    assert abs(got["q"] / 9.0 - 1) < 0.10, got
    assert np.all(np.abs(np.asarray(got["r"]) / 400.0 - 1) < 0.10), got


_COMPILES = """
import json, logging, sys
import tracklab
tracklab.configure()  # the device count from XLA_FLAGS
import jax
from tracklab.config import load_experiment
from tracklab.studies.tune import tune

class Compiles(logging.Handler):
    def __init__(self):
        super().__init__()
        self.names = []
    def emit(self, record):
        msg = record.getMessage()
        if msg.startswith("Compiling jit("):
            self.names.append(msg[len("Compiling jit("):].split(")")[0])

seen = Compiles()
logging.getLogger("jax").addHandler(seen)
with jax.log_compiles():
    res = tune(load_experiment(sys.argv[1]), ["q", "r"], steps=3, lr=0.1, loss="nll", runs_per_step=16, eval_runs=16)
print(json.dumps({"devices": jax.device_count(), "steps": len(res.history), "compiled": seen.names}))
"""


def test_tune_compiles_its_gradient_and_its_evaluation_once(tmp_path, xla_flags):
    """On two devices, every step's parameters find the gradient program the first step compiled
    (an update made of the program's outputs is placed on the devices, where they were, and
    would compile it again), and the held-out evaluation after tuning finds the one before it."""
    import os

    script = tmp_path / "compiles.py"
    script.write_text(_COMPILES)
    env = dict(os.environ, XLA_FLAGS=xla_flags(2))
    done = subprocess.run([sys.executable, str(script), str(write(tmp_path, QR))], env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    doc = json.loads(done.stdout.strip().splitlines()[-1])
    assert doc["devices"] == 2 and doc["steps"] == 3
    assert doc["compiled"].count("total") == 1, doc  # the loss and its gradient
    assert doc["compiled"].count("per_lane") == 1, doc  # the held-out losses, before and after


def test_cli_tune_writes_an_experiment_that_runs(tmp_path, monkeypatch, capsys):
    """The command's main in this process (its own process: test_cli, test_processes)."""
    src = write(tmp_path, QR)
    out = tmp_path / "tuned.toml"
    proc = in_process("tune", src, "--params", "q,r", "--steps", 30, "--lr", 0.1, "--loss", "nll", "--out", out,
                      cwd=tmp_path, monkeypatch=monkeypatch, capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    assert "step" in proc.stdout and "KF: held-out nll" in proc.stdout
    report = tmp_path / "results" / "qr_tune"  # the tuning's results folder, by default under results/
    doc = json.loads((report / "tune.json").read_text())
    assert doc["heldout"]["KF"]["after"] < doc["heldout"]["KF"]["before"]
    assert len(doc["history"]["loss"]["KF"]) == 30 and doc["wall_s"] > 0
    assert (report / "loss.png").exists() and "| KF | q |" in (report / "table.md").read_text()
    assert not (tmp_path / "qr_tuned.toml").exists() and not list(tmp_path.glob("*_tuned.toml"))
    doc = tomllib.loads(out.read_text())
    f = doc["filter"][0]
    assert f["accel_sigma"] > 1.0 and all(s < 60.0 for s in f["sigma"])  # moved towards the truth (3, 20)
    exp = load_experiment(out)  # a valid experiment file
    assert exp.name == "qr_tuned"
    run = in_process("run", out, "--runs", 20, "--no-figures", "--out", tmp_path / "res", cwd=tmp_path,
                     monkeypatch=monkeypatch, capsys=capsys)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "res" / "stats.json").exists()


@pytest.mark.parametrize("args,field", [(("--params", "zeta"), "--params"), (("--params", "q", "--loss", "l1"), "--loss"),
                                        (("--params", "alpha"), "--params")])
def test_cli_tune_refuses_bad_requests(tmp_path, monkeypatch, capsys, args, field):
    src = write(tmp_path, QR)
    proc = in_process("tune", src, *args, "--steps", 2, cwd=tmp_path, monkeypatch=monkeypatch, capsys=capsys)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and field in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.toml"]  # nothing written
