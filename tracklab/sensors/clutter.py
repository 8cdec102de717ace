"""False alarms: a sensor whose scan holds the target's detection among clutter returns.

``Cluttered(sensor, density, half_width, max_returns=…)`` wraps any sensor (a built-in
``Sensor`` or a ``CustomSensor``). At each of the sensor's report epochs it makes a *scan*:

* the target's measurement, with probability ``p_detect`` (the wrapped sensor's);
* N ~ Poisson(λ·V) false alarms, λ = ``density`` per unit volume of the measurement space
  (in the sensor's own units: per m·rad for a polar sensor), uniform over a box
  ``center ± half_width`` of volume V = Π 2·half_width. The box is centred on the target's
  noise-free measurement (``about_target``: a gate-sized window that moves with it) or fixed
  (``center`` given: the sensor's coverage). Angle components are wrapped to (−π, π].

A scan is a fixed-capacity array (``max_returns``, m) — the detection at a random row, the
false alarms in the others, the unused rows NaN — so that every run and step has the same shapes.
With an amplitude model (``snr``: the target's mean signal-to-noise ratio in dB) the rows are in
order of amplitude, strongest first, which is what a strongest-neighbour tracker reads: the target
is a Swerling I return (power exponential with mean 1 + SNR), the false alarms are noise
(exponential with mean 1), both above the detection threshold τ = −(1 + SNR) ln P_D that gives the
sensor's ``p_detect``. Above τ both excesses are again exponential, so the number of false alarms
stronger than the target is Binomial(n, u^(1 + SNR)) with u uniform (``stronger_alarms``); the
false alarms' positions do not depend on their amplitudes, so their rows before and after the
target's can stand in amplitude order as they are. A scan whose returns
(detection and false alarms) pass the capacity is *overflowed*: its first ``max_returns``
returns are kept (the detection among them), and ``overflowed`` tells the world, which counts
and reports such scans. Between report epochs the scan is all NaN.

The number of false alarms is drawn by inverting the Poisson distribution function on one
uniform (exact up to the capacity), so the draws have fixed shapes and ``density`` is an
input of the compiled program: it can be swept, and changing it reuses the program.

``information_reduction_factor`` gives the scalar q ≤ p_detect by which clutter and missed
detections scale the Fisher information of a scan about the target's position (Niu, Willett
& Bar-Shalom, "Matrix CRLB scaling due to measurements of uncertain origin", IEEE Trans.
Signal Processing 49(7), 2001), evaluated by Monte-Carlo integration.
"""

from __future__ import annotations

import functools
import statistics
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tracklab import random
from tracklab.pytree import static
from tracklab.sensors.geometry import measure_whole, report_mask, wrap


def _inverse_cdf(u, pmf):
    """The least index n with u ≤ P(N ≤ n), for a distribution given by its probabilities ``pmf``
    (the last index + 1 when u passes them all)."""
    return jnp.sum(u > jnp.cumsum(pmf)).astype(jnp.int32)


def poisson_count(u, mean, capacity: int):
    """The number N ∈ {0, …, capacity + 1} with P(N ≤ n − 1) < u ≤ P(N ≤ n) for a Poisson(mean)
    N, capacity + 1 standing for "more than capacity": the inverse distribution function at the
    uniform ``u``."""
    n = jnp.arange(capacity + 1, dtype=jnp.result_type(mean))
    log_mean = jnp.log(jnp.maximum(mean, jnp.finfo(jnp.result_type(mean)).tiny))
    log_p = -mean + n * log_mean - jax.scipy.special.gammaln(n + 1.0)
    log_p = jnp.where(n == 0, -mean, log_p)  # 0·log 0 = 0
    return _inverse_cdf(u, jnp.exp(log_p))


