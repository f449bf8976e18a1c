"""The demo: its pure parts against independent numbers, and ``--short`` end to end as a process."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, TEST_DOMAIN, child_env
from dyn_node.ros.demo import (PANDA_POSES, READY, demo_trajectories, effort_residual, model_table,
                           tracking_error)
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def test_model_table_lists_gravity_and_limits(panda):
    text = model_table(panda)
    g = Dynamics(panda).gravity(np.array(PANDA_POSES["stretched"]))
    row = next(ln for ln in text.splitlines() if ln.startswith("panda_joint2"))
    # limit, then the ready block, then the stretched block: its gravity and its utilisation.
    assert "87.0" in row
    assert f"{g[1]:.2f}" in row and f"{abs(g[1]) / 87 * 100:.0f}%" in row
    assert "highest utilisation: panda_joint2" in text


def test_demo_trajectories_shape(panda):
    comfortable, aggressive = demo_trajectories(short=True)
    for t in (comfortable, aggressive):
        np.testing.assert_allclose(t.positions[0], READY)
        np.testing.assert_allclose(t.positions[-1], READY)
        t.validated(panda.joint_names)  # passes JTC's rules
    slowed = aggressive.scaled(2.0, "slowed", "")
    assert slowed.duration == pytest.approx(2 * aggressive.duration)


def test_tracking_error_and_residual_statistics(panda):
    _, aggressive = demo_trajectories(short=True)
    traj = aggressive.validated(panda.joint_names)
    t = np.linspace(0, traj.duration, 50)
    from dyn_node.core.check.trajectory import interpolate

    q = interpolate(traj, "quintic").evaluate(t)[0]
    q[10, 3] += 0.07
    assert tracking_error(traj, 100.0, t + 100.0, q) == pytest.approx(0.07, abs=1e-12)
    meas = {k: np.full(7, 1.0) for k in range(10)}
    model = {k: np.full(7, 1.0) for k in range(10)}
    model[4] = np.array([1.0, 1.0, 1.0, 4.0, 1.0, 1.0, 1.0])
    rms, mx, n = effort_residual(meas, model, 0, 9)
    assert (n, mx) == (10, 3.0)
    assert rms == pytest.approx(np.sqrt(9.0 / 70.0))


def test_task_transfer_is_within_joint_limits_but_over_the_tcp_speed(panda):
    """The TCP's speed against finite differences of Pinocchio's forward kinematics."""
    import pinocchio as pin

    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.core.check.trajectory import interpolate
    from dyn_node.ros.demo import DEMO_TASK_LIMITS, SAFETY_FACTOR, task_checks, task_transfer

    fast = task_transfer()
    traj = fast.validated(panda.joint_names)
    free = check_trajectory(Dynamics(panda), traj)
    limited = load_model(builtin="panda", limits_yaml=str(DEMO_TASK_LIMITS))
    res = check_trajectory(Dynamics(limited), traj)
    e = res.per_frame["panda_hand"]["frame_speed"]
    pm, data = panda.pin_model, panda.pin_model.createData()
    fid = pm.getFrameId("panda_hand")
    point = np.array([0.0, 0.0, 0.1034])
    t = np.linspace(0.0, fast.duration, 4001)
    q = interpolate(traj, "quintic").evaluate(t)[0]

    def tcp(qi):
        pin.framesForwardKinematics(pm, data, qi)
        return data.oMf[fid].act(point)

    x = np.array([tcp(qi) for qi in q])
    v_fd = np.linalg.norm(np.gradient(x, t, axis=0, edge_order=2), axis=1)
    assert free.feasible and not res.feasible
    assert e["value"] == pytest.approx(v_fd.max(), rel=1e-4)
    assert res.time_scale == pytest.approx(e["value"] / 0.25, rel=1e-12)
    slowed = check_trajectory(Dynamics(limited), fast.scaled(res.time_scale * SAFETY_FACTOR, "s", "")
                              .validated(panda.joint_names))
    assert slowed.feasible
    # speed ÷ k exactly; the 1 ms sample grid does not stretch with it (peak found to ~1e-6)
    assert slowed.per_frame["panda_hand"]["frame_speed"]["ratio"] == pytest.approx(
        1 / SAFETY_FACTOR, rel=1e-5)
    # the scene's PASS/FAIL lines
    from types import SimpleNamespace as NS

    bad = NS(feasible=False, worst_joint="panda_hand", worst_constraint="frame_speed",
             time_scale=res.time_scale, message=res.message)
    good = NS(feasible=True, message="feasible")
    place = {"frame_speed_peak": repr(e["value"])}
    assert [ok for ok, _ in task_checks(free, bad, place, good, 2.7)] == [True, True, True]
    assert [ok for ok, _ in task_checks(free, NS(**{**bad.__dict__, "worst_constraint": "effort"}),
                                        place, good, 2.7)] == [True, False, True]
    assert [ok for ok, _ in task_checks(free, bad, None, None, 2.7)] == [True, False, False]
    assert [ok for ok, _ in task_checks(res, None, None, None, 2.7)] == [False, False]


def _leftovers(marker: str) -> list[int]:
    """PIDs of live processes whose environment carries the demo's DYN_DEMO_RUN marker."""
    found = []
    needle = f"DYN_DEMO_RUN={marker}".encode()
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if needle in (d / "environ").read_bytes().split(b"\0"):
                stat = (d / "stat").read_text()
                if stat.split(") ")[-1][0] != "Z":
                    found.append(int(d.name))
        except OSError:
            continue
    return found


