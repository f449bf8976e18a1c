"""The live monitor's worst cases over one diagnostics period."""
from __future__ import annotations

import numpy as np


class Window:
    """Worst cases since the last report (reset by :meth:`Monitor.statuses`).

    Accepted messages are copied as rows into a block (:meth:`add`) and folded into the worst
    cases in batches by :meth:`fold`; the fold gives exactly the state a message-by-message
    update would (earliest maximum wins, NaN never wins, squares summed in message order). A
    copy per message costs what gathering a list of rows into arrays at the fold did, but the
    fold then holds the interpreter for a fraction of the time: the node folds a closed window
    while the next messages are being handled."""

    FOLD_ROWS = 512

    def __init__(self, nv: int, start_s: float | None):
        self.start_s = start_s
        self.received = self.accepted = self.invalid = self.out_of_order = self.zero_stamp = 0
        self.dropped = 0
        self.util = np.zeros(nv)
        self.util_limit = np.full(nv, np.inf)
        self.util_measured = np.zeros(nv, dtype=bool)
        self.pos_excess = np.full(nv, -np.inf)
        self.pos_value = np.zeros(nv)
        self.soft_excess = np.full(nv, -np.inf)
        self.soft_value = np.zeros(nv)
        self.vel_excess = np.full(nv, -np.inf)
        self.vel_value = np.zeros(nv)
        self.dec_excess = np.full(nv, -np.inf)
        self.dec_value = np.zeros(nv)
        self.res_sq = np.zeros(nv)
        self.res_n = np.zeros(nv, dtype=np.int64)
        # per message (q, v, model ratio |τ|/limit, limit, measured ratio, residual, â), NaN
        # where not measured; rows [0, n_rows) are not folded yet
        self._rows = np.empty((self.FOLD_ROWS, 7, nv))
        self.n_rows = 0

    def add(self, row: tuple) -> bool:
        """Queue one message's row (7 arrays of nv, as above); True when the block is full and
        must be folded before the next."""
        self._rows[self.n_rows] = row
        self.n_rows += 1
        return self.n_rows == self.FOLD_ROWS

    @staticmethod
    def _worst(x: np.ndarray, best: np.ndarray, *targets: tuple[np.ndarray, np.ndarray]) -> None:
        """Per column, the first row of ``x`` with the column's largest value replaces ``best``
        (and the same row of each ``(target, source)``) where it is strictly larger."""
        x = np.where(np.isnan(x), -np.inf, x)  # a per-message ``>`` never picks NaN
        cols = np.arange(x.shape[1])
        k = np.argmax(x, axis=0)
        top = x[k, cols]
        b = top > best
        if b.any():
            best[b] = top[b]
            for dst, src in targets:
                dst[b] = src[k, cols][b]

    def fold(self, lo, hi, slo, shi, soft: bool, vel, *, dec: np.ndarray | None = None) -> None:
        """Fold the queued rows into the worst cases."""
        n = self.n_rows
        if not n:
            return
        self.n_rows = 0
        Q, V, UM, L, MR, R, A = (self._rows[:n, j] for j in range(7))
        self.fold_arrays(lo, hi, slo, shi, soft, vel, Q, V, UM, L, MR, R, dec=dec,
                         A=A if dec is not None else None)

    def fold_arrays(self, lo, hi, slo, shi, soft: bool, vel, Q, V, UM, L, MR, R, *,
                    dec: np.ndarray | None = None, A: np.ndarray | None = None) -> None:
        """Fold N rows given as N×nv arrays (queued rows must be folded first, to keep the
        message order). ``MR`` and ``R`` are NaN where not measured. ``dec``: deceleration
        limits (None: none), checked on the acceleration estimates ``A`` where q̇·q̈̂ < 0."""
        # utilisation as process computed it; NaN measured ratio: unmeasured, the model's ratio
        U = np.fmax(UM, MR)
        self._worst(U, self.util, (self.util_limit, L), (self.util_measured, MR > UM))
        self._worst(np.maximum(lo - Q, Q - hi), self.pos_excess, (self.pos_value, Q))
        if soft:
            self._worst(np.maximum(slo - Q, Q - shi), self.soft_excess, (self.soft_value, Q))
        self._worst(np.abs(V) - vel, self.vel_excess, (self.vel_value, V))
        if dec is not None:
            # excess −inf where |q̇| is not decreasing: only decelerations can exceed the limit
            ex = np.where(V * A < 0, np.abs(A) - dec, -np.inf)
            self._worst(ex, self.dec_excess, (self.dec_value, A))
        ok = ~np.isnan(R)
        if ok.any():
            # cumsum adds row by row, in message order: the same rounding as ``res_sq += r²``
            # message by message (adding +0.0 for an unmeasured joint changes nothing).
            with np.errstate(over="ignore"):  # a residual beyond 1e154 N·m: its RMS is inf
                sq = np.where(ok, R * R, 0.0)
            self.res_sq = np.cumsum(np.vstack([self.res_sq, sq]), axis=0)[-1]
            self.res_n += ok.sum(axis=0)


__all__ = ["Window"]
