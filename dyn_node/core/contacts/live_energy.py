"""Kinetic energy and the configured frames' speed and transferred energy over a diagnostics
period, against the limits YAML's ``frame_limits`` and ``robot_limits`` (the trajectory check's
task limits, here on the measured joint states).

The period's states are kept and evaluated once, when the period closes, by the batched frame
kernel (:class:`~dyn_node.core.check.frames.FrameKinematics`), so the 1 kHz path only appends two
references per sample; :meth:`LiveEnergy.swap` hands a period over without evaluating it, so
the node evaluates it off its joint_states lock. Pure: the node and the audit get the same peaks
from the same samples.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.frames import FrameKinematics, FramePoint
from dyn_node.core.robot.model import RobotModel

#: states kept per period at most (about 3.5 minutes at 1 kHz); later ones are counted, not kept
MAX_STATES = 200_000


@dataclass(frozen=True)
class FramePeak:
    """One configured frame over the period: peak speed (m/s) and transferred energy ½·m_u·v²
    (J, advisory) and their limits (inf: not limited)."""

    frame: str
    speed_m_s: float
    speed_limit_m_s: float
    energy_j: float
    energy_limit_j: float


@dataclass(frozen=True)
class EnergyPeaks:
    """``kinetic_j`` ½q̇ᵀM(q)q̇ at the period's last state, ``kinetic_peak_j`` its largest
    (NaN when no limit is configured: only the last state is evaluated then); ``states``
    evaluated, ``skipped`` beyond :data:`MAX_STATES`."""

    kinetic_j: float
    kinetic_peak_j: float
    kinetic_limit_j: float
    frames: tuple[FramePeak, ...]
    states: int
    skipped: int


class LiveEnergy:
    """Collects one period's states (model order) and evaluates them at :meth:`close`."""

    def __init__(self, model: RobotModel, *, include_armature: bool = True):
        # here, not at the first period: loading the compiled kernel is slow, and the first
        # /diagnostics tick would otherwise pay for it
        from dyn_node.core.compiled import frame_kernels  # noqa: F401
        tl = model.task_limits
        self.frame_limits = tuple(tl.frame_limits)
        rl = tl.robot_limits
        self.kinetic_limit_j = rl.max_kinetic_energy if rl is not None else math.inf
        # without a limit only the last state is evaluated (its kinetic energy), not the period
        self.limited = bool(self.frame_limits) or math.isfinite(self.kinetic_limit_j)
        points = [FramePoint(f.frame, tuple(f.point)) for f in self.frame_limits]
        self._kin = FrameKinematics(model, points, include_armature=include_armature)
        self._q: list[np.ndarray] = []
        self._v: list[np.ndarray] = []
        self._skipped = 0
        self._n = 0  # states of the period when they are not kept (no limit configured)
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, q: np.ndarray, v: np.ndarray) -> None:
        self._last = (q, v)
        if not self.limited:
            self._n += 1
        elif len(self._q) < MAX_STATES:
            self._q.append(q)
            self._v.append(v)
        else:
            self._skipped += 1

    def add_rows(self, Q: np.ndarray, V: np.ndarray) -> None:
        """N states at once (N×nv), as :meth:`add` row by row."""
        n = len(Q)
        if not n:
            return
        self._last = (Q[-1], V[-1])
        if not self.limited:
            self._n += n
            return
        room = max(0, MAX_STATES - len(self._q))
        self._q.extend(Q[:room])
        self._v.extend(V[:room])
        self._skipped += max(0, n - room)

    def swap(self) -> "EnergyPeriod":
        """The period's states, and a new, empty period: cheap (no evaluation), so the node can
        take it under its joint_states lock and :meth:`EnergyPeriod.evaluate` it outside."""
        period = EnergyPeriod(self, self._q, self._v, self._last, self._n + len(self._q),
                              self._skipped)
        self._q, self._v, self._skipped, self._n = [], [], 0, 0
        return period

    def close(self) -> EnergyPeaks | None:
        """:meth:`swap` then :meth:`EnergyPeriod.evaluate`."""
        return self.swap().evaluate()

    def _evaluate(self, p: "EnergyPeriod") -> EnergyPeaks | None:
        if not p.q:
            if p.last is None:
                return None
            q, v = p.last
            ke = self._kin.compute(q[None, :], v[None, :], np.zeros((1, self._kin.nv)),
                                   base=False).inertia.kinetic_energy
            return EnergyPeaks(float(ke[-1]), math.nan, self.kinetic_limit_j, (), p.states,
                               p.skipped)
        Q, V = np.array(p.q), np.array(p.v)
        batch = self._kin.compute(Q, V, np.zeros_like(Q), base=False)
        ke = batch.inertia.kinetic_energy
        frames = []
        for f, lim in zip(batch.frames, self.frame_limits):
            frames.append(FramePeak(lim.frame, float(f.speed.max()), lim.max_linear_speed,
                                    float(np.nanmax(f.transferred_energy)),
                                    lim.max_transferred_energy))
        peak = float(ke.max())
        return EnergyPeaks(float(ke[-1]), peak, self.kinetic_limit_j, tuple(frames), p.states,
                           p.skipped)


@dataclass(frozen=True)
class EnergyPeriod:
    """One closed period's states (:meth:`LiveEnergy.swap`), not yet evaluated. A period without
    states, or without a configured limit, evaluates only the last state known."""

    energy: LiveEnergy
    q: list[np.ndarray]  # handed over, not copied: swap() starts new lists
    v: list[np.ndarray]
    last: tuple[np.ndarray, np.ndarray] | None
    states: int
    skipped: int

    def evaluate(self) -> EnergyPeaks | None:
        """The period's peaks (None: no state known yet); its peaks are NaN and its frames not
        given when only the last state is evaluated. Uses the LiveEnergy's kernel buffers: one
        evaluation at a time."""
        return self.energy._evaluate(self)


__all__ = ["LiveEnergy", "EnergyPeriod", "EnergyPeaks", "FramePeak", "MAX_STATES"]
