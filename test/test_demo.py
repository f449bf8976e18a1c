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
from dyn_node.core.dynamics import Dynamics
from dyn_node.core.model import load_model


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
    from dyn_node.core.trajectory import interpolate

    q = interpolate(traj, "quintic").evaluate(t)[0]
    q[10, 3] += 0.07
    assert tracking_error(traj, 100.0, t + 100.0, q) == pytest.approx(0.07, abs=1e-12)
    meas = {k: np.full(7, 1.0) for k in range(10)}
    model = {k: np.full(7, 1.0) for k in range(10)}
    model[4] = np.array([1.0, 1.0, 1.0, 4.0, 1.0, 1.0, 1.0])
    rms, mx, n = effort_residual(meas, model, 0, 9)
    assert (n, mx) == (10, 3.0)
    assert rms == pytest.approx(np.sqrt(9.0 / 70.0))


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
    summary = text[text.index("4. summary"):]
    for name in ("comfortable", "aggressive", "slowed"):
        assert re.search(rf"^{name}\s", summary, re.M), summary
    assert "[FAIL]" not in summary, summary
    assert summary.count("[PASS]") >= 4, summary  # 5 once the bag is audited
    # each trajectory was asked on ~/check_trajectory first, and got the execution's verdict
    assert "[PASS] every trajectory checked on ~/check_trajectory before it was sent" in summary
    assert text.count("  ~/check_trajectory: ") == 3, text[-3000:]
    assert re.search(r"live effort residual .* RMS [0-9.]+ N·m", summary), summary
    assert re.search(r"^aggressive\s+\S+\s+ERROR\s+panda_joint", summary, re.M)
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
