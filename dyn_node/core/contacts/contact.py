"""Contact and collision episodes from the external-torque estimate.

|τ̂_ext,i| against ``contact_threshold``·L_i and ``collision_threshold``·L_i, each held for
``min_duration_s``, with hysteresis on release (rules: docs/OBSERVER.md). Pure: times are passed
in, so a replay from a bag gives the same episodes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple, Sequence

import numpy as np

from dyn_node.core.contacts.observer import WrenchEstimate, per_joint

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


class _RowWrench(NamedTuple):
    """One row of :meth:`ContactDetector.update_rows`'s wrench arrays, shaped like the two
    fields of a :class:`WrenchEstimate` the peak rule reads."""

    wrench: np.ndarray
    force_n: float


def _peak_wrench(pw: np.ndarray | None, pf: float | None,
                 wrench: WrenchEstimate | _RowWrench | None) -> tuple[np.ndarray | None, float | None]:
    """The peak rule for the wrench, one sample: the first one, then a strictly larger force."""
    if wrench is not None and (pf is None or wrench.force_n > pf):
        return wrench.wrench.copy(), wrench.force_n
    return pw, pf


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
        self._index = {n: i for i, n in enumerate(self.names)}
        self._unique_names = len(self._index) == nv  # else the peaks of same-named joints merge
        self._over_contact = _Run()
        self._over_collision = _Run()
        self._candidate: ContactEpisode | None = None  # peaks since the current over-threshold run began
        self.episode: ContactEpisode | None = None
        #: episodes that ended, oldest first (the latest ``history_limit``), and how many ended
        self.history: list[ContactEpisode] = []
        self.ended = 0

    @property
    def contact_level(self) -> np.ndarray:
        """The torque per joint (N·m|N) over which a sample counts as contact."""
        return self._contact_at

    @property
    def idle(self) -> bool:
        """No episode, no candidate and no run under way: a finite sample with every joint
        below its contact level changes nothing (the live path then skips :meth:`update`)."""
        return (self.episode is None and self._candidate is None
                and self._over_contact.since is None and self._over_collision.since is None)

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
              wrench: WrenchEstimate | _RowWrench | None) -> ContactEpisode:
        """One sample folded into ``ep``'s peaks (``tau`` already |τ̂_ext|)."""
        joints = self._peak_joints(ep.joints, tau, ratios, over)
        pw, pf = _peak_wrench(ep.peak_wrench, ep.peak_force_n, wrench)
        return replace(ep, joints=joints, peak_wrench=pw, peak_force_n=pf)

    def _peak_joints(self, joints: tuple[JointPeak, ...], tau: np.ndarray, ratios: np.ndarray,
                     over: np.ndarray) -> tuple[JointPeak, ...]:
        """The peak rule for joints, one sample: a joint over its contact level enters, or
        replaces its peak on a strictly larger ratio; largest ratio first (ties: as before)."""
        peaks = {j.joint: j for j in joints}
        for i in np.flatnonzero(over):
            n = self.names[i]
            if n not in peaks or ratios[i] > peaks[n].ratio:
                peaks[n] = JointPeak(n, float(abs(tau[i])), float(ratios[i]), float(self.limit[i]), self.units[i])
        return tuple(sorted(peaks.values(), key=lambda j: -j.ratio))

    def _ratios(self, tau: np.ndarray) -> np.ndarray:
        """|τ̂|/L (any shape ending in nv; ``tau`` already |τ̂_ext|): a zero limit gives inf for
        any torque, 0 for none; an infinite limit 0."""
        ratios = tau * self._inv_limit
        if self._any_zero_limit:
            ratios[..., self._zero_limit] = np.where(tau[..., self._zero_limit] > 0, np.inf, 0.0)
        return ratios

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
        ratios = self._ratios(tau)
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

    def update_rows(self, t: np.ndarray, tau: np.ndarray, force_n: np.ndarray, wrench: np.ndarray,
                    has_wrench: np.ndarray, unavailable: dict[int, str]) -> list[ContactEpisode]:
        """Many samples at once, exactly as :meth:`update` / :meth:`unavailable` row by row
        (the same state afterwards, the same episodes, bit for bit); returns the episodes that
        ended during the call, oldest first.

        ``t`` (N,) s, non-decreasing; ``tau`` (N, nv) τ̂_ext in model order; ``force_n`` (N,)
        and ``wrench`` (N, 6) the wrench estimate, read only where ``has_wrench`` (N, bool) (the
        row's wrench, else None); ``unavailable``: row → reason for rows without estimate (their
        ``tau`` is not used). Python work is per episode, not per row: quiet rows are skipped,
        the rows of an open episode are folded with array reductions up to the row that ends
        it, and only the rows of a starting contact (until it lasts ``min_duration_s``) and the
        rows that end an episode go through :meth:`update` / :meth:`unavailable`."""
        t = np.asarray(t, dtype=float)
        if t.ndim != 1:
            raise ValueError(f"t needs shape (N,), got {t.shape}")
        n, nv = t.shape[0], len(self.names)
        tau = np.asarray(tau, dtype=float)
        if tau.shape != (n, nv):
            raise ValueError(f"tau needs shape ({n}, {nv}) (rows, joints in model order), got {tau.shape}")
        force_n = np.asarray(force_n, dtype=float)
        wrench = np.asarray(wrench)
        has = np.asarray(has_wrench, dtype=bool)
        if force_n.shape != (n,) or wrench.shape != (n, 6) or has.shape != (n,):
            raise ValueError(f"force_n, wrench, has_wrench need shapes ({n},), ({n}, 6), ({n},); got "
                             f"{force_n.shape}, {wrench.shape}, {has.shape}")
        reasons: dict[int, str] = {}
        for k, why in unavailable.items():
            i = int(k)
            if i != k or not 0 <= i < n:
                raise ValueError(f"unavailable row {k!r} is not a row index in [0, {n})")
            reasons[i] = why
        ended: list[ContactEpisode] = []
        if n == 0:
            return ended

        absf = np.abs(tau)
        rows_out = np.fromiter(reasons, dtype=np.intp, count=len(reasons))
        absf[rows_out] = 0.0  # never read: these rows are events of their own
        bad = ~np.isfinite(absf).all(axis=1)  # update() calls unavailable() on these
        bad[rows_out] = True
        over = absf > self._contact_at
        any_over = over.any(axis=1) & ~bad
        stop = bad | ((absf < self._release_at).all(axis=1) & ~bad)  # where an episode ends
        starts = np.flatnonzero(any_over)
        stops = np.flatnonzero(stop)

        def step(k: int) -> None:  # one row through the per-sample path
            if k in reasons:
                st = self.unavailable(t[k], reasons[k])
            else:
                w = _RowWrench(wrench[k], float(force_n[k])) if has[k] else None
                st = self.update(t[k], tau[k], w)
            if st.ended is not None:
                ended.append(st.ended)

        k = 0
        while k < n:
            if self.episode is None:
                if (self._candidate is None and self._over_contact.since is None
                        and self._over_collision.since is None):
                    # nothing open: rows under every contact level and rows without estimate
                    # change nothing; the next row over a contact level may start one
                    i = int(np.searchsorted(starts, k))
                    if i == starts.size:
                        break
                    k = int(starts[i])
                step(k)  # a candidate: row by row until it lasts min_duration_s or ends
                k += 1
            elif stop[k]:
                step(k)  # the episode ends here
                k += 1
            else:
                i = int(np.searchsorted(stops, k))
                e = int(stops[i]) if i < stops.size else n
                self._fold_run(t[k:e], absf[k:e], over[k:e], any_over[k:e], force_n[k:e],
                               wrench[k:e], has[k:e])
                k = e
        return ended

    def _fold_run(self, t: np.ndarray, tau: np.ndarray, over: np.ndarray, any_over: np.ndarray,
                  force_n: np.ndarray, wrench: np.ndarray, has: np.ndarray) -> None:
        """Rows of an open episode none of which ends it (finite, some joint at or above its
        release level), folded as :meth:`update` would one by one; ``tau`` |τ̂_ext|."""
        ep = self.episode
        over_collision = (tau > self._collision_at).any(axis=1)
        level = ep.level
        if level != COLLISION and over_collision.any():
            since = _run_since(t, over_collision, self._over_collision.since)
            lasted = t - since  # where over_collision holds
            if np.any(over_collision & (lasted >= self.options.min_duration_s - STAMP_RESOLUTION_S)):
                level = COLLISION
        self._over_contact.since = _last_since(t, any_over, self._over_contact.since)
        self._over_collision.since = _last_since(t, over_collision, self._over_collision.since)
        joints = ep.joints
        rows = np.flatnonzero(any_over)
        if rows.size:
            joints = self._peak_joints_rows(joints, tau[rows], over[rows])
        pw, pf = ep.peak_wrench, ep.peak_force_n
        rows = np.flatnonzero(has)
        if rows.size:
            if pf is None:  # the first wrench is the peak so far
                r = rows[0]
                pw, pf = _peak_wrench(pw, pf, _RowWrench(wrench[r], float(force_n[r])))
                rows = rows[1:]
            if rows.size:  # then the first of the largest forces, if larger (NaN never is)
                f = force_n[rows]
                r = rows[int(np.argmax(np.where(np.isnan(f), -np.inf, f)))]
                pw, pf = _peak_wrench(pw, pf, _RowWrench(wrench[r], float(force_n[r])))
        self.episode = replace(ep, level=level, joints=joints, peak_wrench=pw, peak_force_n=pf)

    def _peak_joints_rows(self, joints: tuple[JointPeak, ...], tau: np.ndarray,
                          over: np.ndarray) -> tuple[JointPeak, ...]:
        """:meth:`_peak_joints` applied row by row (rows with some joint over, |τ̂_ext|)."""
        ratios = self._ratios(tau)
        if not self._unique_names:
            for r in range(tau.shape[0]):
                joints = self._peak_joints(joints, tau[r], ratios[r], over[r])
            return joints
        cand = np.where(over, ratios, -np.inf)
        before = np.full(len(self.names), -np.inf)
        for j in joints:
            before[self._index[j.joint]] = j.ratio
        best = cand.max(axis=0)
        changed = best > before
        if not changed.any():
            return joints
        final = np.where(changed, best, before)
        final = final[final > -np.inf]
        if np.unique(final).size == final.size:
            # no two peaks tie: the order is by ratio alone, each peak the first row at the
            # largest ratio (it replaces the one before only when strictly larger)
            first = cand.argmax(axis=0)
            peaks = {j.joint: j for j in joints}
            for i in np.flatnonzero(changed):
                r = first[i]
                peaks[self.names[i]] = JointPeak(self.names[i], float(abs(tau[r, i])), float(ratios[r, i]),
                                                 float(self.limit[i]), self.units[i])
            return tuple(sorted(peaks.values(), key=lambda j: -j.ratio))
        # tied peaks keep the order their history gives: replay the rows where some joint's
        # peak changes (on the others the rule changes nothing)
        so_far = np.maximum.accumulate(np.vstack([before, cand[:-1]]), axis=0)
        for r in np.flatnonzero((cand > so_far).any(axis=1)):
            joints = self._peak_joints(joints, tau[r], ratios[r], over[r])
        return joints


def _run_since(t: np.ndarray, holds: np.ndarray, since: float | None) -> np.ndarray:
    """Per row, ``_Run.since`` after it (where ``holds``; elsewhere any value), starting from
    ``since``."""
    idx = np.arange(t.size)
    last_off = np.maximum.accumulate(np.where(holds, -1, idx))
    first = t[0] if since is None else since
    return np.where(last_off >= 0, t[np.minimum(last_off + 1, t.size - 1)], first)


def _last_since(t: np.ndarray, holds: np.ndarray, since: float | None) -> float | None:
    """``_Run.since`` after the last row, starting from ``since``."""
    if not holds[-1]:
        return None
    off = np.flatnonzero(~holds)
    if off.size:
        return t[off[-1] + 1]
    return t[0] if since is None else since
