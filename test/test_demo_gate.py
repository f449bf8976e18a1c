"""The demo's gate scene end to end (python -m dyn_node.ros.demo.gate): its own dyn_sim and gates."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import pytest

from conftest import REPO, TEST_DOMAIN, child_env

pytest.importorskip("control_msgs", reason="control_msgs not built into the venv (make)")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> str:
    """The scene's output (it exited 0)."""
    proc = subprocess.Popen([sys.executable, "-m", "dyn_node.ros.demo.gate", "--out", str(tmp_path_factory.mktemp("gate")),
                             "--domain", str(TEST_DOMAIN)], cwd=str(REPO), env=child_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        text, _ = proc.communicate(timeout=220)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, text[-3000:]
    return text


@pytest.mark.timeout(240)
def test_feasible_forwarded_infeasible_rejected_and_sim_still(scene):
    text = scene
    assert "FAIL" not in text, text[-3000:]
    assert re.search(r"^PASS gate: feasible goal forwarded → 'Goal successfully reached!' \(error_code 0\)$",
                     text, re.M), text[-3000:]
    assert re.search(r"^PASS gate \(reject\): infeasible goal → ABORTED, INVALID_GOAL, 'infeasible: "
                     r"panda_joint1 velocity 287% of 2\.17 rad/s at t = 0\.0\d s; run 2\.87× slower: velocity of "
                     r"panda_joint1 binds'; "
                     r"dyn_sim never moved \(\d+ joint_states after it, max change \S+ rad\)$", text, re.M), text[-3000:]
    assert "unavailable" not in text  # the retimer is part of the package: the retime goal runs


@pytest.mark.timeout(240)
def test_infeasible_retimed_succeeds_within_the_uniform_slowdown(scene):
    text = scene
    m = re.search(r"^PASS gate \(retime\): the same goal retimed 0\.150 s → ([0-9.]+) s \(uniform slowdown "
                  r"([0-9.]+) s\) → 'Goal successfully reached!'; peak torque \d+% of the limit$", text, re.M)
    assert m, text[-3000:]
    assert 0.15 < float(m[1]) <= float(m[2]) + 1e-3
