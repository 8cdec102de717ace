"""End-to-end training of the dual EKF: initial weights and forgetting factor by optax.

The estimator of a servo experiment sees the measured target angle
θ_m = Δθ + θ_encoder = θ_target(t_exposure) + noise (paper 003 eq. 16), whatever
the loop does, so it can be trained on its own: a batch of Monte-Carlo runs of
noisy measurements at the camera rate, the whole DEKF scan over each, and the
loss the mean squared error of the rate it predicts ``delay`` frames ahead
(eq. 17) — the feed-forward the on-axis loop receives — after ``settle``.
Adam (gradients clipped to norm 1) on (w₀, logit λ); a fresh batch every step;
evaluation on held-out runs.
The paper adapts the weights online only; this trains where they start from.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

from tracklab.filters.core import Meas
from tracklab.filters.dual_ekf import dual_ekf, predict_ahead


def rate_loss_fn(net, base_params, target, prior, frames, frame_dt, delay, sigma, settle):
    """loss(theta, keys) for theta = {"w0", "lam_logit"}: mean squared predicted-rate error."""
    flt = dual_ekf(net, base_params)
    t = frame_dt * jnp.arange(frames)
    truth = jax.vmap(target)(t)  # (frames, 3)
    rate_now = jax.vmap(target)(t + delay * frame_dt)[:, 1]  # what the prediction is for
    late = jnp.asarray(np.asarray(t) >= settle, float)

    def one(params, key):
        z = truth[:, 0] + sigma * jax.random.normal(key, (frames,))
        state = flt.init(params, prior)

        def body(s, inp):
            zk, tk = inp
            s, _ = flt.step(params, s, Meas(zk[None], tk, jnp.asarray(True)))
            return s, predict_ahead(net, s.x, s.w, delay)[1]

        _, pred = jax.lax.scan(body, state, (z, t))
        return jnp.sum(late * (pred - rate_now) ** 2) / jnp.sum(late)

    def loss(theta, keys):
        params = dict(base_params, w0=theta["w0"], forget=jax.nn.sigmoid(theta["lam_logit"]))
        return jnp.mean(jax.vmap(lambda k: one(params, k))(keys))

    return loss


def train_dekf(net, params, target, prior, *, frames, frame_dt, delay, sigma, settle, steps=100, lr=0.01,
               runs_per_step=8, eval_runs=32, seed=0, log=None, on_step=None):
    """Train w0 and λ; returns (trained params, history [(step, loss)], eval before, eval after).
    ``on_step(done, steps, loss)`` after every step (a progress bar)."""
    loss = rate_loss_fn(net, params, target, prior, frames, frame_dt, delay, sigma, settle)
    lam = float(params["forget"])
    theta = {"w0": jnp.asarray(params["w0"]), "lam_logit": jnp.asarray(math.log(lam / max(1 - lam, 1e-9)))}
    key = jax.random.key(seed)
    train_key, eval_key = jax.random.fold_in(key, 1), jax.random.fold_in(key, 2)
    eval_keys = jax.random.split(eval_key, eval_runs)
    evaluate = jax.jit(loss)
    before = float(evaluate(theta, eval_keys))
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(lr))  # the adapting filter's loss is rough
    state = opt.init(theta)
    vg = jax.jit(jax.value_and_grad(loss))
    history = []
    for k in range(steps):
        val, g = vg(theta, jax.random.split(jax.random.fold_in(train_key, k), runs_per_step))
        if not (np.isfinite(float(val)) and all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(g))):
            if log:
                log(f"stopped at step {k}: non-finite loss or gradient")
            break
        history.append((k, float(val)))
        if on_step is not None:
            on_step(k + 1, steps, float(val))
        if log and (k % 10 == 0 or k == steps - 1):
            log(f"step {k:4d}  loss {float(val):.6g}")
        updates, state = opt.update(g, state, theta)
        theta = optax.apply_updates(theta, updates)
    after = float(evaluate(theta, eval_keys))
    trained = dict(params, w0=theta["w0"], forget=jax.nn.sigmoid(theta["lam_logit"]))
    return trained, history, before, after
