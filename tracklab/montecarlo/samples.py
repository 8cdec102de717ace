"""Per-run samples, streamed: the moments that intervals and paired comparisons need.

A world hands the runner, per chunk, each lane's per-run samples ``values``
(lanes, Q, B) — one run's time-averaged quantities — and ``ok`` (lanes, B), the
runs that count for that lane (live and healthy). ``RunSamples`` keeps, over all
chunks and in float64 whatever the run's precision:

* ``n[f, g]``: runs healthy in both lanes f and g;
* ``s[f, g, q]``: the sum of lane f's quantity q over those runs;
* ``cross[f, g, q, r]``: the sum of f's q times g's r over them;
* ``own[f, g, q, r]``: the sum of f's q times f's r over them;

all after subtracting a shift (the first chunk's means), so that variances do
not cancel. From them, ``pair(f, g)`` gives the means and the joint covariance of
both lanes on their common runs (f = g: the lane's own). Memory does not grow
with the runs, except ``kept``: values the world keeps of every healthy run
(a few numbers per run and lane), for percentiles and distributions.
Leading axes (a sweep's grid points) are carried throughout.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Pair(NamedTuple):
    """Two lanes on their common healthy runs."""

    n: int
    mean_f: np.ndarray  # (Q,)
    mean_g: np.ndarray
    cov_ff: np.ndarray  # (Q, Q)
    cov_gg: np.ndarray
    cov_fg: np.ndarray  # covariance of f's quantities (rows) with g's (columns)


class RunSamples:
    """Streaming moments of per-run samples (see the module's doc)."""

    def __init__(self):
        self.shift = None
        self.n = self.s = self.cross = self.own = None
        self._kept: list[np.ndarray] = []

    def add(self, values, ok, kept=None):
        """One chunk's samples ``values`` (..., lanes, Q, B), flags ``ok`` (..., lanes, B) and the
        per-run values to keep whole, ``kept`` (..., lanes, K, B)."""
        values = np.asarray(values, np.float64)
        ok = np.asarray(ok, bool)
        okf = ok.astype(np.float64)
        v = np.where(ok[..., None, :], values, 0.0)  # a run left out may hold NaN
        if self.shift is None:
            count = np.maximum(okf.sum(-1), 1.0)[..., None]
            self.shift = v.sum(-1) / count  # (..., lanes, Q)
        c = np.where(ok[..., None, :], v - self.shift[..., None], 0.0)
        parts = (np.einsum("...fb,...gb->...fg", okf, okf),
                 np.einsum("...fqb,...gb->...fgq", c, okf),
                 np.einsum("...fqb,...grb->...fgqr", c, c),
                 np.einsum("...fqb,...frb,...gb->...fgqr", c, c, okf))
        if self.n is None:
            self.n, self.s, self.cross, self.own = parts
        else:
            self.n, self.s, self.cross, self.own = (a + b for a, b in zip((self.n, self.s, self.cross, self.own), parts))
        if kept is not None:
            self._kept.append(np.where(ok[..., None, :], np.asarray(kept, np.float64), np.nan))

    def kept(self, lane, j=0, point=()):
        """The ``j``-th kept quantity of every run healthy for ``lane`` (run order)."""
        if not self._kept:
            return np.zeros(0)
        v = np.concatenate([k[point + (lane, j)] for k in self._kept])
        return v[np.isfinite(v)]

    def point(self, j) -> "RunSamples":
        """The samples of grid point ``j`` (a leading axis of every array)."""
        out = RunSamples()
        out.shift, out.n, out.s, out.cross, out.own = (a[j] for a in (self.shift, self.n, self.s, self.cross, self.own))
        out._kept = [k[j] for k in self._kept]
        return out

    def pair(self, f, g) -> Pair:
        """Means and covariances of lanes f and g over the runs healthy in both (f = g: f's own)."""
        n = int(round(self.n[f, g]))
        s_f, s_g = self.s[f, g], self.s[g, f]
        nn = max(n, 1)
        mean_f, mean_g = self.shift[f] + s_f / nn, self.shift[g] + s_g / nn
        d = max(n - 1, 1)
        cov_ff = (self.own[f, g] - np.outer(s_f, s_f) / nn) / d
        cov_gg = (self.own[g, f] - np.outer(s_g, s_g) / nn) / d
        cov_fg = cov_ff if f == g else (self.cross[f, g] - np.outer(s_f, s_g) / nn) / d
        return Pair(n, mean_f, mean_g, cov_ff, cov_gg, cov_fg)