def stronger_alarms(u, v, n, snr_db, capacity: int):
    """How many of ``n`` false alarms are stronger than the target (see the module's doc): the
    inverse distribution function at the uniform ``v`` of Binomial(n, p), p = u^(1 + SNR) the
    probability that noise above the threshold passes the target's amplitude (its excess over the
    threshold −(1 + SNR) ln u, u uniform). n ≤ capacity + 1; the result is at most n."""
    dtype = jnp.result_type(u)
    snr = 10.0 ** (jnp.asarray(snr_db, dtype) / 10.0)
    log_p = (1.0 + snr) * jnp.log(jnp.maximum(u, jnp.finfo(dtype).tiny))
    log_q = jnp.log1p(-jnp.exp(log_p))
    k = jnp.arange(capacity + 2, dtype=dtype)
    nf = n.astype(dtype)
    log_choose = (jax.scipy.special.gammaln(nf + 1.0) - jax.scipy.special.gammaln(k + 1.0)
                  - jax.scipy.special.gammaln(jnp.maximum(nf - k, 0.0) + 1.0))
    # 0·log 0 = 0 at the ends (p → 0 or 1)
    terms = log_choose + jnp.where(k > 0, k * log_p, 0.0) + jnp.where(nf - k > 0, (nf - k) * log_q, 0.0)
    return jnp.minimum(_inverse_cdf(v, jnp.where(k <= nf, jnp.exp(terms), 0.0)), n).astype(jnp.int32)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Cluttered:
    """A sensor whose scans hold clutter (see the module's doc). ``density``, ``half_width`` and
    ``center`` are leaves (program inputs); ``max_returns`` and ``about_target`` are structure."""

    sensor: Any  # a Sensor or CustomSensor: the target's measurement, timing and p_detect
    density: Any = 0.0  # λ: false alarms per unit volume of the measurement space
    half_width: Any = ()  # (m,) half-widths of the clutter box, in the sensor's units
    center: Any = None  # (m,) a fixed box's centre; None: the target's noise-free measurement
    max_returns: int = static(16)  # the scan's capacity
    snr: Any = None  # the target's mean SNR (dB): the returns in order of amplitude; None: in random order

    @property
    def about_target(self) -> bool:
        return self.center is None

    # the wrapped sensor's description
    kind = property(lambda self: self.sensor.kind)
    dim = property(lambda self: self.sensor.dim)
    m = property(lambda self: self.sensor.m)
    sigma = property(lambda self: self.sensor.sigma)
    names = property(lambda self: self.sensor.names)
    angle_mask = property(lambda self: self.sensor.angle_mask)
    linear = property(lambda self: self.sensor.linear)
    name = property(lambda self: self.sensor.name)
    dt = property(lambda self: self.sensor.dt)
    period = property(lambda self: self.sensor.period)
    offset = property(lambda self: self.sensor.offset)
    p_detect = property(lambda self: self.sensor.p_detect)
    R = property(lambda self: self.sensor.R)
    misses = False  # detections are part of the scan; a filter always sees the scan pattern

    @property
    def sensors(self):
        return (self,)

    def h(self, p):
        return self.sensor.h(p)

    def report_mask(self, steps: int) -> np.ndarray:
        return report_mask(self, steps)

    def volume(self):
        """V, the clutter box's volume in the measurement space."""
        return jnp.prod(2.0 * jnp.asarray(self.half_width))

    def mean_false_alarms(self):
        """λ·V, the expected number of false alarms per scan."""
        return jnp.asarray(self.density) * self.volume()

    def draws(self, key, steps):
        """One run's draws, float32: the target's (noise and detection uniforms), one uniform per
        step for the false-alarm count, (steps, capacity, m) uniforms for their positions and one
        for the order of the returns."""
        k_target, k_count, k_pos, k_order = jax.random.split(key, 4)
        noise = random.normal(k_target, (steps, self.m))
        detect = random.uniform(jax.random.fold_in(k_target, 1), (steps,))
        order = random.uniform(k_order, (steps,))
        if self.snr is not None:  # and one for the target's amplitude
            order = (order, random.uniform(jax.random.fold_in(k_order, 1), (steps,)))
        return ((noise, detect), random.uniform(k_count, (steps,)),
                random.uniform(k_pos, (steps, self.max_returns, self.m)), order)

    def _counts(self, detect, u_count, k, steps, dtype):
        """(scanning, detected, false alarms drawn (capacity + 1: more than the capacity)) at step k,
        from its detection and count uniforms."""
        scanning = jnp.asarray(self.report_mask(steps))[k]
        detected = scanning & (detect < jnp.asarray(self.p_detect, jnp.float32))
        n = poisson_count(u_count.astype(dtype), self.mean_false_alarms().astype(dtype), self.max_returns)
        return scanning, detected, jnp.where(scanning, n, 0)

    def overflowed(self, detect, u_count, k, steps, dtype=jnp.float32):
        """Whether step k's scan has more returns than its capacity (some were not kept), from that
        step's detection and count uniforms (``draws``' first detection and second entries)."""
        _, detected, n = self._counts(detect, u_count, k, steps, dtype)
        return n + detected.astype(jnp.int32) > self.max_returns

    def measure_step(self, draws_k, k, steps, p):
        """Step k's scan (capacity, m) of the target at ``p`` (dim,): the detection at a random row
        (with ``snr``: after the false alarms stronger than it), NaN rows unused."""
        (noise, detect), u_count, u_pos, u_order = draws_k
        dtype = p.dtype
        K = self.max_returns
        scanning, detected, n = self._counts(detect, u_count, k, steps, dtype)
        z_clean = self.h(p)
        target = self.sensor.measure_step((noise, None), k, steps, p)  # NaN between report epochs
        center = z_clean if self.about_target else jnp.asarray(self.center, dtype)
        alarms = center + (2.0 * u_pos.astype(dtype) - 1.0) * jnp.asarray(self.half_width, dtype)  # (K, m)
        if any(self.angle_mask):
            alarms = jnp.where(jnp.asarray(self.angle_mask), wrap(alarms), alarms)
        # the detection at a random row s, the false alarms in the rows before it and after it, in
        # order (elementwise selections: no gather under vmap)
        j = jnp.arange(K)
        if self.snr is None:
            s = jnp.minimum(jnp.floor(u_order * K).astype(jnp.int32), K - 1)
        else:
            s = jnp.minimum(stronger_alarms(u_order[1].astype(dtype), u_order[0].astype(dtype), n, self.snr, K), K - 1)
        alarm = j - (detected & (j > s)).astype(jnp.int32)  # which false alarm row j holds
        after = jnp.concatenate([alarms[-1:], alarms[:-1]])  # alarm j - 1 in row j
        rows = jnp.where((detected & (j > s))[:, None], after, alarms)
        rows = jnp.where((detected & (j == s))[:, None], target[None, :], rows)
        kept = jnp.where(detected & (j == s), True, alarm < n)
        return jnp.where(kept[:, None], rows, jnp.nan)

    def measure(self, key, pos):
        """Scans of a position sequence ``pos`` (T, dim) -> (T, capacity, m)."""
        return measure_whole(self, key, jnp.asarray(pos, dtype=jnp.result_type(float)))

    def information(self, p):
        """The Fisher information of one scan about the position without clutter, Pd·Hᵀ R⁻¹ H: the
        PCRLB scales it by the information reduction factor over Pd (``scan_information_scale``)."""
        return self.sensor.information(p)

    def capacity_needed(self, tail: float = 1e-6) -> int:
        """The least capacity K at which a scan (the detection and N ~ Poisson(λV) false alarms)
        holds more than K returns with probability below ``tail``."""
        mean = float(np.asarray(self.mean_false_alarms(), float))
        if mean > 500.0:  # e^(−mean) underflows: the normal approximation, far beyond any capacity anyway
            return int(np.ceil(mean + statistics.NormalDist().inv_cdf(1.0 - tail) * np.sqrt(mean))) + 1
        p, cdf, n = np.exp(-mean), 0.0, 0
        while True:  # P(N ≤ n), term by term
            cdf += p
            if 1.0 - cdf < tail:
                return n + 1
            n += 1
            p *= mean / n

    def problem(self, max_overflow: float = 1e-3) -> tuple[str, object, str] | None:
        """Why this cluttered sensor's numbers cannot be simulated faithfully, as (field, value,
        what is allowed), or None: a clutter region not one positive half-width per component, an
        angle's half-width above π or its coverage outside (−π, π], or a capacity that more than
        ``max_overflow`` of the scans pass (an overflowed scan keeps the target's detection and
        drops false alarms: the tracker's task would be easier than the sensor's)."""
        m, angles = self.m, tuple(self.angle_mask)
        half = np.asarray(self.half_width, float)
        if half.shape != (m,) or not np.all(np.isfinite(half)) or np.any(half <= 0):
            return "half_width", self.half_width, f"must be {m} numbers > 0, one per component ({', '.join(self.names)})"
        for i, (h, is_angle) in enumerate(zip(half, angles)):
            if is_angle and h > np.pi:
                return "half_width", self.half_width, (f"{self.names[i]}'s half-width {h:g} rad is more than π: the "
                                                       "clutter region of an angle lies within ±π rad")
        if self.center is not None:
            c = np.asarray(self.center, float)
            for i, is_angle in enumerate(angles):
                if is_angle and (c[i] - half[i] < -np.pi - 1e-9 or c[i] + half[i] > np.pi + 1e-9):
                    return "coverage", self.center, f"{self.names[i]} must lie within [−π, π] rad"
        density = float(np.asarray(self.density, float))
        if not np.isfinite(density) or density < 0:
            return "density", self.density, "must be a number >= 0 (false alarms per unit volume)"
        mean = float(np.asarray(self.mean_false_alarms(), float))
        needed = self.capacity_needed(max_overflow)
        if needed > self.max_returns:
            return ("max_returns", self.max_returns,
                    f"must be at least {needed}: with {mean:.3g} false alarms a scan on average, more than "
                    f"{max_overflow:.1%} of the scans would hold more returns than {self.max_returns} (a capacity "
                    f"of {self.capacity_needed():d} is passed once in a million scans; or narrow the region)")
        return None

    def whitened_density(self) -> float:
        """λ·√det R: false alarms per unit volume of the whitened measurement space (R the true noise)."""
        R = np.asarray(self.R, float)
        return float(np.asarray(self.density, float)) * float(np.sqrt(np.linalg.det(R)))

    def whitened_half_width(self) -> np.ndarray:
        return np.asarray(self.half_width, float) / np.sqrt(np.diag(np.asarray(self.R, float)))


