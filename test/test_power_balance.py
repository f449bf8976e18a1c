"""The power balance on the planar 2-link arm, in closed form (energies, tip motion, push work)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.contacts.power_balance import PowerBalance, PowerBalanceOptions
from robots import G, L1, L2, M1, M2, two_link_terms
from test_observer import READY, two_link_motion


@pytest.fixture(scope="module")
def two_link():
    return Dynamics(load_model(builtin="planar_2link"))


def potential(q):
    """U(q) of the point masses: the arm's plane is the world x-z plane, q = 0 horizontal."""
    return G * ((M1 + M2) * L1 * math.sin(q[0]) + M2 * L2 * math.sin(q[0] + q[1]))


def tip(q):
    """The tool's (x, z) in the world (m)."""
    return np.array([L1 * math.cos(q[0]) + L2 * math.cos(q[0] + q[1]),
                     L1 * math.sin(q[0]) + L2 * math.sin(q[0] + q[1])])


def tip_jacobian(q):
    s1, s12 = math.sin(q[0]), math.sin(q[0] + q[1])
    c1, c12 = math.cos(q[0]), math.cos(q[0] + q[1])
    return np.array([[-L1 * s1 - L2 * s12, -L2 * s12], [L1 * c1 + L2 * c12, L2 * c12]])


def pushed_effort(t, push):
    """Motor torque along two_link_motion while a constant world force ``push`` (Fx, Fz) (N)
    acts at the tool: M q̈ + C q̇ + g − Jᵀ·push."""
    q, v, a = two_link_motion(t)
    M, C, g = two_link_terms(q, v)
    return q, v, M @ a + C @ v + g - tip_jacobian(q).T @ push


def run_period(dyn, dt, push, t1=1.0, **opts):
    pb = PowerBalance(dyn, options=PowerBalanceOptions(**opts))
    for k in range(int(round(t1 / dt)) + 1):
        assert pb.update(k * dt, *pushed_effort(k * dt, push))
    return pb, pb.close()


def test_energies_are_the_closed_form(two_link):
    rng = np.random.default_rng(4)
    for _ in range(20):
        q, v = rng.uniform(-2, 2, 2), rng.uniform(-3, 3, 2)
        assert two_link.potential_energy(q) == pytest.approx(potential(q), abs=1e-12)
        pb = PowerBalance(two_link)
        pb.update(0.0, q, v, np.zeros(2))
        pb.update(0.1, q, v, np.zeros(2))
        p = pb.close()
        M = two_link_terms(q, v)[0]
        assert p.kinetic_end_j == pytest.approx(0.5 * v @ M @ v, abs=1e-12)
        assert p.potential_end_j == pytest.approx(potential(q), abs=1e-12)


def test_no_push_no_friction_balance_is_zero_to_second_order(two_link):
    """The arm swinging through 1 s (energy changes of ~10 J): the balance is the trapezoid's
    error only, below 1e-4 J at 1 kHz and quartered when dt is halved."""
    errs = [abs(run_period(two_link, dt, np.zeros(2))[1].balance_j) for dt in (0.002, 0.001)]
    _, p = run_period(two_link, 0.001, np.zeros(2))
    assert abs(p.delta_energy_j) > 1.0 or p.gross_work_j > 5.0  # a motion that moves energy
    assert errs[1] < 1e-4
    assert 3.0 < errs[0] / errs[1] < 5.0, errs
    assert not p.negative and p.friction_work_j == 0.0


def test_a_push_shows_as_minus_its_work(two_link):
    """A constant −3 N along x and 5 N along z at the tool: its work is F·Δx_tip in closed form;
    the balance equals −W to O(dt²); a negative balance over three periods in a row is the
    persistent reading."""
    push = np.array([-3.0, 5.0])
    pb = PowerBalance(two_link, options=PowerBalanceOptions(persistent_periods=3))
    dt = 0.001
    # periods chosen so the push does work of one sign in each: the tip moves with the force
    bounds, periods = [0.0, 0.12, 0.24, 0.36], []
    k = 0
    for end in bounds[1:]:
        while k * dt <= end + 1e-12:
            pb.update(k * dt, *pushed_effort(k * dt, push))
            k += 1
        periods.append(pb.close())
    for p in periods:
        work = float(push @ (tip(two_link_motion(p.end_s)[0]) - tip(two_link_motion(p.start_s)[0])))
        assert p.balance_j == pytest.approx(-work, abs=5e-5)  # trapezoid: 1.1e-5 J of 1.6 J
        assert p.unexplained_j == p.balance_j  # no friction in this model
        assert work > 0.05 and p.negative
    # periods tile the time line
    assert [p.start_s for p in periods[1:]] == [p.end_s for p in periods[:-1]]
    assert pb.persistent_negative and pb.negative_run == 3
    assert "negative for 3 periods in a row: the environment is pushing the robot" in pb.reading()


def test_friction_takes_its_share():
    """The Panda's URDF damping (0.003 N·m·s/rad): joint 1 spinning at 1 rad/s, driven with the
    model torque (friction included) for 0.4 s: the balance is the friction's work
    0.003·1²·0.4 J, positive, and nothing is unexplained."""
    panda = load_model(builtin="panda")
    d = Dynamics(panda)
    v = np.zeros(7)
    v[0] = 1.0
    pb = PowerBalance(d)
    for k in range(401):
        q = READY.copy()
        q[0] = k * 0.001
        pb.update(k * 0.001, q, v, d.rnea(q, v, np.zeros(7)))
    p = pb.close()
    assert p.friction_work_j == pytest.approx(0.003 * 0.4, rel=1e-9)
    assert p.balance_j == pytest.approx(0.003 * 0.4, abs=1e-9)
    assert abs(p.unexplained_j) < 1e-9 and not p.negative


def test_a_bad_sample_discards_the_period(two_link):
    pb = PowerBalance(two_link)
    for k in range(50):
        pb.update(k * 0.001, *pushed_effort(k * 0.001, np.zeros(2)))
    q, v, e = pushed_effort(0.05, np.zeros(2))
    assert not pb.update(0.05, q, v, None)
    assert not pb.update(0.051, q, v, [e[0], math.nan])
    assert pb.broken_periods == 1 and pb.close() is None
    for k in range(52, 60):
        pb.update(k * 0.001, *pushed_effort(k * 0.001, np.zeros(2)))
    p = pb.close()
    assert p.start_s == pytest.approx(0.052) and p.samples == 8
    assert pb.reading().startswith("power balance ")
    with pytest.raises(ValueError, match="persistent_periods"):
        PowerBalance(two_link, options=PowerBalanceOptions(persistent_periods=0))
