"""The power balance of the robot over a period: where the energy the actuators put in went.

balance = ∫ τ_mᵀq̇ dt − ΔE, the energy friction and the environment took out; a balance that stays
negative means the environment is pushing the robot or the model is wrong (derivation and
discretisation: docs/OBSERVER.md). Pure: times are passed in.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dyn_node.core.compiled import observer_kernels as ok
from dyn_node.core.robot.dynamics import Dynamics


@dataclass(frozen=True, kw_only=True)
class PowerBalanceOptions:
    """A period's balance counts as negative below −max(``tolerance_j``, ``relative_tolerance``
    × the gross work ∫|τ_mᵀq̇|dt), so discretisation and noise on a fast motion do not count;
    ``persistent_periods`` negative periods in a row make the reading."""

    tolerance_j: float = 0.05
    relative_tolerance: float = 0.02
    persistent_periods: int = 3


@dataclass(frozen=True)
class PeriodBalance:
    """One period (energies and work in J, times in s)."""

    start_s: float
    end_s: float
    samples: int
    measured_work_j: float
    gross_work_j: float
    friction_work_j: float
    kinetic_start_j: float
    kinetic_end_j: float
    potential_start_j: float
    potential_end_j: float
    tolerance_j: float

    @property
    def delta_energy_j(self) -> float:
        return (self.kinetic_end_j + self.potential_end_j) - (self.kinetic_start_j + self.potential_start_j)

    @property
    def balance_j(self) -> float:
        """Work of the measured torques minus the change in mechanical energy."""
        return self.measured_work_j - self.delta_energy_j

    @property
    def unexplained_j(self) -> float:
        """balance − the model friction's work: −(work done by the environment) if the model is right."""
        return self.balance_j - self.friction_work_j

    @property
    def negative(self) -> bool:
        return self.balance_j < -self.tolerance_j


class PowerBalance:
    """Accumulates samples; :meth:`close` ends a period and starts the next at its last sample.

    The running sums live in ``state`` (:mod:`dyn_node.core.compiled.observer_kernels`' P_* layout), which
    the contact monitor's compiled pass updates in place (then :meth:`noted` keeps the states
    whose energies a period needs); :meth:`update` is the same step for one sample."""

    def __init__(self, dynamics: Dynamics, *, options: PowerBalanceOptions = PowerBalanceOptions()):
        if not (options.tolerance_j >= 0 and options.relative_tolerance >= 0
                and math.isfinite(options.tolerance_j) and math.isfinite(options.relative_tolerance)):
            raise ValueError("tolerances must be finite and ≥ 0")
        if options.persistent_periods < 1:
            raise ValueError("persistent_periods must be ≥ 1")
        self.dynamics = dynamics
        self.options = options
        self._nv = dynamics.nv
        self.state = np.zeros(9)
        self._first: tuple[float, np.ndarray, np.ndarray] | None = None
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None
        self._first_energy = (math.nan, math.nan)
        #: negative periods in a row, up to the last closed one
        self.negative_run = 0
        self.last: PeriodBalance | None = None

    @property
    def broken_periods(self) -> int:
        """Periods discarded because a sample broke the integral."""
        return int(self.state[ok.P_BROKEN])

    def _energies(self, q: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        """(kinetic, potential) at a sample: only a period's first and last need them."""
        d = self.dynamics
        return 0.5 * float(v @ d.mass_matrix(q) @ v), d.potential_energy(q)

    def restart(self) -> None:
        """Discard the open period (if it had begun) and start over at the next sample."""
        ok._power_restart(self.state)
        self._first = self._last = None

    def dropped(self) -> None:
        """The compiled pass restarted the period (a sample it could not use): forget its states."""
        self._first = self._last = None

    def noted(self, t: float, q: np.ndarray, v: np.ndarray, step: int) -> None:
        """After the compiled pass took a sample at t (``step`` as power_step returns): keep
        the states a period's energies are taken at (callers pass arrays they do not modify)."""
        if step == 2:
            return
        if step == 1:
            self._first, self._first_energy = (t, q, v), (math.nan, math.nan)
        self._last = (t, q, v)

    def update(self, t: float, q: Sequence[float], v: Sequence[float] | None,
               effort: Sequence[float] | None) -> bool:
        """Add one sample (model order); False when it cannot be used (no velocity or effort,
        a non-finite value), which restarts the period; a step back in time restarts it too."""
        if v is None or effort is None or not math.isfinite(t):
            self.restart()
            return False
        q, v, e = (np.array(x, dtype=float) for x in (q, v, effort))  # copies: samples are kept
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v)) and np.all(np.isfinite(e))):
            self.restart()
            return False
        # summed in index order, as the compiled pass does: a BLAS dot's order depends on the
        # arrays' alignment, and the two must agree to the bit
        pw = fw = 0.0
        for ei, fi, vi in zip(e.tolist(), self.dynamics.friction(v).tolist(), v.tolist()):
            pw += ei * vi
            fw += fi * vi
        self.noted(t, q, v, ok.power_step(self.state, t, pw, fw))
        return True

    def close(self) -> PeriodBalance | None:
        """End the period at the last sample (None when it has fewer than two samples) and
        start the next one there."""
        st = self.state
        a, b = self._first, self._last
        n = int(st[ok.P_N])
        if a is None or b is None or n < 2:
            return None
        o = self.options
        if math.isnan(self._first_energy[0]):
            self._first_energy = self._energies(a[1], a[2])
        (k0, u0), (k1, u1) = self._first_energy, self._energies(b[1], b[2])
        gross = float(st[ok.P_GROSS])
        out = PeriodBalance(start_s=a[0], end_s=b[0], samples=n, measured_work_j=float(st[ok.P_WORK]),
                            gross_work_j=gross, friction_work_j=float(st[ok.P_FRICTION]),
                            kinetic_start_j=k0, kinetic_end_j=k1, potential_start_j=u0, potential_end_j=u1,
                            tolerance_j=max(o.tolerance_j, o.relative_tolerance * gross))
        self.negative_run = self.negative_run + 1 if out.negative else 0
        self.last = out
        self._first, self._first_energy = b, (k1, u1)
        st[ok.P_N] = 1.0
        st[ok.P_WORK] = st[ok.P_GROSS] = st[ok.P_FRICTION] = 0.0
        return out

    @property
    def persistent_negative(self) -> bool:
        return self.negative_run >= self.options.persistent_periods

    def reading(self) -> str:
        """One line on the last period; names the persistent-negative reading when it holds."""
        p = self.last
        if p is None:
            return "power balance: no complete period yet"
        head = (f"power balance {p.balance_j:.3g} J over {p.end_s - p.start_s:.3g} s "
                f"(measured work {p.measured_work_j:.3g} J, energy change {p.delta_energy_j:.3g} J)")
        if self.persistent_negative:
            return (f"{head}: negative for {self.negative_run} periods in a row: the environment "
                    "is pushing the robot, or the model (masses, friction, torque scale) is wrong")
        return head