def cluttered_of(sensor) -> Cluttered | None:
    """The cluttered sensor among ``sensor``'s (a suite, a sensor or a view of them); None: none."""
    return next((s for s in getattr(sensor, "sensors", ()) if isinstance(s, Cluttered)), None)


def scan_information_scale(sensor) -> float:
    """q / Pd: what a scan's information without clutter (Pd·Hᵀ R⁻¹ H) is multiplied by."""
    pd = float(np.asarray(sensor.p_detect, float))
    q = information_reduction_factor(sensor.whitened_density(), pd, tuple(np.round(sensor.whitened_half_width(), 9)),
                                     sensor.max_returns)
    return q / pd


@functools.lru_cache(maxsize=256)
def information_reduction_factor(density_w: float, p_detect: float, half_width_w: tuple, capacity: int,
                                 scans: int = 200_000, seed: int = 0) -> float:
    """The information reduction factor q (Niu, Willett & Bar-Shalom 2001): the Fisher information
    of a scan about the target's position is q·Hᵀ R⁻¹ H, with q = E[sᵀ s]/m and s the score of
    the scan's likelihood in whitened coordinates (unit measurement noise),

        s = Pd Σᵢ N(zᵢ; 0, I) zᵢ / (λ_w (1 − Pd) + Pd Σᵢ N(zᵢ; 0, I))   (the target at 0),

    λ_w the whitened clutter density, the false alarms uniform over ± ``half_width_w`` (whitened)
    about the target, at most ``capacity`` returns. Evaluated by Monte-Carlo integration over
    ``scans`` scans (a fixed seed: the same number every time); q = Pd without clutter."""
    rng = np.random.default_rng(seed)
    m = len(half_width_w)
    w = np.asarray(half_width_w, float)
    mean = density_w * float(np.prod(2.0 * w))
    detected = rng.random(scans) < p_detect
    n = np.minimum(rng.poisson(mean, scans), capacity - detected.astype(int))
    K = int(n.max(initial=0)) + 1
    z = (2.0 * rng.random((scans, K, m)) - 1.0) * w  # false alarms in the first n rows
    valid = np.arange(K)[None, :] < n[:, None]
    z = np.concatenate([rng.standard_normal((scans, 1, m)), z], axis=1)  # the detection in row 0
    valid = np.concatenate([detected[:, None], valid], axis=1)
    g = np.where(valid, np.exp(-0.5 * np.sum(z**2, axis=-1)) / (2.0 * np.pi) ** (m / 2), 0.0)
    denom = density_w * (1.0 - p_detect) + p_detect * g.sum(axis=1)
    score = p_detect * np.einsum("sk,skm->sm", g, z) / np.where(denom > 0, denom, 1.0)[:, None]
    return float(np.mean(np.sum(score**2, axis=1)) / m)
