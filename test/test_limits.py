"""Joint limits: URDF parsing, the ros2_control-style YAML with dyn_node's keys, and warnings."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from dyn_node.errors import ModelError
from dyn_node.core.robot.limits import IGNORED_YAML_KEYS, LIMIT_KINDS, LIMITS_YAML_KEYS, load_limits_yaml
from dyn_node.core.robot.model import Payload, load_model

FULL = """
joint_limits:
  joint1:
    has_position_limits: true
    min_position: -2.0
    max_position: 2.5
    has_velocity_limits: true
    max_velocity: 1.5
    has_acceleration_limits: true
    max_acceleration: 10.0
    has_jerk_limits: true
    max_jerk: 200.0
    has_effort_limits: true
    max_effort: 35.0
    max_effort_rate: 500.0
    max_rms_effort: 20.0
    rms_window: 2.5
    max_power: 80.0
    effort_speed_curve: [[0.0, 35.0], [1.0, 30.0], [3.0, 10.0]]
    armature: 0.01
  joint2:
    has_velocity_limits: false
    has_position_limits: false
    max_acceleration: 12.0
"""


@pytest.fixture(scope="module")
def two_link():
    return load_model(builtin="planar_2link")


def test_urdf_limits(two_link):
    lim = two_link.limits
    assert lim.names == ("joint1", "joint2")
    np.testing.assert_array_equal(lim.position_lower, [-3.0, -2.6])
    np.testing.assert_array_equal(lim.position_upper, [3.0, 2.6])
    np.testing.assert_array_equal(lim.soft_lower, [-2.9, -2.5])
    np.testing.assert_array_equal(lim.soft_upper, [2.9, 2.5])
    np.testing.assert_array_equal(lim.effort, [40.0, 15.0])
    np.testing.assert_array_equal(lim.velocity, [3.0, 4.0])
    # Missing limits are unlimited, never zero.
    for kind in ("acceleration", "jerk", "effort_rate", "rms_effort", "power"):
        assert np.all(getattr(lim, kind) == np.inf), kind
    np.testing.assert_array_equal(lim.armature, [0.0, 0.0])
    assert lim.effort_speed_curve == (None, None)
    np.testing.assert_array_equal(lim.effort_envelope(np.array([[1.0, 2.0]])), [[np.inf, np.inf]])
    assert "effort_speed" in LIMIT_KINDS


def test_full_yaml_overrides(two_link, tmp_path):
    m = two_link.with_limits(FULL)
    lim = m.limits
    assert lim.position_lower.tolist() == [-2.0, -np.inf]
    assert lim.position_upper.tolist() == [2.5, np.inf]
    assert lim.velocity.tolist() == [1.5, np.inf]  # has_velocity_limits: false removes the URDF's 4.0
    assert lim.acceleration.tolist() == [10.0, 12.0]  # max_* without has_* applies
    assert lim.jerk.tolist() == [200.0, np.inf]
    assert lim.effort.tolist() == [35.0, 15.0]  # joint2 keeps its URDF effort
    assert lim.effort_rate.tolist() == [500.0, np.inf]
    assert lim.rms_effort.tolist() == [20.0, np.inf]
    assert lim.rms_window.tolist() == [2.5, 1.0]
    assert lim.power.tolist() == [80.0, np.inf]
    assert lim.armature.tolist() == [0.01, 0.0]
    np.testing.assert_array_equal(m.pin_model.armature, [0.01, 0.0])
    env = lim.effort_envelope(np.array([[0.5, 1.0], [-2.0, 0.0], [9.0, 1.0]]))
    np.testing.assert_allclose(env, [[32.5, np.inf], [20.0, np.inf], [10.0, np.inf]])
    d = lim.to_dict()
    assert d["velocity"] == [1.5, None] and d["effort_speed_curve"][1] is None
    # Same from a file, and nested under <node>: ros__parameters:.
    f = tmp_path / "limits.yaml"
    f.write_text(FULL)
    assert m.with_limits(f).limits.to_dict() == d
    assert m.with_limits(str(f)).limits.to_dict() == d
    nested = tmp_path / "params.yaml"
    nested.write_text(yaml.safe_dump({"dyn_node": {"ros__parameters": yaml.safe_load(FULL)}}))
    assert m.with_limits(nested).limits.to_dict() == d
    assert m.with_limits(yaml.safe_load(FULL)).limits.to_dict() == d
    several = {"controller_manager": {"ros__parameters": {"update_rate": 100}},
               "/**": {"ros__parameters": yaml.safe_load(FULL)}}
    assert m.with_limits(several).limits.to_dict() == d
    several["other"] = {"ros__parameters": yaml.safe_load(FULL)}
    bad(several, "limits_no_joint_limits", "several")
    # None goes back to URDF limits only.
    assert m.with_limits(None).limits.to_dict() == two_link.limits.to_dict()
    lm = load_model(builtin="planar_2link", limits_yaml=f)
    assert lm.limits.to_dict() == d


def bad(text_or_map, code, *fragments):
    with pytest.raises(ModelError) as e:
        load_model(builtin="planar_2link", limits_yaml=text_or_map)
    assert e.value.code == code, str(e.value)
    for f in fragments:
        assert f in str(e.value), str(e.value)


def test_yaml_errors(tmp_path):
    bad("joint_limits:\n  joint1:\n    max_velocty: 2.0\n", "limits_unknown_key",
        "joint1", "max_velocty", "did you mean 'max_velocity'")
    bad("joint_limits:\n  joint1:\n    has_effort_limit: true\n", "limits_unknown_key",
        "has_effort_limits")
    bad("joint_limits:\n  joint1:\n    max_velocity: fast\n", "limits_wrong_type",
        "joint1.max_velocity", "float")
    bad("joint_limits:\n  joint1:\n    has_velocity_limits: 1\n", "limits_wrong_type", "bool")
    bad("joint_limits:\n  joint1:\n    max_effort: true\n", "limits_wrong_type")
    bad("joint_limits:\n  joint1:\n    max_effort: .nan\n", "limits_wrong_type")
    bad("joint_limits:\n  elbow:\n    max_effort: 3.0\n", "limits_unknown_joint", "elbow", "joint1")
    bad("joint_limits:\n  joint1: 3\n", "limits_bad_entry", "joint1")
    bad("limits:\n  joint1: {}\n", "limits_no_joint_limits")
    bad("joint_limits: [1, 2\n", "limits_bad_yaml")
    bad(str(tmp_path / "missing.yaml"), "limits_file_missing", "missing.yaml")
    for curve in ("[[1.0, 5.0], [0.5, 4.0]]", "[[0.0, -1.0]]", "[[0.0, 1.0, 2.0]]", "[]",
                  "[[0.0, .inf]]", "[[a, b]]", "7"):
        bad(f"joint_limits:\n  joint1:\n    effort_speed_curve: {curve}\n", "limits_bad_curve",
            "effort_speed_curve")
    f = tmp_path / "typo.yaml"
    f.write_text("joint_limits:\n  joint2:\n    max_jrek: 1.0\n")
    bad(f, "limits_unknown_key", str(f), "joint2", "max_jerk")


def _merged(two_link, entry: dict):
    return two_link.with_limits({"joint_limits": {"joint1": entry}}).limits.to_dict()


#: Per value key: an entry whose value differs from every planar_2link URDF value.
_VALUE_ENTRIES = {"min_position": -1.25, "max_position": 1.25, "max_velocity": 1.25,
                  "max_acceleration": 1.25, "max_deceleration": 1.25, "max_jerk": 1.25,
                  "max_effort": 1.25, "soft_lower_limit": -1.25, "soft_upper_limit": 1.25,
                  "max_effort_rate": 1.25, "max_rms_effort": 1.25, "rms_window": 1.25,
                  "max_power": 1.25, "effort_speed_curve": [[0.0, 1.25]], "armature": 1.25,
                  "k_position": 1.25, "k_velocity": 1.25}
#: Per has_ flag: the value keys it switches (given beside ``has_X: false``, they must not apply).
_FLAGS = {"has_position_limits": ("min_position", "max_position"),
          "has_velocity_limits": ("max_velocity",), "has_acceleration_limits": ("max_acceleration",),
          "has_deceleration_limits": ("max_deceleration",), "has_jerk_limits": ("max_jerk",),
          "has_effort_limits": ("max_effort",),
          "has_soft_limits": ("soft_lower_limit", "soft_upper_limit")}


def test_every_accepted_key_is_applied_or_documented_as_unused(two_link):
    """Each key the YAML accepts must change the merged limits (a value key), disable its limit
    (a has_ flag set false), make the joint wrap (angle_wraps), or be one of the documented
    non-limits (k_position, k_velocity: soft-limit controller gains), which change nothing. An
    accepted key that changes nothing and is not documented fails here."""
    urdf = two_link.limits.to_dict()
    assert set(LIMITS_YAML_KEYS) == set(_VALUE_ENTRIES) | set(_FLAGS) | {"angle_wraps"}
    assert IGNORED_YAML_KEYS == {"k_position", "k_velocity"}
    for key, value in _VALUE_ENTRIES.items():
        assert load_limits_yaml({"joint_limits": {"j": {key: value}}})["j"][key] is not None
        changed = _merged(two_link, {key: value}) != urdf
        assert changed is (key not in IGNORED_YAML_KEYS), key
    for flag, keys in _FLAGS.items():
        given = {k: _VALUE_ENTRIES[k] for k in keys}
        on, off = _merged(two_link, {flag: True, **given}), _merged(two_link, {flag: False, **given})
        fields = {"has_position_limits": ("position_lower", "position_upper"),
                  "has_soft_limits": ("soft_lower", "soft_upper")}.get(
            flag, (flag[len("has_"):-len("_limits")],))
        for f in fields:
            assert on[f][0] in (-1.25, 1.25), (flag, f, on[f])
            assert off[f][0] is None, (flag, f, off[f])   # None: unlimited in to_dict
        # false also removes what the URDF set (planar_2link's URDF has these four)
        if flag in ("has_position_limits", "has_velocity_limits", "has_effort_limits",
                    "has_soft_limits"):
            assert all(_merged(two_link, {flag: False})[f][0] is None for f in fields), flag
    wraps = _merged(two_link, {"angle_wraps": True})
    assert wraps["continuous"] == [True, False]
    assert [wraps[f][0] for f in ("position_lower", "position_upper", "soft_lower",
                                  "soft_upper")] == [None] * 4
    assert _merged(two_link, {"angle_wraps": False}) == urdf
    page = (Path(__file__).resolve().parents[1] / "docs" / "limits.md").read_text()
    assert "`k_position` and `k_velocity` are gains of ros2_control's soft-limit controller" in page
    assert "dyn_node does not use them" in page


def test_yaml_zero_is_a_real_limit_with_a_warning_urdf_zero_means_not_given(two_link):
    m = two_link.with_limits("joint_limits:\n  joint1: {max_velocity: 0.0, max_deceleration: 0}\n")
    assert m.limits.velocity[0] == 0.0 and m.limits.deceleration[0] == 0.0
    assert m.warnings == (
        "joint1: velocity limit 0 is not positive: applied as a real limit (any nonzero velocity "
        "violates it); for no limit remove the key or set has_velocity_limits: false",
        "joint1: deceleration limit 0 is not positive: applied as a real limit (any nonzero "
        "deceleration violates it); for no limit remove the key or set "
        "has_deceleration_limits: false")
    rate = two_link.with_limits("joint_limits:\n  joint2: {max_power: 0.0}\n").warnings
    assert rate == ("joint2: power limit 0 is not positive: applied as a real limit (any nonzero "
                    "power violates it); for no limit remove the key",)


def test_angle_wraps_drops_position_limits_given_beside_it_with_a_warning(two_link):
    m = two_link.with_limits("joint_limits:\n  joint2: {angle_wraps: true, min_position: -1.0,"
                             " max_position: 1.0}\n")
    assert m.limits.position_lower[1] == -np.inf and m.limits.position_upper[1] == np.inf
    assert m.warnings == ("joint2: angle_wraps: true, so min_position, max_position not applied "
                          "(a wrapping joint has no position limit)",)


def test_suspicious_limits_warn(two_link):
    m = two_link.with_limits(
        "joint_limits:\n"
        "  joint1: {min_position: 1.0, max_position: -1.0, max_velocity: 0.0, max_effort: 100000.0}\n"
        "  joint2: {soft_lower_limit: 1.0, soft_upper_limit: 0.5}\n")
    w = "\n".join(m.warnings)
    assert "joint1: lower position limit 1 > upper -1" in w
    assert "joint1: velocity limit 0 is not positive" in w
    assert "joint1: effort limit 100000" in w and "gravity load" in w
    assert "joint2: soft lower limit 1 > soft upper 0.5" in w
    assert len(m.warnings) == 4   # a negative limit is an error (test_negative_or_infinite_limit_is_an_error)
    assert two_link.warnings == ()
    # A realistic limit (40 N·m vs a ≈ 10 N·m gravity load) is not flagged.
    assert not any("gravity load" in x for x in two_link.with_limits(
        "joint_limits:\n  joint1: {max_effort: 40.0}\n").warnings)


def test_urdf_zero_effort_and_velocity_mean_unlimited():
    urdf = """<robot name="z"><link name="b"/><link name="l"><inertial><mass value="1"/>
      <origin xyz="0.2 0 0"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>
      </inertial></link><joint name="j" type="revolute"><parent link="b"/><child link="l"/>
      <axis xyz="0 1 0"/><limit lower="0" upper="0" effort="0" velocity="0"/></joint></robot>"""
    lim = load_model(urdf=urdf).limits
    assert lim.effort[0] == np.inf and lim.velocity[0] == np.inf
    assert lim.position_lower[0] == -np.inf and lim.position_upper[0] == np.inf


@pytest.mark.parametrize("text, code, words", [
    # a misspelt section would otherwise be ignored: the check it names silently off
    ("joint_limits: {}\nframe_limit: {panda_link8: {max_linear_speed: 0.25}}\n",
     "limits_unknown_section", ["unknown top-level key 'frame_limit'", "did you mean 'frame_limits'"]),
    ("joint_limits: {}\njoint_limit: {}\n", "limits_unknown_section", ["'joint_limit'",
                                                                      "did you mean 'joint_limits'"]),
])
def test_top_level_keys_that_would_switch_a_check_off_are_errors(text, code, words):
    with pytest.raises(ModelError) as err:
        load_limits_yaml(text)
    assert err.value.code == code
    for w in words:
        assert w in str(err.value), str(err.value)


@pytest.mark.parametrize("text", [
    "joint_limits: {}\nframe_limits: {panda_link8: {max_linear_speed: 0.25}}\n",
    "dyn_node:\n  ros__parameters:\n    joint_limits: {}\n    grasp: {frame: panda_hand}\n",
])
def test_task_sections_beside_joint_limits_are_accepted_and_left_to_task_limits(text):
    # the joint-limit parser accepts them in both forms; their keys are task_limits' to check
    assert load_limits_yaml(text) == {}


def test_task_sections_reach_the_model_and_bad_ones_are_named():
    y = ("joint_limits: {}\nframe_limits: {panda_link8: {max_linear_speed: 0.25}}\n"
         "task_wrench: {frame: panda_link8, force: [0, 0, 20]}\n")
    m = load_model(builtin="panda", limits_yaml=y)
    assert m.task_limits.frame_limits[0].max_linear_speed == 0.25
    assert m.task_limits.task_wrench.force.tolist() == [0.0, 0.0, 20.0]
    # kept by every derived model
    for d in (m.with_payload(Payload(1.0)), m.with_gravity((0.0, 0.0, -9.0))):
        assert d.task_limits is m.task_limits
    assert load_model(builtin="panda").task_limits.frame_limits == ()
    assert m.with_limits(None).task_limits.task_wrench is None
    assert m.with_limits(y.replace("0.25", "0.5")).task_limits.frame_limits[0].max_linear_speed == 0.5
    with pytest.raises(ModelError) as err:
        load_model(builtin="panda", limits_yaml=y.replace("panda_link8: {max", "panda_link9: {max"))
    assert err.value.code == "limits_unknown_frame" and "'panda_link9'" in str(err.value)
    with pytest.raises(ModelError) as err:
        load_model(builtin="panda", limits_yaml=y.replace("0.25", ".nan"))
    assert "frame_limits.panda_link8.max_linear_speed" in str(err.value)
    tip = ("joint_limits: {}\nbase_limits: {support_polygon: [[-1, -1], [1, -1], [1, 1], "
           "[-1, 1]]}\n")
    tipping = load_model(builtin="panda", limits_yaml=tip)
    with pytest.raises(ModelError) as err:
        tipping.with_gravity((9.81, 0.0, 0.0))
    assert err.value.code == "tipping_gravity"
    with pytest.raises(ModelError):
        load_model(builtin="panda", limits_yaml=tip, gravity=(0.0, 9.81, 0.0))


def test_moveit_scaling_factors_and_node_parameters_beside_joint_limits_are_accepted():
    bare = load_limits_yaml("joint_limits: {j: {max_velocity: 1.0}}\n"
                            "default_velocity_scaling_factor: 0.1\n"
                            "default_acceleration_scaling_factor: 0.1\n")
    nested = load_limits_yaml("dyn_node:\n  ros__parameters:\n    robot_model: panda\n"
                              "    joint_limits: {j: {max_velocity: 1.0}}\n")
    assert bare == nested == {"j": {"max_velocity": 1.0}}


LIMIT_KEYS = ("max_velocity", "max_acceleration", "max_deceleration", "max_jerk", "max_effort",
              "max_effort_rate", "max_rms_effort", "max_power")


@pytest.mark.parametrize("key", LIMIT_KEYS)
@pytest.mark.parametrize("value", ["-.inf", ".inf", "-1.0", "-1e-300", ".nan"])
def test_negative_or_infinite_limit_is_an_error(key, value):
    """``max_velocity: -.inf`` once read as "no limit": each limit key refuses a negative or
    non-finite value, naming joint and key (0 stays a real limit, warned about)."""
    with pytest.raises(ModelError) as e:
        load_limits_yaml(f"joint_limits:\n  joint2:\n    {key}: {value}\n")
    assert f"joint_limits.joint2.{key} must be " in str(e.value)
    assert e.value.code in ("limits_bad_value", "limits_wrong_type")
    assert load_limits_yaml(f"joint_limits:\n  joint2:\n    {key}: 0.0\n") == {"joint2": {key: 0.0}}
    assert load_limits_yaml(f"joint_limits:\n  joint2:\n    {key}: 2\n") == {"joint2": {key: 2.0}}


def test_every_bad_limit_is_named_once(two_link):
    with pytest.raises(ModelError) as e:
        two_link.with_limits("joint_limits:\n  joint1: {max_velocity: -.inf}\n"
                             "  joint2: {max_power: .inf, max_acceleration: -5.0}\n")
    assert str(e.value).count("must be a finite number ≥ 0") == 3
    assert ("joint_limits.joint1.max_velocity must be a finite number ≥ 0, got -inf (for no limit "
            "remove the key or set has_velocity_limits: false)") in str(e.value)
    assert "joint_limits.joint2.max_power must be a finite number ≥ 0, got inf (for no limit remove the key)" in str(e.value)
