"""Bad input and faults (issue 27): hostile limits and trajectory files end in one bounded,
escaped error naming what was refused (dyn-check: one line, exit 2), never a traceback, a hang or
a verdict built on NaN; a far-future point cannot hide a violent segment."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

from dyn_node.audit.check import main
from dyn_node.audit.trajectory_files import parse_trajectory, read_trajectory
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.core.check.trajectory import MIN_SEGMENT_STEPS, validate_trajectory
from dyn_node.errors import ModelError, TrajectoryError, TrajectoryFileError

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
READY = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
#: Pinocchio's panda_joint2 velocity limit (the URDF's)
V2 = 2.175


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def run(capsys, *args) -> tuple[int, str, str]:
    code = main([*map(str, args), "--robot-model", "panda"])
    out, err = capsys.readouterr()
    return code, out, err


# --- 1: every segment checked, however long the trajectory -----------------------------------

def _move_then_hold(hold_s: float, *, T: float = 0.05, delta: float = 0.6):
    """0.6 rad of joint2 in 50 ms (quintic, at rest at both ends), then a hold until ``hold_s``."""
    q0, q1 = list(READY), list(READY)
    q1[1] += delta
    zero = [0.0] * 7
    times = [0.0, T] + ([hold_s] if hold_s else [])
    pos = [q0, q1] + ([q1] if hold_s else [])
    return times, pos, [zero] * len(times)


@pytest.mark.parametrize("hold_s", [1e5, 1e9])
def test_far_future_hold_does_not_hide_a_violent_segment(panda, hold_s):
    times, pos, zero = _move_then_hold(hold_s)
    traj = validate_trajectory(PANDA_JOINTS, PANDA_JOINTS, times, pos, zero, zero)
    opts = FeasibilityOptions()
    r = check_trajectory(Dynamics(panda), traj, opts)
    assert not r.feasible
    # closed form: the quintic's peak velocity 15/8·Δ/T against joint2's limit, sampled exactly
    # at mid-segment (the first segment keeps its 1 ms steps)
    assert r.time_scale == pytest.approx(15 / 8 * 0.6 / 0.05 / V2, rel=1e-9)
    assert (r.binding_joint, r.binding_constraint) == ("panda_joint2", "velocity")
    assert r.n_samples <= opts.max_samples
    assert any("long segment(s) sampled with" in w for w in r.warnings), r.warnings


def test_too_long_to_check_is_rejected_with_a_reason(panda):
    t = np.arange(41) * 10.0      # 40 segments of 10 s: 10,000 steps each at 1 ms
    pos = [list(READY)] * 41
    traj = validate_trajectory(PANDA_JOINTS, PANDA_JOINTS, t, pos)
    with pytest.raises(TrajectoryError) as e:
        check_trajectory(Dynamics(panda), traj, FeasibilityOptions(max_samples=40 * MIN_SEGMENT_STEPS))
    assert e.value.code == "too_long" and "too long to check" in str(e.value)
    # a budget that gives each segment its floor is checked, the long segments coarser
    r = check_trajectory(Dynamics(panda), traj,
                         FeasibilityOptions(max_samples=41 * (MIN_SEGMENT_STEPS + 1) + 41))
    assert r.n_samples <= 41 * (MIN_SEGMENT_STEPS + 1) + 41 and r.feasible


def test_dyn_check_far_future_file_is_infeasible(capsys, tmp_path):
    times, pos, _ = _move_then_hold(1e9)
    lines = [f"joint_names: {PANDA_JOINTS}", "points:"]
    for t, q in zip(times, pos):
        lines += [f"- positions: {q}", f"  velocities: {[0.0] * 7}", f"  accelerations: {[0.0] * 7}",
                  f"  time_from_start: {t!r}"]
    p = tmp_path / "far.yaml"
    p.write_text("\n".join(lines) + "\n")
    code, out, _ = run(capsys, p)
    assert code == 1 and ": INFEASIBLE (ERROR)" in out, out


# --- 3, 4, 9: bounded parsing, one-line errors, exit 2 -----------------------------------------

def _bomb(levels: int = 9) -> str:
    doc = 'a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    for i in range(1, levels):
        doc += f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 10) + "]\n"
    return doc


def _assert_one_line_exit_2(capsys, path, *words):
    code, out, err = run(capsys, path)
    assert code == 2, (out, err)
    assert err.count("\n") == 1 and "Traceback" not in err and len(err) < 2000, err
    for w in words:
        assert w in err, err
    return err


def test_alias_bomb_in_a_trajectory_is_refused(capsys, tmp_path):
    p = tmp_path / "bomb.yaml"
    p.write_text(_bomb() + f"joint_names: {PANDA_JOINTS}\npoints:\n- positions: *a8\n"
                 "  time_from_start: 0\n")
    _assert_one_line_exit_2(capsys, p, "aliases expand")


def test_alias_bomb_in_a_limits_value_is_refused():
    with pytest.raises(ModelError) as e:
        load_model(builtin="panda", limits_yaml=_bomb() + "joint_limits:\n  panda_joint1:\n"
                                                          "    max_velocity: *a8\n")
    assert e.value.code == "limits_bad_yaml" and "aliases expand" in str(e.value)


@pytest.mark.parametrize("name,text,words", [
    ("bigint.yaml", f"joint_names: [panda_joint1]\npoints:\n- positions: [1{'0' * 400}]\n"
                    "  time_from_start: 0\n", ["too large for a number", "positions[0]"]),
    ("bigtime.yaml", f"joint_names: {PANDA_JOINTS}\npoints:\n- positions: {READY}\n"
                     "  time_from_start: 1.0e300\n", ["time_from_start", "int32"]),
    ("bigtime.csv", "time," + ",".join(PANDA_JOINTS) + "\n0," + ",".join(map(str, READY))
                    + "\n1e300," + ",".join(map(str, READY)) + "\n", ["time", "int32"]),
    ("deep.yaml", "joint_names: " + "[" * 100000 + "]" * 100000 + "\n", ["nested more than 64"]),
    ("deep.json", '{"joint_names": ' + "[" * 100000 + "]" * 100000 + "}", ["nested too deeply"]),
    ("secbig.yaml", f"header: {{stamp: {{sec: {2 ** 64}, nanosec: 0}}}}\njoint_names: "
                    f"{PANDA_JOINTS}\npoints: []\n", ["header.stamp.sec", "0 to 2147483647"]),
    ("nsneg.yaml", f"joint_names: {PANDA_JOINTS}\npoints:\n- positions: {READY}\n"
                   "  time_from_start: {sec: 0, nanosec: -5}\n", ["nanosec", "0 to 999999999"]),
    ("nsbig.yaml", f"joint_names: {PANDA_JOINTS}\npoints:\n- positions: {READY}\n"
                   "  time_from_start: {sec: 0, nanosec: 5000000000}\n", ["nanosec"]),
    ("effort.yaml", f"joint_names: {PANDA_JOINTS}\npoints:\n- positions: {READY}\n"
                    "  effort: [1.0, 2.0]\n  time_from_start: 0\n",
     ["points[0].effort", "2 values for 7 joints"]),
    ("dup.yaml", f"joint_names: {PANDA_JOINTS}\njoint_names: {PANDA_JOINTS}\npoints: []\n",
     ["duplicate key 'joint_names'"]),
    ("dup.json", '{"points": [], "points": []}', ["duplicate key 'points'"]),
    ("under.csv", "time,panda_joint1\n0,1_000\n", ["not a number ('1_000')"]),
    ("arabic.csv", "time,panda_joint1\n0,\u0661\n", ["not a number ('\u0661')"]),
    ("fullwidth.csv", "time,panda_joint1\n0,\uff11\n", ["not a number"]),
    ("nul.yaml", "joint_names: [\"a\\0\\u202eb\"]\npoints:\n- positions: [\"x\\u202e\\0\"]\n"
                 "  time_from_start: 0\n", ["\\u202e", "\\x00"]),
])
def test_hostile_trajectory_files_end_in_one_line_exit_2(capsys, tmp_path, name, text, words):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    err = _assert_one_line_exit_2(capsys, p, *words)
    assert "\u202e" not in err and "\0" not in err


def test_a_huge_value_is_echoed_capped(capsys, tmp_path):
    p = tmp_path / "huge.yaml"
    p.write_text(f"joint_names: {PANDA_JOINTS}\npoints:\n- positions: ['{'x' * 5_000_000}']\n"
                 "  time_from_start: 0\n")
    err = _assert_one_line_exit_2(capsys, p, "not a number")
    assert len(err) < 600


def test_170000_unknown_joints_make_a_short_message(capsys, tmp_path):
    names = PANDA_JOINTS + [f"x{i}" for i in range(170_000)]
    p = tmp_path / "many.csv"
    p.write_text("time," + ",".join(names) + "\n0," + ",".join(["0"] * len(names)) + "\n"
                 "1," + ",".join(["0"] * len(names)) + "\n")
    code, out, _ = run(capsys, p)
    assert code == 1 and "REJECTED: joints not in the model: x0, x1" in out
    assert "and 169990 more" in out and len(out) < 1000


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_fifo_and_symlink_to_dev_zero_are_refused_at_once(capsys, tmp_path):
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    _assert_one_line_exit_2(capsys, fifo, "is a FIFO, not a regular file")
    zero = tmp_path / "zero.yaml"
    zero.symlink_to("/dev/zero")
    _assert_one_line_exit_2(capsys, zero, "is a device, not a regular file")
    with pytest.raises(ModelError) as e:
        load_model(builtin="panda", limits_yaml=str(zero))
    assert "not a regular file" in str(e.value)


# --- 7: silently accepted before ---------------------------------------------------------------

def test_csv_with_a_byte_order_mark_reads(tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes("\ufefftime,panda_joint1\n0,0.5\n1,0.25\n".encode("utf-8"))
    tf = read_trajectory(p)
    assert tf.joint_names == ["panda_joint1"] and tf.times == [0.0, 1.0]
    assert tf.positions == [[0.5], [0.25]]


def test_yaml_numbers_are_yaml_1_2():
    """``1:30`` is not 90 (sexagesimal), ``012`` is twelve, ``1e3`` a number."""
    with pytest.raises(TrajectoryFileError, match=r"not a number \('1:30'\)"):
        parse_trajectory("joint_names: [a]\npoints:\n- positions: [1:30]\n  time_from_start: 0\n",
                         "yaml")
    tf = parse_trajectory("joint_names: [a]\npoints:\n- positions: [012, 1e3]\n"
                          "  time_from_start: 0\n", "yaml")
    assert tf.positions == [[12.0, 1000.0]]


# --- limits files: every problem in one error, validated at load -------------------------------

def _limits_error(text: str) -> ModelError:
    with pytest.raises(ModelError) as e:
        load_model(builtin="panda", limits_yaml=text)
    return e.value


def test_every_typo_of_a_limits_file_in_one_error():
    e = _limits_error("joint_limits:\n  panda_joint1:\n    has_velocity_limit: true\n"
                      "    max_velocty: 2.0\n  panda_joint2:\n    max_effort: fast\n")
    s = str(e)
    assert "3 problems" in s and e.code == "limits_unknown_key"
    assert "unknown key 'has_velocity_limit' (did you mean 'has_velocity_limits'?)" in s
    assert "unknown key 'max_velocty' (did you mean 'max_velocity'?)" in s
    assert "joint_limits.panda_joint2.max_effort must be float, got 'fast'" in s


def test_every_task_section_problem_in_one_error():
    e = _limits_error("joint_limits: {panda_joint1: {max_velocity: 1.0}}\n"
                      "grasp: {frame: panda_hand, normal_axis: [0, 0, 1], friction_coefficient: 0.5,"
                      " grip_force: 10, faces: 2, colour: red}\n"
                      "base_limits: {max_force: -1, max_momnt: 2}\n")
    s = str(e)
    assert "2 problems" in s and "unknown key 'colour'" in s and "unknown key 'max_momnt'" in s


@pytest.mark.parametrize("entry,key", [
    ("armature: -1", "armature"), ("armature: .inf", "armature"),
    ("rms_window: 0", "rms_window"), ("rms_window: .inf", "rms_window"),
    (f"max_effort: 1{'0' * 400}", "max_effort"),
    ("max_velocity: 1:30", "max_velocity"),
])
def test_limits_that_would_break_every_check_are_refused_at_load(entry, key):
    e = _limits_error(f"joint_limits:\n  panda_joint1:\n    {entry}\n")
    assert f"joint_limits.panda_joint1.{key}" in str(e) and len(str(e)) < 500


def test_duplicate_joint_blocks_are_refused():
    e = _limits_error("joint_limits:\n  panda_joint1: {max_velocity: 1.0}\n"
                      "  panda_joint1: {max_velocity: 2.0}\n")
    assert "duplicate key 'panda_joint1'" in str(e) and "line 3" in str(e)


JL = "joint_limits: {panda_joint1: {max_velocity: 1.0}}\n"
GRASP = ("grasp: {frame: panda_hand, normal_axis: %s, friction_coefficient: %s, grip_force: 20, "
         "faces: 2}\n")


def test_grasp_friction_that_overflows_is_refused():
    e = _limits_error(JL + GRASP % ("[0, 0, 1]", "1e308"))
    assert "grasp.friction_coefficient" in str(e) and e.code == "limits_bad_value"


@pytest.mark.parametrize("axis,unit", [("[0, 1e-320, 0]", [0, 1, 0]),
                                       ("[0, 1e308, 1e308]", [0, math.sqrt(0.5), math.sqrt(0.5)])])
def test_grasp_normal_axis_normalises_without_under_or_overflow(axis, unit):
    m = load_model(builtin="panda", limits_yaml=JL + GRASP % (axis, "0.5"))
    np.testing.assert_allclose(m.task_limits.grasp.normal_axis, unit, rtol=0, atol=1e-15)


def test_base_mass_beyond_the_bound_is_refused():
    e = _limits_error(JL + "base_limits: {support_polygon: [[-1, -1], [1, -1], [1, 1], [-1, 1]], "
                      "base_mass: 1e308, base_com: [0, 0, 0]}\n")
    assert "base_limits.base_mass" in str(e) and e.code == "limits_bad_value"


def test_a_5_mb_limits_value_is_echoed_capped_and_escaped():
    e = _limits_error('joint_limits:\n  panda_joint1:\n    max_velocity: "\\u202e\\0' + "x" * 5_000_000
                      + '"\n')
    s = str(e)
    assert len(s) < 400 and "\\u202e" in s and "\u202e" not in s and "\0" not in s


# --- unknown joints: what is missing, and the closest names ------------------------------------

def test_unknown_joint_names_the_missing_ones_and_the_closest(capsys, tmp_path):
    names = PANDA_JOINTS[:6] + ["panda_joint8"]
    p = tmp_path / "typo.csv"
    p.write_text("time," + ",".join(names) + "\n0," + ",".join(map(str, READY)) + "\n1,"
                 + ",".join(map(str, READY)) + "\n")
    code, out, _ = run(capsys, p)
    assert code == 1
    assert ("REJECTED: joints not in the model: panda_joint8; model joints missing from the "
            "trajectory: panda_joint7 (did you mean 'panda_joint8' → 'panda_joint7'?)") in out, out


# --- 6: NaN never reaches a verdict ------------------------------------------------------------

@pytest.mark.parametrize("window", [0.0, math.inf])
def test_a_nan_limit_that_slips_past_the_parser_rejects_instead_of_a_verdict(window):
    """rms_window 0 or ∞ set directly (the parser refuses it): the RMS is NaN, which before gave
    'feasible … no margin left' with time_scale inf."""
    from dataclasses import replace

    m = load_model(builtin="planar_2link")
    lim = replace(m.limits, rms_window=np.full(m.nv, window), rms_effort=np.full(m.nv, 5.0))
    names = list(m.joint_names)
    traj = validate_trajectory(names, names, [0.0, 1.0, 2.0], [[0, 0], [0.5, 0.3], [1, 0.6]])
    with pytest.raises(TrajectoryError) as e, np.errstate(all="ignore"):
        check_trajectory(Dynamics(replace(m, limits=lim)), traj)
    assert e.value.code == "evaluation_failed" and "rms_effort" in str(e.value)


def test_huge_integer_polygon_coordinate_is_a_limits_error():
    e = _limits_error(JL + f"base_limits: {{support_polygon: [[-1, -1], [1{'0' * 400}, -1], [1, 1]]}}\n")
    assert "base_limits.support_polygon" in str(e) and len(str(e)) < 500


def test_joint_and_task_problems_of_one_file_in_one_error():
    e = _limits_error("joint_limits:\n  panda_joint1: {max_velocty: 1.0}\n"
                      "grasp: {frame: panda_hand, normal_axis: [0, 0, 1], friction_coefficient: 0.5,"
                      " grip_force: 10, faces: 2, colour: red}\n")
    s = str(e)
    assert "unknown key 'max_velocty'" in s and "unknown key 'colour'" in s
    e = _limits_error("joint_limits:\n  panda_joint1: {max_velocity: 1.0}\nframe_limitz: {}\n")
    assert str(e).count("frame_limitz") == 1     # refused by both parsers, said once


def test_effort_neither_empty_nor_one_per_joint_is_rejected_as_the_controller_does():
    zero = [[0.0] * 7] * 2
    pos = [READY, READY]
    with pytest.raises(TrajectoryError, match=r"point 1: 2 effort for 7 joints") as e:
        validate_trajectory(PANDA_JOINTS, PANDA_JOINTS, [0.0, 1.0], pos, efforts=[[], [1.0, 2.0]])
    assert e.value.code == "length_mismatch"
    for ok in ([[], []], zero, None):
        validate_trajectory(PANDA_JOINTS, PANDA_JOINTS, [0.0, 1.0], pos, efforts=ok)