def _demo(out: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dyn_node.ros.demo", "--short", "--out", str(out),
                             "--domain", str(TEST_DOMAIN), *args],
                            cwd=str(REPO), env=child_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


@pytest.mark.timeout(150)
def test_demo_short_end_to_end(tmp_path):
    out = tmp_path / "demo"
    proc = _demo(out)
    try:
        text, _ = proc.communicate(timeout=140)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, text[-3000:]
    assert "highest utilisation" in text                     # the model table came first
    assert f"writing to {out.resolve()}: a new bag in {out.resolve() / 'bags'}/dyn_node_" in text
    # inputs the node did not answer come with its own reason (taken before it had its model)
    live = re.findall(r"/dyn_node/(gravity_torque|inverse_dynamics)\s+matched \d+, unmatched 0, "
                      r"not answered live (\d+)( \(all taken before dyn_node had its model from "
                      r"/robot_description\))?, ", text)
    assert len(live) == 2 and all((n == "0") == (reason == "") for _t, n, reason in live), live
    summary = text[text.index("4. summary"):]
    for name in ("comfortable", "aggressive", "slowed", "retimed"):
        assert re.search(rf"^{name}\s", summary, re.M), summary
    assert "[FAIL]" not in summary, summary
    assert summary.count("[PASS]") >= 4, summary  # 5 once the bag is audited
    # each trajectory was asked on ~/check_trajectory first, and got the execution's verdict
    assert "[PASS] every trajectory checked on ~/check_trajectory before it was sent" in summary
    assert text.count("  ~/check_trajectory: ") == 4, text[-3000:]   # the retimed one too
    # the aggressive one asked on ~/retime_trajectory: a real retimed answer (the one path to the
    # retimed trajectory), faster than the uniform slowdown, no shorter than its lower bound
    m = re.search(r"^  ~/retime_trajectory: retimed: ([0-9.]+) s -> ([0-9.]+) s \(uniform ([0-9.]+) s, "
                  r"T\* ([0-9.]+) s\): ", text, re.M)
    assert m, text[-3000:]
    d_in, d_out, uniform, bound = (float(x) for x in m.groups())
    assert d_in < d_out < uniform and bound * (1 - 1e-2) <= d_out, m[0]  # printed to 3 digits
    assert "not retimed" not in text and "retimer_unavailable" not in text
    assert re.search(r"sent 'retimed' \(aggressive retimed by ~/retime_trajectory: ", text), text[-3000:]
    # that answer executed without a live violation
    assert re.search(r"\[PASS\] retimed: ~/retime_trajectory's answer passes the exact check \([0-9.]+ s; ", summary)
    assert re.search(r"\[PASS\] retimed: executed without a live violation \(~/feasibility "
                     r"(OK|WARN), 0 saturated samples", summary), summary
    assert re.search(r"live effort residual .* RMS [0-9.]+ N·m", summary), summary
    assert re.search(r"^aggressive\s+\S+\s+ERROR\s+panda_joint", summary, re.M)
    # the push scene: contact reported while the 30 N push lasted, its force estimated
    assert re.search(r"\[PASS\] push: dyn_node reported (contact|collision) \d+ ms after", summary), summary
    assert re.search(r"\[PASS\] push: estimated force [0-9.]+ N vs 30 N applied at panda_link8", summary)
    # the press scene: the hand on dyn_sim's table, the estimate against ~/contact_truth
    assert re.search(r"\[PASS\] press: dyn_node reported (contact|collision) \d+ ms after the first touch", summary)
    assert re.search(r"\[PASS\] press: settled estimate [0-9.]+ N vs truth [0-9.]+ N at panda_link8", summary)
    # the audit replays the contact outputs of a node that took its model from /robot_description
    # (a fresh observer at its first core, no recording_start reset) identically
    for topic in ("external_torque", "external_wrench", "observer_events"):
        assert re.search(rf"/dyn_node/{topic}\s+matched [1-9]\d*, unmatched 0, not answered live 0, "
                         r"max \|difference\| 0\.0, identical True", text), text[-3000:]
    assert re.search(r"- (contact|collision) from [0-9.]+ s to [0-9.]+ s: peak [0-9.]+ N at panda_link8", text)
    # dyn-audit's line adds up: the executed trajectories and the questions apart, the questions
    # asked through the services counted. Executed: comfortable, aggressive (the "no"), slowed,
    # retimed, the slowed transfer, the press scene's press and release. Questions: six checks
    # (the four of scene 3, the fast and the slowed transfer; two said no: aggressive, the fast
    # transfer) and one retime, answered with a retimed trajectory.
    assert re.search(r"; 1 of 7 executed trajectories infeasible or rejected; 2 of 7 "
                     r"questions answered infeasible or rejected \(check 6, retime 1\)", text), text[-3000:]
    # 3b: the TCP speed limit, before execution with its time_scale, and the slowed transfer
    assert re.search(r"\[PASS\] fast transfer: infeasible before execution on the TCP speed "
                     r"\(worst panda_hand frame_speed, peak 0\.64\d* m/s of 0\.25 m/s\), "
                     r"time_scale 2\.56", summary), summary
    assert re.search(r"\[PASS\] slowed transfer \(× 2\.69\d*\): feasible", summary), summary
    left = _leftovers(str(out.resolve()))
    assert left == [], [(pid, Path(f"/proc/{pid}/cmdline").read_bytes()) for pid in left]


