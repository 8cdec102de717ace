"""Per-run samples, streamed: the moments that intervals and paired comparisons need.

A world hands the runner, per chunk, each lane's per-run samples ``values``
(lanes, Q, B) — one run's time-averaged quantities — and ``ok`` (lanes, B), the
runs that count for that lane (live and healthy). ``RunSamples`` keeps, over all
chunks and in float64 whatever the run's precision:

* ``n[f, g]``: runs healthy in both lanes f and g;
* ``s[f, g, q]``: the sum of lane f's quantity q over those runs;
* ``own[f, g, q, r]``: the sum of f's q times f's r over them;
* ``sd[f, g, q]``, ``dd[f, g, q, r]``, ``dg[f, g, q, r]``: over the same runs, the sums of the
  difference D = f's samples − g's, of D_q D_r and of D_q times g's r;

each after subtracting a shift (the first chunk's means: of a lane's samples, and of each
pair's differences), so that variances do not cancel. From them, ``pair(f, g)`` gives both
lanes' means and covariances on their common runs (f = g: the lane's own), and the covariances
of their differences, taken from the differences themselves: two filters whose samples agree
run by run have differences of variance exactly 0, and two that nearly agree the variance that
``cov_ff + cov_gg − 2 cov_fg`` would round away. Memory does not grow with the runs, except
``kept``: values the world keeps of every healthy run (a few numbers per run and lane), for
percentiles and distributions. Leading axes (a sweep's grid points) are carried throughout.
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
    cov_dd: np.ndarray  # covariance of the differences D = f's − g's
    cov_dg: np.ndarray  # covariance of D (rows) with g's quantities (columns)


class RunSamples:
    """Streaming moments of per-run samples (see the module's doc)."""

    def __init__(self):
        self.shift = self.dshift = None
        self.n = self.s = self.own = self.sd = self.dd = self.dg = None
        self._kept: list[np.ndarray] = []

    def add(self, values, ok, kept=None):
        """One chunk's samples ``values`` (..., lanes, Q, B), flags ``ok`` (..., lanes, B) and the
        per-run values to keep whole, ``kept`` (..., lanes, K, B)."""
        values = np.asarray(values, np.float64)
        ok = np.asarray(ok, bool)
        okf = ok.astype(np.float64)
        v = np.where(ok[..., None, :], values, 0.0)  # a run left out may hold NaN
        both = ok[..., :, None, :] & ok[..., None, :, :]  # (..., f, g, B)
        n = both.sum(-1).astype(np.float64)  # (..., f, g)
        first = self.shift is None
        if first:
            self.shift = v.sum(-1) / np.maximum(okf.sum(-1), 1.0)[..., None]  # (..., lanes, Q)
            self.dshift = np.zeros(n.shape + v.shape[-2:-1])  # (..., f, g, Q), set lane by lane below
        c = np.where(ok[..., None, :], v - self.shift[..., None], 0.0)
        # np.einsum's own loops, not BLAS: OpenBLAS's threads, waiting on after a call, would take the
        # cores from the next chunk's program
        own, sd, dd, dg = [], [], [], []
        for f in range(v.shape[-3]):  # one lane against every other at a time: (…, lanes, Q, B) at most
            own.append(np.einsum("...qb,...rb,...gb->...gqr", c[..., f, :, :], c[..., f, :, :], okf))
            raw = np.where(both[..., f, :, None, :], v[..., f, None, :, :] - v, 0.0)  # f's samples − each g's
            if first:
                self.dshift[..., f, :, :] = raw.sum(-1) / np.maximum(n[..., f, :], 1.0)[..., None]
            d = np.where(both[..., f, :, None, :], raw - self.dshift[..., f, :, :, None], 0.0)
            sd.append(d.sum(-1))
            dd.append(np.einsum("...gqb,...grb->...gqr", d, d))
            dg.append(np.einsum("...gqb,...grb->...gqr", d, c))
        parts = (n, np.einsum("...fqb,...gb->...fgq", c, okf), np.stack(own, axis=-4), np.stack(sd, axis=-3),
                 np.stack(dd, axis=-4), np.stack(dg, axis=-4))
        for name, part in zip(("n", "s", "own", "sd", "dd", "dg"), parts):
            setattr(self, name, part if first else getattr(self, name) + part)
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
        for name in ("shift", "dshift", "n", "s", "own", "sd", "dd", "dg"):
            setattr(out, name, getattr(self, name)[j])
        out._kept = [k[j] for k in self._kept]
        return out

    def pair(self, f, g) -> Pair:
        """Means and covariances of lanes f and g over the runs healthy in both (f = g: f's own)."""
        n = int(round(self.n[f, g]))
        s_f, s_g, s_d = self.s[f, g], self.s[g, f], self.sd[f, g]
        nn = max(n, 1)
        mean_f, mean_g = self.shift[f] + s_f / nn, self.shift[g] + s_g / nn
        d = max(n - 1, 1)
        cov_ff = (self.own[f, g] - np.outer(s_f, s_f) / nn) / d
        cov_gg = (self.own[g, f] - np.outer(s_g, s_g) / nn) / d
        cov_dd = (self.dd[f, g] - np.outer(s_d, s_d) / nn) / d
        cov_dg = (self.dg[f, g] - np.outer(s_d, s_g) / nn) / d
        return Pair(n, mean_f, mean_g, cov_ff, cov_gg, cov_dd, cov_dg)
