"""Streaming aggregates of the replayed joint states (memory independent of bag length): time
bins, per-joint peaks, violation episodes and latency histograms."""
from __future__ import annotations

import math

import numpy as np

from dyn_node.audit.replay.common import SeriesBins

MAX_EPISODES = 1000      # violation episodes listed (the rest are counted)


class LiveStats:
    """Time bins, per-joint peaks and violation episodes of the accepted joint states.

    Rows are buffered (references to the monitor's result arrays, which are never written after
    they are returned) and processed in vectorised batches; results equal a message-by-message
    update, including the order in which violation episodes close."""

    BATCH = 1024
    KINDS = ("effort", "position", "velocity", "deceleration")

    def __init__(self, nv: int, lo: np.ndarray, hi: np.ndarray, vel: np.ndarray,
                 dec: np.ndarray | None = None):
        # dec: deceleration limits, |q̈̂| where q̇·q̈̂ < 0 as the live monitor checks it
        self.nv, self.lo, self.hi, self.vel = nv, lo, hi, vel
        self.dec = np.full(nv, np.inf) if dec is None else dec
        self.series: SeriesBins | None = None
        self.episodes = Episodes()
        self.peak_util = np.full(nv, -np.inf)
        self.peak_t = np.zeros(nv, dtype=np.int64)
        self.peak_tau = np.zeros(nv)
        self.peak_meas = np.full(nv, np.nan)  # measured effort at the peak (NaN: not measured)
        self.peak_limit = np.full(nv, np.inf)
        self.rows: list[tuple] = []
        self._nan = np.full(nv, np.nan)

    def add(self, t_ns: int, tau, util, limit, q, v, measured, a_hat=None) -> None:
        rows = self.rows
        rows.append((t_ns, tau, util, limit, q, v, measured, a_hat))
        if len(rows) >= self.BATCH:
            self.flush()

    def flush(self) -> None:
        rows = self.rows
        n = len(rows)
        if not n:
            return
        self.rows = []
        nan = self._nan
        T = np.array([r[0] for r in rows], dtype=np.int64)
        TAU = np.array([r[1] for r in rows], dtype=float)
        UTIL = np.array([r[2] for r in rows], dtype=float)
        LIM = np.array([r[3] for r in rows], dtype=float)
        Q = np.array([r[4] for r in rows], dtype=float)
        V = np.array([r[5] for r in rows], dtype=float)
        MEAS = np.array([nan if r[6] is None else r[6] for r in rows], dtype=float)
        A = (np.array([np.zeros(self.nv) if r[7] is None else r[7] for r in rows], dtype=float)
             if np.isfinite(self.dec).any() else None)   # only a deceleration limit reads it
        self._rows(T, TAU, UTIL, LIM, Q, V, MEAS, A)

    def add_arrays(self, T, TAU, UTIL, LIM, Q, V, MEAS, A=None) -> None:
        """N rows of :meth:`add` at once ((N,) int64 log times ns, N×nv arrays; ``MEAS`` NaN
        where not measured; ``A`` the acceleration estimates, None: zero); the same result as
        N calls of :meth:`add`."""
        self.flush()
        self._rows(T, TAU, UTIL, np.ascontiguousarray(LIM), Q, V, MEAS, A)

    def _rows(self, T, TAU, UTIL, LIM, Q, V, MEAS, A) -> None:
        if self.series is None:
            self.series = SeriesBins(self.nv, int(T[0]))
        self.series.add_batch(T, TAU, UTIL, LIM, MEAS)
        k = np.argmax(UTIL, axis=0)  # first occurrence of each joint's batch maximum
        cols = np.arange(self.nv)
        best = UTIL[k, cols]
        better = best > self.peak_util
        if better.any():
            self.peak_util[better] = best[better]
            self.peak_t[better] = T[k[better]]
            self.peak_tau[better] = TAU[k[better], cols[better]]
            self.peak_meas[better] = MEAS[k[better], cols[better]]
            self.peak_limit[better] = LIM[k[better], cols[better]]
        over_e = UTIL > 1.0
        over_p = (Q < self.lo) | (Q > self.hi)
        AV = np.abs(V)
        over_v = AV > self.vel
        # decelerating (|q̇| decreasing) beyond the limit, as Monitor's limits status counts it
        if np.isfinite(self.dec).any() and A is not None:
            self._decel = np.where(V * A < 0, np.abs(A), 0.0)
            over_d = self._decel > self.dec
        else:
            self._decel, over_d = None, np.zeros(np.shape(Q), dtype=bool)
        # the |effort| behind each ratio where a limit is ≤ 0 (elsewhere it is ratio·limit)
        self._effort_value = np.fmax(np.abs(TAU), np.abs(MEAS)) if np.any(LIM <= 0) else None
        if self.episodes.open or over_e.any() or over_p.any() or over_v.any() or over_d.any():
            self._episodes(T, UTIL, LIM, Q, AV, (over_e, over_p, over_v, over_d))

    def _values(self, kind: int, r: int, j: int, UTIL, LIM, Q, AV) -> tuple[float, float, float]:
        """(value, limit, severity) of row r, joint j, as a message-by-message update has them."""
        lo, hi, vel = self.lo, self.hi, self.vel
        if kind == 0:
            u, lim = float(UTIL[r, j]), float(LIM[r, j])
            if lim <= 0 and self._effort_value is not None:
                # a zero (YAML) limit is a real one: u is inf, u·lim would be NaN
                return float(self._effort_value[r, j]), lim, u
            return u * lim, lim, u
        if kind == 1:
            qj = float(Q[r, j])
            below = qj < lo[j]
            return qj, float(lo[j] if below else hi[j]), float(lo[j] - qj if below else qj - hi[j])
        if kind == 3:
            d = float(self._decel[r, j])
            return d, float(self.dec[j]), d - float(self.dec[j])
        return float(AV[r, j]), float(vel[j]), float(AV[r, j] / vel[j])

    def _episodes(self, T, UTIL, LIM, Q, AV, overs) -> None:
        """Episodes of consecutive over-limit rows per (joint, kind), run by run.

        Equal to calling :meth:`Episodes.update` row by row, joint by joint, kind by kind: an
        episode's peak is its earliest sample of largest severity (a NaN first sample stays the
        peak, as ``>`` never replaces it), episodes close on the first row not over the limit, in
        (row, joint, kind) order, and episodes still open keep that order for :meth:`finish`."""
        ep = self.episodes
        n = len(T)
        with np.errstate(divide="ignore", invalid="ignore"):   # a zero (YAML) velocity limit
            sevs = (UTIL, np.where(Q < self.lo, self.lo - Q, Q - self.hi), AV / self.vel,
                    None if self._decel is None else self._decel - self.dec)
        closing: list[tuple[int, int, int, tuple[int, str] | None, dict]] = []
        opening: list[tuple[int, int, int, tuple[int, str], dict]] = []
        for kind_i, kind in enumerate(self.KINDS):
            OVER = overs[kind_i]
            SEV = sevs[kind_i]
            any_col = OVER.any(axis=0)
            for j in range(self.nv):
                key = (j, kind)
                cur = ep.open.get(key)
                if not any_col[j]:
                    if cur is not None:
                        closing.append((0, j, kind_i, key, cur))
                    continue
                o = OVER[:, j]
                starts = np.flatnonzero(np.r_[o[0], o[1:] & ~o[:-1]])
                ends = np.flatnonzero(np.r_[o[:-1] & ~o[1:], o[-1]])  # last row of each run
                sev = SEV[:, j]
                if cur is not None and starts[0] != 0:
                    closing.append((0, j, kind_i, key, cur))
                    cur = None
                for s, e in zip(starts.tolist(), ends.tolist()):
                    seg = sev[s:e + 1]
                    clean = np.where(np.isnan(seg), -np.inf, seg)
                    m = int(np.argmax(clean))
                    if cur is not None:  # the open episode continues from the last batch (s == 0)
                        d = cur
                        d["end"] = int(T[e])
                        d["n"] += e - s + 1
                        if clean[m] > d["sev"]:
                            value, limit, severity = self._values(kind_i, s + m, j, UTIL, LIM, Q, AV)
                            d["peak"], d["peak_t"], d["limit"], d["sev"] = value, int(T[s + m]), limit, severity
                        cur = None
                    else:
                        if math.isnan(seg[0]) or not clean[m] > clean[0]:
                            m = 0
                        value, limit, severity = self._values(kind_i, s + m, j, UTIL, LIM, Q, AV)
                        d = {"j": j, "kind": kind, "start": int(T[s]), "end": int(T[e]),
                             "peak_t": int(T[s + m]), "peak": value, "limit": limit, "n": e - s + 1,
                             "sev": severity}
                        if e == n - 1:
                            opening.append((s, j, kind_i, key, d))
                            continue
                        closing.append((e + 1, j, kind_i, None, d))
                        continue
                    if e != n - 1:
                        closing.append((e + 1, j, kind_i, key, d))
        closing.sort(key=lambda c: c[:3])
        for _r, _j, _k, key, d in closing:
            if key is not None:
                del ep.open[key]
            ep.total += 1
            if len(ep.closed) < MAX_EPISODES:
                ep.closed.append(d)
        opening.sort(key=lambda c: c[:3])
        for _r, _j, _k, key, d in opening:
            ep.open[key] = d

    def finish(self) -> None:
        self.flush()
        self.episodes.finish()


