"""What the bag audit's replay (:mod:`~dyn_node.audit.replay.inputs`) and the contact replay
(:mod:`~dyn_node.audit.replay.contact`) share: time-binned series, the pending recomputed outputs
and their comparison with the recorded ones, and the stamp the node gives a zero-stamped input's
output. A module apart so that neither imports the other for them."""
from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import numpy as np

MAX_BINS = 1024          # time bins kept for plots (adaptive width: memory flat in bag length)
MAX_PENDING = 20_000     # recomputed outputs waiting for their recorded counterpart (20 s at 1 kHz)
RECHECK_EXCLUDED_KEYS = ("compute_time",)  # wall-clock figures cannot be reproduced


class SeriesBins:
    """Per-joint min/max torque, max utilisation and min limit in time bins over log time.

    The bin width doubles (pairs merge) whenever the bag outgrows :data:`MAX_BINS` bins."""

    def __init__(self, nv: int, t0_ns: int, width_ns: int = 10_000_000):
        self.t0, self.width, self.nv = t0_ns, width_ns, nv
        self.n = 0
        self.tau_min = np.full((MAX_BINS, nv), np.inf)
        self.tau_max = np.full((MAX_BINS, nv), -np.inf)
        self.util = np.zeros((MAX_BINS, nv))
        self.limit = np.full((MAX_BINS, nv), np.inf)
        # measured effort, signed like the model torque (NaN: none measured in the bin)
        self.meas_min = np.full((MAX_BINS, nv), np.nan)
        self.meas_max = np.full((MAX_BINS, nv), np.nan)
        self.count = np.zeros(MAX_BINS, dtype=np.int64)

    def _merge(self) -> None:
        half = MAX_BINS // 2
        for arr, red in ((self.tau_min, np.minimum), (self.tau_max, np.maximum),
                         (self.util, np.maximum), (self.limit, np.minimum)):
            arr[:half] = red(arr[0::2], arr[1::2])
            arr[half:] = np.inf if red is np.minimum else (-np.inf if arr is self.tau_max else 0.0)
        for arr, red in ((self.meas_min, np.fmin), (self.meas_max, np.fmax)):
            arr[:half] = red(arr[0::2], arr[1::2])
            arr[half:] = np.nan
        self.count[:half] = self.count[0::2] + self.count[1::2]
        self.count[half:] = 0
        self.width *= 2
        self.n = (self.n + 1) // 2

    def add(self, t_ns: int, tau: np.ndarray, util: np.ndarray, limit: np.ndarray,
            measured: np.ndarray | None = None) -> None:
        i = max((t_ns - self.t0) // self.width, 0)
        while i >= MAX_BINS:
            self._merge()
            i = max((t_ns - self.t0) // self.width, 0)
        np.minimum(self.tau_min[i], tau, out=self.tau_min[i])
        np.maximum(self.tau_max[i], tau, out=self.tau_max[i])
        np.fmax(self.util[i], util, out=self.util[i])
        np.minimum(self.limit[i], limit, out=self.limit[i])
        if measured is not None:
            np.fmin(self.meas_min[i], measured, out=self.meas_min[i])
            np.fmax(self.meas_max[i], measured, out=self.meas_max[i])
        self.count[i] += 1
        if i >= self.n:
            self.n = i + 1

    def add_batch(self, t_ns: np.ndarray, tau: np.ndarray, util: np.ndarray, limit: np.ndarray,
                  measured: np.ndarray) -> None:
        """Rows of :meth:`add` at once (same result; ``measured`` NaN where not measured)."""
        idx = np.maximum((t_ns - self.t0) // self.width, 0)
        while idx.max() >= MAX_BINS:
            self._merge()
            idx = np.maximum((t_ns - self.t0) // self.width, 0)
        if np.all(idx[1:] >= idx[:-1]):
            starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
            b = idx[starts]
            self.tau_min[b] = np.minimum(self.tau_min[b], np.minimum.reduceat(tau, starts))
            self.tau_max[b] = np.maximum(self.tau_max[b], np.maximum.reduceat(tau, starts))
            self.util[b] = np.fmax(self.util[b], np.fmax.reduceat(util, starts))
            self.limit[b] = np.minimum(self.limit[b], np.minimum.reduceat(limit, starts))
            self.meas_min[b] = np.fmin(self.meas_min[b], np.fmin.reduceat(measured, starts))
            self.meas_max[b] = np.fmax(self.meas_max[b], np.fmax.reduceat(measured, starts))
            self.count[b] += np.diff(np.r_[starts, len(idx)])
        else:  # log time went backwards inside the batch: slower unbuffered path
            np.minimum.at(self.tau_min, idx, tau)
            np.maximum.at(self.tau_max, idx, tau)
            np.fmax.at(self.util, idx, util)
            np.minimum.at(self.limit, idx, limit)
            np.fmin.at(self.meas_min, idx, measured)
            np.fmax.at(self.meas_max, idx, measured)
            np.add.at(self.count, idx, 1)
        self.n = max(self.n, int(idx.max()) + 1)


class Pending:
    """Recomputed outputs keyed by header stamp, waiting for the recorded one (bounded FIFO)."""

    def __init__(self) -> None:
        self.d: OrderedDict[int, list] = OrderedDict()
        self.evicted = 0

    def put(self, key: int, value: Any) -> None:
        self.d.setdefault(key, []).append(value)
        if len(self.d) > MAX_PENDING:
            self.evicted += len(self.d.popitem(last=False)[1])

    def left(self) -> int:
        """Values never taken: evicted ones and those still waiting."""
        return self.evicted + sum(len(v) for v in self.d.values())

    def take(self, key: int) -> Any:
        lst = self.d.get(key)
        if not lst:
            return None
        v = lst.pop(0)
        if not lst:
            del self.d[key]
        return v


class Recheck:
    def __init__(self) -> None:
        self.matched = 0
        self.unmatched = 0
        self.max_diff = 0.0
        self.mismatched_values = 0
        self.worst: dict | None = None

    def diff(self, d: float, where: dict) -> None:
        self.matched += 1
        if not d <= self.max_diff:  # also catches NaN
            self.max_diff = d if not math.isnan(d) else math.inf
            self.worst = where

    def to_dict(self, unanswered: int = 0) -> dict:
        """``unmatched``: recorded outputs with no recomputed counterpart (a real discrepancy);
        ``unanswered``: recomputed outputs the bag has no recorded output for (inputs the node
        did not answer: taken before it had a model, or after the recording stopped)."""
        out = {"matched": self.matched, "unmatched": self.unmatched, "unanswered": unanswered,
               "max_abs_difference": self.max_diff if self.matched else None,
               "identical": bool(self.matched and self.max_diff == 0.0 and not self.mismatched_values)}
        if self.mismatched_values:
            out["mismatched_non_numeric_values"] = self.mismatched_values
        if self.worst:
            out["worst"] = self.worst
        return out


def worst_status_difference(recorded: Any, mine: dict[str, dict[str, str]]
                            ) -> tuple[float, dict | None, int]:
    """(largest numeric difference, where it is, number of differing non-numeric values) between
    recorded DiagnosticStatus values and the recomputed ones (wall-clock keys excluded). A status
    (a joint's or a task place's) that only one side has counts as one differing value."""
    worst, where = 0.0, None
    mismatched = len({st.name for st in recorded} ^ set(mine))
    for st in recorded:
        ref = mine.get(st.name)
        if ref is None:
            continue
        for kv in st.values:
            if kv.key not in ref or any(x in kv.key for x in RECHECK_EXCLUDED_KEYS):
                continue
            a, b = kv.value, ref[kv.key]
            try:
                fa, fb = float(a), float(b)
            except ValueError:
                mismatched += a != b
                continue
            if fa == fb or (math.isnan(fa) and math.isnan(fb)):
                continue
            d = abs(fa - fb) if math.isfinite(fa) and math.isfinite(fb) else math.inf
            if d > worst:
                worst, where = d, {"status": st.name, "key": kv.key, "recorded": a, "recomputed": b}
    return worst, where, mismatched


def output_stamp_ns(t_s: float) -> int:
    """The header stamp (ns) the node gives an output whose input had a zero stamp: the receipt
    time in seconds, split into sec/nanosec exactly as ``ros_convert.s_to_stamp`` does."""
    sec = int(t_s // 1)
    nanosec = int(round((t_s - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return sec * 1_000_000_000 + nanosec
