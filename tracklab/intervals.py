"""Monte-Carlo confidence intervals from per-run samples.

Every run of an experiment is an independent draw, so each run's time-averaged
value of a quantity (its mean-square position error over the report window, its
mean NEES, …) is one sample, and a summary number is a smooth function of the
samples' means. Its interval is a Student-t interval with the delta method:

    half-width = t_{1-α/2, n-1} · sqrt(∇gᵀ Σ ∇g / n)

with Σ the samples' covariance. For a mean (mean error, NEES) that is the
ordinary t interval; for an RMSE, sqrt of a mean square, ∇g = 1/(2·RMSE); for a
ratio of means (the NIS: innovations' χ² over the updates that made them) the
usual ratio-estimator variance. A difference between two filters on the same
runs (a *paired* comparison) is g(m_f) - g(m_b) with the joint covariance of
both filters' samples: the common draws cancel, which is why it is far narrower
than the two separate intervals. A fraction of runs (the diverged ones) has a
Wilson score interval, which stays inside [0, 1] and is sound at 0 of n.
"""

from __future__ import annotations

import functools
import math
from statistics import NormalDist

import numpy as np

LEVEL = 0.95  # default confidence level


@functools.lru_cache(maxsize=256)
def t_quantile(level: float, dof: float) -> float:
    """Two-sided Student-t quantile t_{(1+level)/2, dof} (bisection on the regularised beta)."""
    import jax
    from jax.scipy.special import betainc

    if not dof >= 1:
        return float("nan")
    p = 1.0 - (1.0 - level) / 2.0
    z = NormalDist().inv_cdf(p)
    if dof > 1e7:
        return z
    with jax.enable_x64(True):
        lo, hi = z, max(2.0 * z, 1.0)

        def cdf(t):  # P(T <= t), t > 0
            return 1.0 - 0.5 * float(betainc(dof / 2.0, 0.5, dof / (dof + t * t)))

        while cdf(hi) < p:
            hi *= 2.0
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return 0.5 * (lo + hi)


def wilson(k, n, level: float = LEVEL):
    """Wilson score interval (lo, hi) of a fraction k/n; (NaN, NaN) when n = 0."""
    k, n = float(k), float(n)
    if n <= 0:
        return float("nan"), float("nan")
    z = NormalDist().inv_cdf(1.0 - (1.0 - level) / 2.0)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (0.0 if k <= 0 else max(0.0, centre - half)), (1.0 if k >= n else min(1.0, centre + half))


# A summary statistic as a function of the per-run samples' means ``m`` (a vector indexed by
# quantity): ("mean", q) -> m[q]; ("root", qs) -> sqrt(sum m[qs]); ("ratio", q, r) -> m[q] / m[r].

