"""Contact and collision episodes from the external-torque estimate.

|τ̂_ext,i| against ``contact_threshold``·L_i and ``collision_threshold``·L_i, each held for
``min_duration_s``, with hysteresis on release (rules: docs/OBSERVER.md). Pure: times are passed
in, so a replay from a bag gives the same episodes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from dyn_node.core.observer import WrenchEstimate, per_joint

NONE, CONTACT, COLLISION = "none", "contact", "collision"
#: durations are compared with this slack: stamps are whole nanoseconds, and a run of 20
#: samples 1 ms apart must last 0.02 s although its float seconds differ by ~1e-17
STAMP_RESOLUTION_S = 1e-9


@dataclass(frozen=True, kw_only=True)
class ContactOptions:
    """Thresholds as fractions of each joint's effort limit (one value or one per joint),
    ``min_duration_s`` (s) and the hysteresis ``release_fraction`` of the contact threshold."""

    contact_threshold: float | Sequence[float] = 0.05
    collision_threshold: float | Sequence[float] = 0.20
    min_duration_s: float = 0.02
    release_fraction: float = 0.5
    #: ended episodes kept in ``history`` (None: all; a long-running node keeps the latest)
    history_limit: int | None = None


@dataclass(frozen=True)
class JointPeak:
    """A joint that went over its contact threshold: its largest |τ̂_ext| (N·m|N) and ratio."""

    joint: str
    torque: float
    ratio: float
    limit: float
    unit: str


@dataclass(frozen=True)
class ContactEpisode:
    """One contact. Times in s (the samples' clock); ``end_s`` None while it lasts.

    ``joints``: every joint that went over its contact threshold, largest ratio first;
    ``peak_ratio`` = ``joints[0].ratio``; ``peak_wrench`` (6, N and N·m at ``frame``, its axes)
    the wrench estimate with the largest force seen, ``peak_force_n`` its force (None when no
    wrench was estimated); ``end_reason`` why it ended."""

    start_s: float
    level: str
    joints: tuple[JointPeak, ...]
    frame: str | None = None
    peak_wrench: np.ndarray | None = None
    peak_force_n: float | None = None
    end_s: float | None = None
    end_reason: str | None = None

    @property
    def peak_ratio(self) -> float:
        return self.joints[0].ratio if self.joints else 0.0

    def duration_s(self, now_s: float | None = None) -> float:
        end = self.end_s if self.end_s is not None else now_s
        return float(end - self.start_s) if end is not None else 0.0

    def message(self, now_s: float | None = None) -> str:
        """``collision: 38 N at panda_link8 (panda_joint4 14.1 N·m of 87), 0.12 s``: the peak
        force, the joints at their peaks (up to three) and the duration (so far)."""
        joints = ", ".join(f"{j.joint} {j.torque:.3g} {j.unit} of {j.limit:.4g}" for j in self.joints[:3])
        if len(self.joints) > 3:
            joints += f", +{len(self.joints) - 3} more"
        where = (f"{self.peak_force_n:.3g} N at {self.frame or 'the contact frame'} ({joints})"
                 if self.peak_force_n is not None else joints)
        return f"{self.level}: {where}, {self.duration_s(now_s):.2f} s"


@dataclass(frozen=True)
class ContactState:
    """After one sample: ``state`` (``none``, ``contact``, ``collision``), the open episode,
    the episode that ended on this sample (if any), ``available`` (False: no estimate this
    sample, ``reason`` says why) and the per-joint ratios |τ̂|/L (None without estimate)."""

    t: float
    state: str
    episode: ContactEpisode | None
    ended: ContactEpisode | None
    available: bool
    reason: str | None
    ratios: np.ndarray | None


class _Run:
    """Since when a condition has held on every sample (None: it does not hold now)."""

    def __init__(self) -> None:
        self.since: float | None = None

    def update(self, t: float, holds: bool) -> float:
        """The condition's duration so far (−inf when it does not hold)."""
        if not holds:
            self.since = None
            return -math.inf
        if self.since is None:
            self.since = t
        return t - self.since


class ContactDetector:
    """The episode state machine for one robot (joint names, effort limits, units in model
    order) and one contact frame (the wrench estimates' frame; None: torques only)."""

    def __init__(self, joint_names: Sequence[str], effort_limit: Sequence[float], *,
                 units: Sequence[str] | None = None, frame: str | None = None,
                 options: ContactOptions = ContactOptions()):
        nv = len(joint_names)
        self.names = tuple(joint_names)
        self.limit = np.asarray(effort_limit, dtype=float)
        if self.limit.shape != (nv,) or np.any(np.isnan(self.limit)) or np.any(self.limit < 0):
            raise ValueError(f"effort_limit needs {nv} values ≥ 0")
        self.units = tuple(units) if units is not None else ("N·m",) * nv
        self.contact = per_joint(options.contact_threshold, nv, "contact_threshold")
        self.collision = per_joint(options.collision_threshold, nv, "collision_threshold")
        if np.any(self.collision < self.contact):
            raise ValueError("collision_threshold must be ≥ contact_threshold on every joint")
        if not (options.min_duration_s >= 0 and math.isfinite(options.min_duration_s)):
            raise ValueError(f"min_duration_s must be finite and ≥ 0, got {options.min_duration_s}")
        if not 0 < options.release_fraction <= 1:
            raise ValueError(f"release_fraction must be in (0, 1], got {options.release_fraction}")
        self.options = options
        self.frame = frame
        # torque levels per joint (N·m|N); an infinite limit never triggers
        self._contact_at = self.contact * self.limit
        self._collision_at = self.collision * self.limit
        self._release_at = options.release_fraction * self._contact_at
        self._zero_limit = self.limit == 0
        self._any_zero_limit = bool(self._zero_limit.any())
        with np.errstate(divide="ignore"):
            self._inv_limit = np.where(self._zero_limit, 0.0, 1.0 / self.limit)  # inf limit → 0
        self._over_contact = _Run()
        self._over_collision = _Run()
        self._candidate: ContactEpisode | None = None  # peaks since the current over-threshold run began
        self.episode: ContactEpisode | None = None
        #: episodes that ended, oldest first (the latest ``history_limit``), and how many ended
        self.history: list[ContactEpisode] = []
        self.ended = 0

    @property
    def state(self) -> str:
        return self.episode.level if self.episode is not None else NONE

    def _end(self, t: float, reason: str) -> ContactEpisode | None:
        ended = None
        if self.episode is not None:
            ended = replace(self.episode, end_s=t, end_reason=reason)
            self.history.append(ended)
            self.ended += 1
            limit = self.options.history_limit
            if limit is not None and len(self.history) > limit:
                del self.history[:len(self.history) - limit]
        self.episode = self._candidate = None
        self._over_contact.since = self._over_collision.since = None
        return ended

    def unavailable(self, t: float, reason: str) -> ContactState:
        """A sample without estimate: an open episode ends here (its end is not observable)."""
        ended = self._end(t, f"no estimate: {reason}")
        return ContactState(t, NONE, None, ended, False, reason, None)

    def _fold(self, ep: ContactEpisode, tau: np.ndarray, ratios: np.ndarray, over: np.ndarray,
              wrench: WrenchEstimate | None) -> ContactEpisode:
        peaks = {j.joint: j for j in ep.joints}
        for i in np.flatnonzero(over):
            n = self.names[i]
            if n not in peaks or ratios[i] > peaks[n].ratio:
                peaks[n] = JointPeak(n, float(abs(tau[i])), float(ratios[i]), float(self.limit[i]), self.units[i])
        joints = tuple(sorted(peaks.values(), key=lambda j: -j.ratio))
        pw, pf = ep.peak_wrench, ep.peak_force_n
        if wrench is not None and (pf is None or wrench.force_n > pf):
            pw, pf = wrench.wrench.copy(), wrench.force_n
        return replace(ep, joints=joints, peak_wrench=pw, peak_force_n=pf)

    def update(self, t: float, tau_ext: np.ndarray | None, wrench: WrenchEstimate | None = None,
               reason: str | None = None) -> ContactState:
        """One sample of τ̂_ext (nv, model order; None: no estimate, ``reason`` why) and,
        optionally, the wrench estimate at the contact frame."""
        if tau_ext is None:
            return self.unavailable(t, reason or "no external-torque estimate")
        tau = np.abs(np.asarray(tau_ext, dtype=float))
        if tau.shape != self.limit.shape:
            raise ValueError(f"tau_ext needs {len(self.names)} values in model order, got shape {tau.shape}")
        # a sum of |τ| is NaN or inf iff an element is (or it overflows: then each element decides)
        if not math.isfinite(float(tau.sum())) and not np.all(np.isfinite(tau)):
            return self.unavailable(t, "external-torque estimate not finite")
        ratios = tau * self._inv_limit
        if self._any_zero_limit:
            ratios[self._zero_limit] = np.where(tau[self._zero_limit] > 0, np.inf, 0.0)
        over = tau > self._contact_at
        min_d = self.options.min_duration_s - STAMP_RESOLUTION_S
        contact_for = self._over_contact.update(t, bool(over.any()))
        collision_for = self._over_collision.update(t, bool((tau > self._collision_at).any()))
        ended = None
        if self.episode is None:
            if contact_for < 0:
                self._candidate = None
            else:
                if self._candidate is None:
                    self._candidate = ContactEpisode(start_s=t, level=CONTACT, joints=(), frame=self.frame)
                self._candidate = self._fold(self._candidate, tau, ratios, over, wrench)
                if contact_for >= min_d:
                    self.episode, self._candidate = self._candidate, None
        else:
            if bool(np.all(tau < self._release_at)):
                ended = self._end(t, "every joint below half its contact threshold")
            else:
                self.episode = self._fold(self.episode, tau, ratios, over, wrench)
        if self.episode is not None and collision_for >= min_d and self.episode.level != COLLISION:
            self.episode = replace(self.episode, level=COLLISION)
        return ContactState(t, self.state, self.episode, ended, True, None, ratios)
