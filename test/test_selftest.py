"""Self-test: identities hold on the built-in models and the checks catch a broken model."""
from __future__ import annotations

import numpy as np
import pytest

from dyn_node.dynamics import Dynamics
from dyn_node.errors import EVALUATION_ERROR
from dyn_node.model import load_model
from dyn_node.selftest import run_self_test
from dyn_node.status import ERROR, OK, WARN


@pytest.mark.parametrize("name", ["panda", "ur5", "planar_2link"])
def test_builtin_models_pass(name):
    passed, statuses = run_self_test(load_model(builtin=name), hardware_id=name)
    assert passed
    assert [s.name.split("/")[-1] for s in statuses] == ["rnea_identity", "gravity_identity", "mass_matrix",
                                                          "limits"]
    assert all(s.level == OK and s.hardware_id == name for s in statuses)
    mm = statuses[2].values
    assert mm["min_eigenvalue_kg_m2"] > 0 and mm["max_asymmetry"] <= mm["tolerance_nm"]


def test_seeded_and_reproducible():
    m = load_model(builtin="panda")
    a = run_self_test(m, seed=5)[1]
    b = run_self_test(m, seed=5)[1]
    assert [s.values for s in a] == [s.values for s in b]


def test_broken_bias_is_detected(monkeypatch):
    orig = Dynamics.bias
    monkeypatch.setattr(Dynamics, "bias", lambda self, q, v: orig(self, q, v) + 1e-6)
    passed, statuses = run_self_test(load_model(builtin="panda"))
    assert not passed
    st = statuses[0]
    assert st.level == ERROR and st.values["failure_label"] == EVALUATION_ERROR
    assert st.values["max_error_nm"] == pytest.approx(1e-6, rel=1e-6)


def test_broken_mass_matrix_is_detected(monkeypatch):
    orig = Dynamics.mass_matrix

    def skewed(self, q):
        M = orig(self, q)
        M[0, 1] += 1e-3
        return M

    monkeypatch.setattr(Dynamics, "mass_matrix", skewed)
    passed, statuses = run_self_test(load_model(builtin="ur5"))
    assert not passed and statuses[2].level == ERROR


def test_suspicious_limits_reported():
    m = load_model(builtin="panda", limits_yaml={"joint_limits": {"panda_joint2": {
        "has_effort_limits": True, "max_effort": 1.0e6}}})
    passed, statuses = run_self_test(m)
    lim = statuses[3]
    assert passed and lim.level == WARN and lim.values["warnings"] >= 1
    assert "panda_joint2" in lim.message and lim.values["failure_label"] == EVALUATION_ERROR
    assert np.isfinite(lim.values["joints_with_effort_limit"])