def value_and_gradient(stat, m):
    """(g(m), ∇g(m)) of a statistic (see above) at the means ``m`` (Q,)."""
    m = np.asarray(m, float)
    grad = np.zeros_like(m)
    kind = stat[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        if kind == "mean":
            grad[stat[1]] = 1.0
            return m[stat[1]], grad
        if kind == "root":
            qs = list(stat[1])
            v = np.sqrt(np.sum(m[qs]))
            grad[qs] = 0.5 / v
            return v, grad
        if kind == "ratio":
            q, r = stat[1], stat[2]
            v = m[q] / m[r]
            grad[q] = 1.0 / m[r]
            grad[r] = -m[q] / m[r] ** 2
            return v, grad
    raise ValueError(f"unknown statistic {stat!r}")


def _quad(a, cov, b) -> float:
    """aᵀ cov b over the quantities either gradient uses (another quantity may be NaN: a
    filter that reports no prediction has no prediction-error samples)."""
    used = (a != 0) | (b != 0)
    return float(a[used] @ cov[np.ix_(used, used)] @ b[used])


def half_width(grad, cov, n, level: float = LEVEL) -> float:
    """t_{n-1} · sqrt(gradᵀ cov grad / n): NaN with fewer than two samples."""
    if n < 2:
        return float("nan")
    var = _quad(grad, cov, grad)
    return t_quantile(level, n - 1) * np.sqrt(max(var, 0.0) / n)


def paired_half_width(grad_f, grad_b, cov_dd, cov_db, cov_bb, n, level: float = LEVEL) -> float:
    """Half-width of g(m_f) - g(m_b) on the same n runs, by the delta method: with D = f's samples
    − b's and δ = grad_f − grad_b, grad_fᵀ f − grad_bᵀ b = grad_fᵀ D + δᵀ b, whose variance is
    grad_fᵀ cov_dd grad_f + δᵀ cov_bb δ + 2 grad_fᵀ cov_db δ (cov_db: covariance of D with b's
    samples). From the differences' own covariance, not as var f + var b − 2 cov(f, b), which
    cancels: exactly 0 for two filters whose samples agree run by run."""
    if n < 2:
        return float("nan")
    delta = grad_f - grad_b
    var = _quad(grad_f, cov_dd, grad_f) + _quad(delta, cov_bb, delta) + 2.0 * _quad(grad_f, cov_db, delta)
    return t_quantile(level, n - 1) * np.sqrt(max(var, 0.0) / n)


def precision_reached(samples, target: float, level: float = LEVEL, stat=("root", [0])) -> bool:
    """Whether every lane's ``stat`` of its runs' samples (default: the root of the first sample's
    mean, an RMSE) has its ``level`` interval within ± ``target`` of itself (relative); a lane
    with no healthy run does not hold it back (``samples``: a ``RunSamples``; None: not yet)."""
    if samples is None:
        return False
    for li in range(samples.n.shape[-1]):
        own = samples.pair(li, li)
        if own.n == 0:
            continue
        v, g = value_and_gradient(stat, own.mean_f)
        if not half_width(g, own.cov_ff, own.n, level) <= target * abs(v):
            return False
    return True


def missing(v) -> bool:
    """None or not finite: a statistic with no healthy run behind it."""
    return v is None or (isinstance(v, (float, np.floating)) and not math.isfinite(v))


def percent(fraction, sign: bool = True) -> str:
    """A fraction as a plain percentage: ``0 %``, ``0.012 %``, ``12 %``, ``99.97 %``, ``100 %``
    (``sign=False``: without " %"); "—" for a missing value. Two significant digits, and as many
    more decimals as keep a fraction just below 1 from showing as 100 (and one just above 0
    from showing as 0); never an exponent."""
    if missing(fraction):
        return "—"
    p = 100.0 * float(fraction)
    d = 0
    if p != 0:
        d = max(0, 1 - math.floor(math.log10(abs(p))))
        if 50 < p < 100:
            d = max(d, -math.floor(math.log10(100 - p)))
    s = f"{p:.{d}f}"
    s = s.rstrip("0").rstrip(".") if "." in s else s
    return s + " %" if sign else s


def format_value(v, spec) -> str:
    """A table cell: ``spec`` (a ``%`` spec: the plain percentage without its sign, ``percent``),
    or "—" for a missing value."""
    if missing(v):
        return "—"
    return percent(v, sign=False) if spec.endswith("%}") else spec.format(v)


def with_half_width(v, hw, spec="{:.2f}", sign=False) -> str:
    """``34.45 ± 0.05``: the half-width to two significant digits, the value to the same decimal;
    the column's own format when there is no half-width."""
    if missing(v) or missing(hw):
        return format_value(v, spec)
    if hw == 0:
        return f"{v:{'+' if sign else ''}.{_decimals(spec)}f} ± 0"
    d = max(0, 1 - math.floor(math.log10(abs(hw))))
    return f"{v:{'+' if sign else ''}.{d}f} ± {hw:.{d}f}"


def _decimals(spec) -> int:
    try:
        return int(spec.split(".")[1].split("f")[0]) if "f}" in spec else 2
    except ValueError:
        return 2
