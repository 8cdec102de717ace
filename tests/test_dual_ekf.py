"""Dual EKF (paper 003): against a NumPy implementation of the same equations, and its gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tracklab
from tracklab.filters.dual_ekf import Network, dekf_params, dual_ekf

SCALE = (80.0, 50.0, 30.0)


def numpy_dekf(z, x0, P0, p, hidden, scale, dt, residual):
    """Eqs. (6)-(15) as read in tracklab.filters.dual_ekf, with hand-written Jacobians."""
    s = np.asarray(scale)
    k = hidden
    Phi = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    G = np.array([dt**2 / 2, dt, 1.0])
    x, P = np.array(x0, float), np.array(P0, float)
    w = np.array(p["w0"], float)
    Pw = float(p["pw0"]) * np.eye(len(w))
    C = np.array([[1.0, 0.0, 0.0]])
    xs, ws = [], []
    for zk in z:
        W1, b1 = w[: 3 * k].reshape(k, 3), w[3 * k: 4 * k]
        W2, b2 = w[4 * k: 7 * k].reshape(3, k), w[7 * k: 7 * k + 3]
        u = x / s
        h = np.tanh(W1 @ u + b1)
        so = s * dt if residual else s  # the network's output scale: a correction per step, or the state
        F = so * (W2 @ h + b2) + (Phi @ x if residual else 0.0)
        dh = 1.0 - h**2
        A = (so[:, None] * W2) @ (dh[:, None] * W1 / s[None, :]) + (Phi if residual else 0.0)
        # ∂F/∂w, block by block
        dW1 = np.einsum("ij,j,l->ijl", so[:, None] * W2, dh, u).reshape(3, 3 * k)  # ∂F_i/∂W1[j, l]
        db1 = (so[:, None] * W2) * dh[None, :]
        dW2 = np.einsum("i,j->ij", so, h)  # ∂F_i/∂W2[i, j]
        dW2_full = np.zeros((3, 3 * k))
        for i in range(3):
            dW2_full[i, i * k:(i + 1) * k] = dW2[i]
        db2 = np.diag(so)
        Jw = np.hstack([dW1, db1, dW2_full, db2])
        Pw_pred = Pw / float(p["forget"])
        Pp = A @ P @ A.T + float(p["q"]) * np.outer(G, G)
        if np.isfinite(zk[0]):
            nu = zk[0] - F[0]
            S = (C @ Pp @ C.T)[0, 0] + float(p["r"])
            K = (Pp @ C.T)[:, 0] / S
            x = F + K * nu
            P = (np.eye(3) - np.outer(K, C)) @ Pp
            Cw = (C @ Jw)[0]
            Sw = Cw @ Pw_pred @ Cw + float(p["r_e"])
            Kw = Pw_pred @ Cw / Sw
            w = w + Kw * nu
            Pw = (np.eye(len(w)) - np.outer(Kw, Cw)) @ Pw_pred
        else:
            x, P, Pw = F, Pp, Pw_pred
        xs.append(x)
        ws.append(w)
    return np.array(xs), np.array(ws)


def _sine(T=400, dt=0.01, seed=0, sigma=10 / 3600):
    t = dt * np.arange(1, T + 1)
    theta = 83.33 * np.sin(0.6 * t)
    rng = np.random.default_rng(seed)
    return t, theta, (theta + sigma * rng.normal(size=T))[:, None]


@pytest.mark.parametrize("residual", [False, True], ids=["literal", "residual"])
def test_dual_ekf_matches_numpy(residual):
    net = Network(hidden=4, scale=SCALE, dt=0.01, residual=residual)
    p = dekf_params(net, q=1e-2, r=(10 / 3600) ** 2, lam=0.995, r_e=0.5, pw0=1e-3, key=jax.random.key(1))
    t, theta, z = _sine()
    z[[30, 31, 200]] = np.nan
    x0 = np.array([0.0, 50.0, 0.0])
    P0 = np.diag([1e-4, 1.0, 1.0])
    got = tracklab.run_filter(dual_ekf(net, p), z, x0=x0, P0=P0, dt=0.01)
    xs, ws = numpy_dekf(z, x0, P0, {k: np.asarray(v) for k, v in p.items()}, 4, SCALE, 0.01, residual)
    assert np.abs(ws[-1] - np.asarray(p["w0"])).max() > 1e-6  # the weights did adapt
    np.testing.assert_allclose(got.x, xs, rtol=1e-8, atol=1e-8 * np.abs(xs).max())
    np.testing.assert_allclose(got.aux["weights"], ws, rtol=1e-8, atol=1e-8 * np.abs(ws).max())


@pytest.mark.parametrize("name", ["forget", "w0"])
def test_gradient_through_the_dual_ekf_matches_finite_differences(name):
    """d(mean squared rate error)/d(λ or the initial weights) through a whole run."""
    net = Network(hidden=4, scale=SCALE, dt=0.01, residual=True)
    p = dekf_params(net, q=1e-2, r=(10 / 3600) ** 2, lam=0.99, pw0=1e-3, key=jax.random.key(2))
    t, theta, z = _sine(T=200)
    rate = 83.33 * 0.6 * np.cos(0.6 * t)
    x0 = np.array([0.0, 50.0, 0.0])
    P0 = np.diag([1e-4, 1.0, 1.0])
    flt = dual_ekf(net, p)

    def loss(v):
        out = tracklab.run_filter(flt, z, x0=x0, P0=P0, params=dict(p, **{name: v}), dt=0.01)
        return jnp.mean((out.x[:, 1] - rate) ** 2)

    v0 = jnp.asarray(p[name])
    g = np.asarray(jax.grad(loss)(v0))
    rng = np.random.default_rng(0)
    direction = rng.normal(size=np.shape(v0))
    direction = direction / np.linalg.norm(direction) if direction.ndim else np.asarray(1.0)
    eps = 1e-6
    fd = (float(loss(v0 + eps * direction)) - float(loss(v0 - eps * direction))) / (2 * eps)
    analytic = float(np.sum(g * direction))
    assert abs(analytic) > 0
    np.testing.assert_allclose(analytic, fd, rtol=1e-4)


def test_dekf_as_an_experiment_filter_on_the_sine_target(tmp_path):
    """kind = "dekf" in an experiment file (1-D sine truth, angle measurements): runs beside a CA KF."""
    from tracklab.config import load_experiment
    from tracklab.montecarlo.statistics import statistics

    (tmp_path / "d.toml").write_text("""
[experiment]
name = "dekf"
runs = 16
dt = 0.01
steps = 1500

[scenario]
kind = "sine"
amplitude = 83.33
omega = 0.6

[sensor]
kind = "cartesian"
sigma = 0.002777777777777778   # 10 arcsec

[prior]
pos_sigma = 0.01
vel_sigma = 1.0
acc_sigma = 1.0

[[filter]]
kind = "kf"
label = "KF"
model = "ca"
q = 1.0

[[filter]]
kind = "dekf"
label = "DEKF"
q = 1.0
forget = 0.999
scale = [80.0, 50.0, 30.0]

[report]
window = [500, 1500]
""")
    exp = load_experiment(tmp_path / "d.toml")
    assert exp.filters[1].params["forget"] == 0.999 and len(exp.filters[1].params["w0"]) == 31
    st = statistics(exp.monte_carlo(), exp.window)["filters"]
    assert st["DEKF"]["summary"]["diverged"] == 0
    assert st["DEKF"]["summary"]["rmse_vel"] < 1.5 * st["KF"]["summary"]["rmse_vel"]
