"""What the live monitor produces: one message's result, a batch's results, and the running counts."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dyn_node.errors import InputError


@dataclass(frozen=True)
class SampleResult:
    """What one joint_states message produced. When ``accepted`` is False only ``error`` is set.

    Arrays are in model order, each joint in its own units (revolute|prismatic): q (rad|m),
    v (rad/s|m/s), a_hat (rad/s²|m/s²), gravity and tau (N·m|N),
    residual = measured − tau (N·m|N, NaN where not measured; None when no effort at all),
    utilisation = max(|tau|, |measured|) / effort limit at the current speed.
    ``stamp_s`` is the stamp used (receipt time for a zero stamp).
    """

    accepted: bool
    error: InputError | None = None
    stamp_s: float = 0.0
    q: np.ndarray | None = None
    v: np.ndarray | None = None
    a_hat: np.ndarray | None = None
    gravity: np.ndarray | None = None
    tau: np.ndarray | None = None
    residual: np.ndarray | None = None
    utilisation: np.ndarray | None = None
    measured_ratio: float = float("nan")
    zero_stamp: bool = False
    out_of_order: bool = False
    effort_limit: np.ndarray | None = None  # effort limit at the current speed (N·m|N; inf: none)


_new = object.__new__


def accepted_result(t: float, q: np.ndarray, v: np.ndarray, a: np.ndarray, g: np.ndarray,
                    tau: np.ndarray, residual: np.ndarray | None, util: np.ndarray,
                    measured_ratio: float, zero: bool, ooo: bool, lim: np.ndarray) -> SampleResult:
    """An accepted :class:`SampleResult`, built for the hot path."""
    # The hot path's constructor: the frozen dataclass __init__ sets 14 fields one by one through
    # object.__setattr__ (~2 µs); filling the instance dict directly gives the same object.
    r = _new(SampleResult)
    r.__dict__.update(accepted=True, error=None, stamp_s=t, q=q, v=v, a_hat=a, gravity=g, tau=tau,
                      residual=residual, utilisation=util, measured_ratio=measured_ratio,
                      zero_stamp=zero, out_of_order=ooo, effort_limit=lim)
    return r


@dataclass(frozen=True)
class BatchResult:
    """What :meth:`Monitor.process_batch` produced for N accepted messages: row k holds exactly
    the values :meth:`Monitor.process` returns for message k (same units and order as
    :class:`SampleResult`). ``residual`` is None when the messages carry no effort;
    ``measured_ratio`` is NaN then. ``effort_limit`` may be a read-only broadcast view."""

    stamp_s: np.ndarray          # (N,) s
    q: np.ndarray                # N×nv
    v: np.ndarray
    a_hat: np.ndarray
    gravity: np.ndarray
    tau: np.ndarray
    residual: np.ndarray | None
    utilisation: np.ndarray
    measured_ratio: np.ndarray   # (N,)
    zero_stamp: np.ndarray       # (N,) bool
    out_of_order: np.ndarray     # (N,) bool
    effort_limit: np.ndarray
    measured: np.ndarray | None = None  # (N,) bool: rows with effort (None: all, or none)

    def __len__(self) -> int:
        return len(self.stamp_s)

    def result(self, k: int) -> SampleResult:
        """Row k as the :class:`SampleResult` :meth:`Monitor.process` would have returned."""
        residual = None if self.residual is None or (
            self.measured is not None and not self.measured[k]) else self.residual[k]
        return accepted_result(float(self.stamp_s[k]), self.q[k], self.v[k], self.a_hat[k],
                               self.gravity[k], self.tau[k], residual, self.utilisation[k],
                               float(self.measured_ratio[k]), bool(self.zero_stamp[k]),
                               bool(self.out_of_order[k]), self.effort_limit[k])


@dataclass
class Counts:
    """Totals since the node started (they survive model and settings changes). Every message
    taken lands in exactly one of accepted, invalid and before_model (taken while no model
    existed), so received = accepted + invalid + before_model."""

    received: int = 0
    accepted: int = 0
    invalid: int = 0
    before_model: int = 0
    invalid_by_reason: dict = field(default_factory=dict)
    out_of_order: int = 0
    zero_stamp: int = 0
    dropped: int = 0
    ignored_joint_values: int = 0


__all__ = ["SampleResult", "BatchResult", "Counts", "accepted_result"]