class Histogram:
    """Fixed log-spaced histogram for latency quantiles (1 µs … 100 s, 200 bins per decade)."""

    LO, DECADES, PER = 1e-6, 8, 200

    def __init__(self) -> None:
        self.bins = np.zeros(self.DECADES * self.PER + 2, dtype=np.int64)
        self.n, self.sum, self.min, self.max = 0, 0.0, math.inf, -math.inf

    def add(self, x: float) -> None:
        self.n += 1
        self.sum += x
        self.min = min(self.min, x)
        self.max = max(self.max, x)
        if x <= self.LO:
            self.bins[0] += 1
        else:
            k = int(math.log10(x / self.LO) * self.PER) + 1
            self.bins[min(k, len(self.bins) - 1)] += 1

    def quantile(self, q: float) -> float | None:
        if not self.n:
            return None
        k = int(np.searchsorted(np.cumsum(self.bins), q * self.n, side="left"))
        if k == 0:
            return max(self.min, 0.0) if self.min < self.LO else self.LO
        mid = self.LO * 10 ** ((k - 0.5) / self.PER)
        return float(min(max(mid, self.min), self.max))

    def to_dict(self) -> dict:
        if not self.n:
            return {"count": 0}
        return {"count": self.n, "min": self.min, "max": self.max, "mean": self.sum / self.n,
                "p50": self.quantile(0.5), "p95": self.quantile(0.95), "p99": self.quantile(0.99)}


class Episodes:
    """Consecutive-message violation episodes per (joint, kind)."""

    def __init__(self) -> None:
        self.open: dict[tuple[int, str], dict] = {}
        self.closed: list[dict] = []
        self.total = 0

    def update(self, j: int, kind: str, over: bool, t_ns: int, value: float, limit: float,
               severity: float = 0.0) -> None:
        """``severity`` orders samples within an episode (ratio or excess beyond the limit)."""
        key = (j, kind)
        ep = self.open.get(key)
        if over:
            if ep is None:
                self.open[key] = {"j": j, "kind": kind, "start": t_ns, "end": t_ns, "peak_t": t_ns,
                                  "peak": value, "limit": limit, "n": 1, "sev": severity}
            else:
                ep["end"] = t_ns
                ep["n"] += 1
                if severity > ep["sev"]:
                    ep["peak"], ep["peak_t"], ep["limit"], ep["sev"] = value, t_ns, limit, severity
        elif ep is not None:
            self._close(key)

    def _close(self, key: tuple[int, str]) -> None:
        ep = self.open.pop(key)
        self.total += 1
        if len(self.closed) < MAX_EPISODES:
            self.closed.append(ep)

    def finish(self) -> None:
        for key in list(self.open):
            self._close(key)
