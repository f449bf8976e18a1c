"""dyn_sim --check-physics: free-motion energy against the closed form of the planar 2-link arm,
convergence with the timestep, and the command's exit codes and evidence (read back with
jsonschema against the shipped schema)."""
from __future__ import annotations

import json
import math

import jsonschema
import numpy as np
import pytest

from dyn_node.audit.evidence import SCHEMA_PATH
from dyn_node.core.robot.model import load_model
from dyn_node.ros.sim_node import main as dyn_sim_main
from dyn_node.sim.physics_check import contact_failures, free_motion_run

M1, M2, L1, L2, G = 1.5, 1.0, 0.5, 0.4, 9.81  # planar_2link.urdf: point masses at the link tips


def closed_form_energy(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """KE + PE of the 2-link arm in the vertical x-z plane (q = 0 horizontal, z up), PE = 0 at
    the shoulder height: the textbook formulas, per sample."""
    q1, q2, v1, v2 = q[:, 0], q[:, 1], v[:, 0], v[:, 1]
    z1, z2 = L1 * np.sin(q1), L1 * np.sin(q1) + L2 * np.sin(q1 + q2)
    ke = 0.5 * M1 * L1 ** 2 * v1 ** 2 + 0.5 * M2 * (
        L1 ** 2 * v1 ** 2 + L2 ** 2 * (v1 + v2) ** 2 + 2 * L1 * L2 * v1 * (v1 + v2) * np.cos(q2))
    return ke + G * (M1 * z1 + M2 * z2)


@pytest.fixture(scope="module")
def arm():
    return load_model(builtin="planar_2link")


def test_free_motion_energy_is_the_closed_form(arm):
    run = free_motion_run(arm, np.array([0.3, 0.2]), integrator="euler", timestep=0.001, duration=2.0)
    E_mj = run["potential"] + run["kinetic"]
    E_cf = closed_form_energy(run["q"], run["v"])
    np.testing.assert_allclose(E_mj, E_cf, rtol=0, atol=1e-9 * np.abs(E_cf).max())
    peak_ke = (E_cf - G * (M1 * L1 * np.sin(run["q"][:, 0]) + M2 * (L1 * np.sin(run["q"][:, 0])
               + L2 * np.sin(run["q"].sum(axis=1))))).max()
    expected = np.abs(E_cf - E_cf[0]).max() / peak_ke
    assert run["energy_error_rel"] == pytest.approx(expected, rel=1e-7)
    assert run["peak_kinetic_j"] > 5.0  # a real swing, not a robot at rest


def test_euler_is_first_order_and_rk4_fourth_order(arm):
    errs = [free_motion_run(arm, np.array([0.3, 0.2]), integrator="euler", timestep=h, duration=2.0)
            ["energy_error_rel"] for h in (0.002, 0.001, 0.0005)]
    for a, b in zip(errs, errs[1:]):
        assert 1.7 < a / b < 2.3  # first order: the error halves with the timestep
    rk4 = [free_motion_run(arm, np.array([0.3, 0.2]), integrator="rk4", timestep=h, duration=2.0)
           ["energy_error_rel"] for h in (0.004, 0.002, 0.001)]
    for a, b in zip(rk4, rk4[1:]):
        assert 12 < a / b < 20  # fourth order: ÷16 per halving (measured 15.1, 15.5)
    assert rk4[2] < 1e-6 * errs[1]  # dyn_sim's default at 1 ms (2.3e-9) against Euler's 1.1 %


def _validated(path) -> dict:
    rec = json.loads(path.read_text())
    jsonschema.Draft202012Validator(json.loads(SCHEMA_PATH.read_text())).validate(rec)
    return rec


def test_command_exit_codes_and_evidence(tmp_path):
    out = tmp_path / "pc"
    # no --integrator: dyn_sim's default (RK4, 1 ms) is the nominal run
    code = dyn_sim_main(["dyn_sim", "--check-physics", "--out", str(out), "--robot-model",
                         "planar_2link", "--only", "free_motion"])
    assert code == 0
    rec = _validated(out / "free_motion" / "evidence.json")
    fm = rec["outputs"]["physics"]
    assert rec["figures"]["energy_error_rel"] == fm["nominal"]["energy_error_rel"] < 1e-2
    assert fm["nominal"]["integrator"] == "rk4" and fm["nominal"]["timestep_s"] == 0.001
    assert rec["verdict"]["exit_code"] == 0
    assert {(r["integrator"], r["timestep_s"]) for r in fm["runs"]} >= {("euler", 0.001), ("euler", 0.0005)}
    assert all(h["error_ratio"] > 1 for h in fm["halving"] if h["integrator"] == "euler")
    assert (out / "free_motion" / "energy.png").stat().st_size > 1000
    # Euler (still selectable) at 4 ms drifts past 1 %: exit 1, labelled
    assert dyn_sim_main(["dyn_sim", "--check-physics", "--out", str(out), "--robot-model", "planar_2link",
                         "--integrator", "euler", "--timestep", "0.004", "--only", "free_motion"]) == 1
    rec = _validated(out / "free_motion" / "evidence.json")
    assert rec["failure_labels"] == ["evaluation error"] and rec["figures"]["energy_error_rel"] >= 1e-2
    for bad in (["--timestep", "-1"], ["--robot-model", "nao"], ["--integrator", "verlet"], []):
        args = ["--out", str(out)] if bad != [] else []
        assert dyn_sim_main(["dyn_sim", "--check-physics", *args, *bad]) == 2


def test_contact_check(tmp_path):
    code = dyn_sim_main(["dyn_sim", "--check-physics", "--out", str(tmp_path), "--only", "contact"])
    assert code == 0
    rec = _validated(tmp_path / "contact" / "evidence.json")
    ph, fig = rec["outputs"]["physics"], rec["figures"]
    assert 0 < fig["max_penetration_m"] < 5e-3 and fig["normal_force_n"] > 20.0
    assert ph["nominal"]["balance_residual_rel"] < 1e-3 and ph["nominal"]["normal_force_variation_rel"] < 0.05
    by = {r["label"]: r for r in ph["perturbed"]}
    # a stiffer contact (shorter solref time constant) penetrates less, a softer one more
    assert by["stiffer (solref 0.01 s)"]["max_penetration_m"] < fig["max_penetration_m"] \
        < by["softer (solref 0.04 s)"]["max_penetration_m"]
    assert math.isclose(by["timestep 0.5 ms"]["normal_force_n"], fig["normal_force_n"], rel_tol=0.02)
    # the nominal press runs dyn_sim's default RK4; Euler holds the same press
    assert ph["nominal"]["solver"]["integrator"] == "rk4"
    euler = by["integrator euler (MuJoCo default)"]
    assert euler["solver"]["integrator"] == "euler" and not contact_failures(euler)
    assert math.isclose(euler["normal_force_n"], fig["normal_force_n"], rel_tol=0.02)
    assert rec["verdict"]["exit_code"] == 0 and rec["failure_labels"] == []


@pytest.mark.parametrize("args, words", [
    (["--timestep", "1e-300"], "--timestep must be in [0.0001, 0.01] s"),
    (["--timestep", "nan"], "--timestep must be in"),
    (["--out", "/dev/full"], "File exists"),
])
def test_hostile_arguments_exit_2_in_one_line(args, words, tmp_path, capsys):
    """Issue 37: a timestep that would never end (1e-300 s) and an --out that is a device."""
    base = ["--out", str(tmp_path / "pc")] if "--out" not in args else []
    code = dyn_sim_main(["dyn_sim", "--check-physics", *base, *args, "--only", "free_motion"])
    err = capsys.readouterr().err
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_a_full_disk_exits_2_in_one_line(tmp_path, capsys, monkeypatch):
    """The evidence cannot be written (ENOSPC, as on a full disk): one line, exit 2, not 1."""
    import errno

    from dyn_node.sim import physics_report

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(physics_report, "write_free_motion", full)
    code = dyn_sim_main(["dyn_sim", "--check-physics", "--out", str(tmp_path / "pc"), "--robot-model",
                         "planar_2link", "--only", "free_motion"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip().splitlines() == [
        f"dyn_sim --check-physics: cannot write the evidence in {tmp_path / 'pc'}: No space left on device"]
