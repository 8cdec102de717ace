"""One-step prediction error: the engine's windowed statistics against the same runs
filtered one by one, and the mount frame's angles and rates against finite differences."""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np

import tracklab
from tracklab.config import load_experiment
from tracklab.worlds.tracking.scan import simulate_runs
from tracklab.montecarlo.statistics import statistics
from tracklab.scenarios import MountFrame, Overflight

EXPERIMENT = """
[experiment]
name = "pred"
runs = 37
seed = 5
dt = 0.04
steps = 400

[scenario]
kind = "overflight"
t_closest = 8.0
altitude = 3000.0

[sensor]
kind = "mount"
sigma_az = 0.02
sigma_el = 0.03

[prior]
pos_sigma = 0.05
vel_sigma = 0.5
acc_sigma = 0.1

[[filter]]
kind = "kf"
label = "KF"
model = "ca"
q = 2e-6

[[filter]]
kind = "error_space"
label = "ES"
model = "ca"
q = 2e-6

[report]
window = [10, 400]
[report.windows]
"6-10 s" = [6.0, 10.0]
elsewhere = "rest"
"""


def test_windowed_prediction_errors_equal_those_of_the_runs_filtered_one_by_one(tmp_path):
    path = tmp_path / "pred.toml"
    path.write_text(textwrap.dedent(EXPERIMENT))
    exp = load_experiment(path)
    st = statistics(exp.monte_carlo(chunk=16), exp.window, exp.pred_windows)

    # the same runs: the engine's keys, truth, measurements and priors
    runs, T = exp.runs, exp.steps
    idx = jnp.arange(runs, dtype=jnp.uint32)
    P0 = exp.prior_covariance()
    truth, z, prior = simulate_runs(exp.scenario, exp.sensor, P0,
                                    jax.random.key(exp.seed), idx)
    t = exp.dt * np.arange(1, T + 1)
    masks = {"": (np.arange(1, T + 1) >= 10), "[6-10 s]": (t >= 6.0 - 1e-9) & (t <= 10.0 + 1e-9)}
    masks["[elsewhere]"] = masks[""] & ~masks["[6-10 s]"]
    for spec in exp.filter_specs():
        x0, P0s = spec.layout.embed(prior, jnp.asarray(P0), exp.prior["acc_sigma"] ** 2)
        out = tracklab.run_filter(spec.filter, z, x0=x0, P0=P0s, dt=exp.dt)
        err = np.asarray(out.x_pred[..., [0, 3]] - truth[:, 1:, 0::2])  # (runs, T, 2): az, el
        norm = np.linalg.norm(err, axis=-1)
        summary = st["filters"][spec.label]["summary"]
        for name, m in masks.items():
            np.testing.assert_allclose(summary[f"pred_err_rms{name}"], np.sqrt(np.mean(norm[:, m] ** 2)), rtol=1e-10)
            np.testing.assert_allclose(summary[f"pred_err_max{name}"], np.mean(norm[:, m].max(axis=1)), rtol=1e-10)
            np.testing.assert_allclose(summary[f"pred_err_max_az{name}"], np.mean(np.abs(err[:, m, 0]).max(axis=1)),
                                       rtol=1e-10)
            np.testing.assert_allclose(summary[f"pred_err_rms_el{name}"], np.sqrt(np.mean(err[:, m, 1] ** 2)), rtol=1e-10)
        series = st["filters"][spec.label]["series"]
        np.testing.assert_allclose(series["pred_rmse_az"], np.sqrt(np.mean(err[..., 0] ** 2, axis=0)), rtol=1e-10)


def test_mount_frame_angles_and_rates():
    """az = atan2(x, y) clockwise from north, el above the horizon; rates = finite differences."""
    dt = 0.01
    sc = MountFrame(Overflight(dt=dt, steps=3000, altitude=1000.0, speed=200.0, max_elevation=80.0, t_closest=15.0,
                               heading=30.0))
    a = np.asarray(sc.simulate(jax.random.key(0)))
    cart = np.asarray(sc.scenario.simulate(jax.random.key(0)))
    x, y, zz = cart[:, 0], cart[:, 2], cart[:, 4]
    np.testing.assert_allclose(np.radians(a[:, 2]), np.arctan2(zz, np.hypot(x, y)), atol=1e-12)
    np.testing.assert_allclose(np.radians(a[:, 0]), np.unwrap(np.arctan2(x, y)), atol=1e-12)
    assert abs(a[:, 2].max() - 80.0) < 1e-3 and abs(dt * np.argmax(a[:, 2]) - 15.0) < dt
    fd = (a[2:, [0, 2]] - a[:-2, [0, 2]]) / (2 * dt)
    np.testing.assert_allclose(a[1:-1, [1, 3]], fd, rtol=1e-3, atol=1e-6 * np.abs(a[:, 1]).max())