@pytest.mark.timeout(90)
def test_demo_interrupted_leaves_nothing_behind(tmp_path):
    out = tmp_path / "demo"
    proc = _demo(out)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 70
        assert proc.stdout is not None
        for line in proc.stdout:  # until the stack is up and a trajectory is under way
            lines.append(line)
            if "sent 'comfortable'" in line or time.monotonic() > deadline:
                break
        assert any("sent 'comfortable'" in ln for ln in lines), "".join(lines)[-2000:]
        os.kill(proc.pid, signal.SIGINT)  # Ctrl-C reaches the demo; children are in own groups
        rest, _ = proc.communicate(timeout=40)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, ("".join(lines) + rest)[-3000:]
    assert "interrupted" in rest, rest[-2000:]
    left = _leftovers(str(out.resolve()))
    assert left == [], [(pid, Path(f"/proc/{pid}/cmdline").read_bytes()) for pid in left]


def test_a_partial_audit_of_the_demos_own_bag_is_a_failure_not_a_missing_stage():
    """dyn-audit's 3 (partial) is neither "audited" (0 feasible, 1 violations: expected) nor a
    stage that could not run (2 unusable, no report): the demo's own bag must be whole."""
    from dyn_node.ros.demo import audit_outcome
    from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_UNUSABLE, EXIT_VIOLATIONS

    assert [audit_outcome(rc, True) for rc in (EXIT_OK, EXIT_VIOLATIONS, EXIT_PARTIAL,
                                               EXIT_UNUSABLE, -9)] == [
        "audited", "audited", "partial", "failed", "failed"]
    assert audit_outcome(EXIT_OK, False) == "failed"


def test_push_checks_against_the_applied_force_and_the_push_time():
    """The push scene's PASS lines: reported within the push (0.3 s) after it was sent, and the
    settled estimate within 10 % + 1 N of the applied force (vector difference), averaged over
    the part of the push dyn_sim says it applied, 0.1 s after it began."""
    from dyn_node.ros.demo.push import PushOutcome, push_checks, settle_estimate

    F = np.array([0.0, 0.0, -30.0])
    o = PushOutcome("panda_link8", F, sent_s=100.2, reported_s=100.235, reported_state="contact")
    # stamps 1 ms apart; the simulator ran 0.1 s behind the wall clock, so it stamped the push
    # 100.1 → 100.4 although it was sent at 100.2; a 5 N blip before it (a late joint_states
    # burst) and the decay after it are outside the window; another frame never counts
    def f(k):
        if k == 80:
            return np.array([5.0, 0.0, 0.0])
        if k < 100 or k >= 400:
            return np.zeros(3) if k < 100 else 0.2 * F
        return 0.5 * F if k < 200 else F + (0.0, 3.9, 0.0)
    o.wrenches = [(100.0 + k * 1e-3, "panda_link8", f(k)) for k in range(500)] + [
        (100.25, "panda_hand", np.zeros(3))]
    o.truth = [(100.1, "panda_link8", F), (100.4, "panda_link8", np.zeros(3))]
    settle_estimate(o)
    assert o.estimate_samples == 200 and np.allclose(o.estimate, F + (0.0, 3.9, 0.0))
    (ok_t, t_text), (ok_f, f_text) = push_checks(o)
    assert ok_t and "reported contact 35 ms after the 30 N push" in t_text
    assert ok_f and "|F̂ − F| 3.90 N ≤ 4.0 N" in f_text
    # without dyn_sim's word on the push there is nothing to compare with: a FAIL that says so
    o.truth = []
    settle_estimate(o)
    assert o.estimate is None
    ok, text = push_checks(o)[1]
    assert not ok and "did not say it applied the push" in text
    o.truth = [(100.1, "panda_link8", F), (100.4, "panda_link8", np.zeros(3))]
    o.wrenches = [(t, fid, w + (0.0, 0.2, 0.0)) for t, fid, w in o.wrenches]  # 4.1 N off: fails
    settle_estimate(o)
    assert not push_checks(o)[1][0]
    o.reported_s = 100.51  # after the push ended
    assert not push_checks(o)[0][0]
    o.reported_s = None
    assert not push_checks(o)[0][0]
