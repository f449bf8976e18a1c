"""Task-space limits configuration (dyn_node.core.robot.task_limits): the issue's YAML parses into the typed
sections, and bad configuration is rejected with a message naming what and where."""
from __future__ import annotations

import dataclasses
import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

from dyn_node.errors import ModelError
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.task_limits import (
          LIMITS_FILE_KEYS, UNUSED_TOP_LEVEL_KEYS, check_tipping_gravity, did_you_mean,
          limits_mapping, parse_task_limits, support_polygon)

SRC = "config/limits.yaml"

ISSUE_EXAMPLE = """
default_velocity_scaling_factor: 0.1
default_acceleration_scaling_factor: 0.1
joint_limits:
  panda_joint1: {max_velocity: 2.0}
frame_limits:                 # any URDF link
  panda_link8:
    point: [0.0, 0.0, 0.1]
    max_linear_speed: 0.25
    max_angular_speed: 3.0
    max_linear_acceleration: 10.0
    max_transferred_energy: 2.0
robot_limits:
  max_kinetic_energy: 5.0
task_wrench: {frame: panda_link8, force: [0, 0, 20], torque: [0, 0, 0]}
base_limits: {max_force: 400.0, max_moment: 150.0, base_mass: 20.0, base_com: [0, 0, 0.1],
              support_polygon: [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]}
grasp: {frame: panda_hand, normal_axis: [0, 1, 0], friction_coefficient: 0.5, grip_force: 40.0, faces: 2}
"""


@pytest.fixture(scope="module")
def panda_links() -> tuple[str, ...]:
    urdf = load_model(builtin="panda").urdf
    return tuple(link.get("name") for link in ET.fromstring(urdf).findall("link"))


def _parse(text_or_map, links):
    data = yaml.safe_load(text_or_map) if isinstance(text_or_map, str) else text_or_map
    return parse_task_limits(data, frames=links, source=SRC)


def _error(text_or_map, links) -> ModelError:
    with pytest.raises(ModelError) as e:
        _parse(text_or_map, links)
    assert str(e.value).startswith(SRC), str(e.value)    # every message says which file
    return e.value


def _with(section: str, **entries) -> dict:
    base = yaml.safe_load(ISSUE_EXAMPLE)
    base[section] = {**base[section], **entries}
    return base


def test_issue_example_parses_against_the_panda_links(panda_links):
    t = _parse(ISSUE_EXAMPLE, panda_links)
    (f,) = t.frame_limits
    assert f.frame == "panda_link8" and f.point.tolist() == [0.0, 0.0, 0.1]
    assert (f.max_linear_speed, f.max_angular_speed, f.max_linear_acceleration,
            f.max_transferred_energy) == (0.25, 3.0, 10.0, 2.0)
    assert t.robot_limits.max_kinetic_energy == 5.0
    assert t.task_wrench.frame == "panda_link8" and t.task_wrench.force.tolist() == [0, 0, 20]
    b = t.base_limits
    assert (b.max_force, b.max_moment, b.base_mass) == (400.0, 150.0, 20.0)
    assert b.base_com.tolist() == [0, 0, 0.1] and t.tipping
    assert b.support_polygon.vertices.tolist() == [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]
    np.testing.assert_allclose(b.support_polygon.centroid, [0, 0], atol=1e-17)
    g = t.grasp
    assert g.frame == "panda_hand" and g.normal_axis.tolist() == [0, 1, 0]
    assert g.max_tangential_force == 0.5 * 40.0 * 2
    assert t.unused_keys == ("default_acceleration_scaling_factor",
                             "default_velocity_scaling_factor")
    assert t.source == SRC
    json.dumps(t.to_dict())       # evidence-record ready


def test_absent_limits_are_unlimited_and_absent_sections_none(panda_links):
    t = _parse("frame_limits: {panda_hand: {max_linear_speed: 0.25}}", panda_links)
    f = t.frame_limits[0]
    assert f.point.tolist() == [0, 0, 0] and math.isinf(f.max_angular_speed)
    assert (t.robot_limits, t.task_wrench, t.base_limits, t.grasp) == (None,) * 4
    assert not t.tipping
    assert t.to_dict()["frame_limits"]["panda_hand"]["max_angular_speed"] is None
    t = _parse("joint_limits: {}", panda_links)
    assert t.frame_limits == () and t.unused_keys == ()


def test_results_are_frozen(panda_links):
    t = _parse(ISSUE_EXAMPLE, panda_links)
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.grasp.faces = 3
    with pytest.raises(ValueError):
        t.frame_limits[0].point[0] = 1.0           # arrays are read-only too
    with pytest.raises(ValueError):
        t.base_limits.support_polygon.vertices[0, 0] = 1.0


def test_ros_parameters_form(panda_links):
    data = {"/**": {"ros__parameters": yaml.safe_load(ISSUE_EXAMPLE)},
            "dyn_sim": {"ros__parameters": {"timestep": 0.001}}}
    t = _parse(data, panda_links)
    assert t.grasp.frame == "panda_hand"
    assert t.source == f"{SRC}: /**.ros__parameters"
    # a misspelt section inside ros__parameters is named with where it stands
    data["/**"]["ros__parameters"]["frame_limit"] = data["/**"]["ros__parameters"].pop("frame_limits")
    e = _error(data, panda_links)
    assert "/**.ros__parameters: unknown top-level key 'frame_limit'" in str(e)
    assert "did you mean 'frame_limits'" in str(e)


def test_ros_parameters_form_with_two_nodes_is_ambiguous(panda_links):
    data = {n: {"ros__parameters": {"joint_limits": {}}} for n in ("a", "b")}
    assert "several nodes" in str(_error(data, panda_links))


def test_unknown_top_level_keys_are_errors(panda_links):
    # without this check a misspelt section silently switches a safety check off
    e = _error("joint_limits: {}\nframe_limit: {panda_hand: {max_linear_speed: 0.25}}",
               panda_links)
    assert "unknown top-level key 'frame_limit' (did you mean 'frame_limits'?)" in str(e)
    assert e.code == "limits_unknown_section"
    e = _error("frame_limit: {panda_hand: {max_linear_speed: 0.25}}", panda_links)
    assert "did you mean 'frame_limits'" in str(e)
    # dyn_node's own node parameters are not a limits file's
    e = _error({"dyn_node": {"ros__parameters": {"joint_limits": {}, "robot_model": "panda"}}},
               panda_links)
    assert "unknown top-level key 'robot_model'" in str(e)


def test_the_key_sets_the_loader_needs():
    assert LIMITS_FILE_KEYS == {"joint_limits", "frame_limits", "robot_limits", "task_wrench",
                                "base_limits", "grasp", "default_velocity_scaling_factor",
                                "default_acceleration_scaling_factor"}
    assert UNUSED_TOP_LEVEL_KEYS < LIMITS_FILE_KEYS
    mapping, where = limits_mapping({"joint_limits": {}}, source=SRC)
    assert mapping == {"joint_limits": {}} and where == SRC


@pytest.mark.parametrize("value", ["fast", math.nan, -0.1, 0, True])
def test_unused_scaling_factors_must_still_be_numbers(panda_links, value):
    e = _error({"joint_limits": {}, "default_velocity_scaling_factor": value}, panda_links)
    assert "default_velocity_scaling_factor must be a finite number > 0" in str(e)


def test_empty_or_non_mapping_file(panda_links):
    assert "empty" in str(_error({}, panda_links))
    assert "expected a mapping" in str(_error([1, 2], panda_links))


@pytest.mark.parametrize("section,key,suggested", [
    ("frame_limits", "max_linear_sped", "max_linear_speed"),
    ("robot_limits", "max_kinetic_enery", "max_kinetic_energy"),
    ("task_wrench", "forces", "force"),
    ("base_limits", "support_polygone", "support_polygon"),
    ("grasp", "friction_coeficient", "friction_coefficient"),
])
def test_unknown_keys_suggest_the_intended_one(panda_links, section, key, suggested):
    data = yaml.safe_load(ISSUE_EXAMPLE)
    target = data[section]["panda_link8"] if section == "frame_limits" else data[section]
    target[key] = 1.0
    e = _error(data, panda_links)
    where = "frame_limits.panda_link8" if section == "frame_limits" else section
    assert f"{where}: unknown key '{key}' (did you mean '{suggested}'?)" in str(e)
    assert e.code == "limits_unknown_key"


@pytest.mark.parametrize("text,where", [
    ("frame_limits: {panda_link9: {max_linear_speed: 0.25}}", "frame_limits"),
    ("task_wrench: {frame: panda_link9, force: [0, 0, 1]}", "task_wrench.frame"),
    ("grasp: {frame: panda_link9, normal_axis: [0, 1, 0], friction_coefficient: 0.5, "
     "grip_force: 40.0, faces: 2}", "grasp.frame"),
])
def test_a_frame_not_in_the_urdf_is_named_with_close_matches(panda_links, text, where):
    e = _error(text, panda_links)
    assert f"{where}: frame 'panda_link9' is not a link of the URDF (close: " in str(e)
    assert "panda_link8" in str(e) and e.code == "limits_unknown_frame"


def test_a_frame_with_no_close_match_lists_the_links():
    e = _error("frame_limits: {gripper: {max_linear_speed: 0.25}}", ("base", "tool"))
    assert "frame 'gripper' is not a link of the URDF (links: base, tool)" in str(e)


@pytest.mark.parametrize("section,key,value,message", [
    ("grasp", "friction_coefficient", -0.5, "grasp.friction_coefficient must be a finite number ≥ 0"),
    ("grasp", "friction_coefficient", math.nan, "must be a finite number ≥ 0"),
    ("grasp", "friction_coefficient", "0.5",
     "grasp.friction_coefficient must be a finite number ≥ 0"),
    ("grasp", "grip_force", 0.0, "grasp.grip_force must be a finite number > 0"),
    ("grasp", "grip_force", math.nan, "grasp.grip_force must be a finite number > 0"),
    ("grasp", "normal_axis", [0, math.nan, 1], "grasp.normal_axis must be 3 finite numbers"),
    ("base_limits", "max_force", math.nan, "base_limits.max_force must be a finite number > 0"),
    ("base_limits", "base_com", [0, math.inf, 0], "base_limits.base_com must be 3 finite numbers"),
    ("grasp", "faces", 0, "grasp.faces must be a whole number ≥ 1"),
    ("grasp", "faces", 2.0, "grasp.faces must be a whole number ≥ 1"),
    ("grasp", "faces", True, "grasp.faces must be a whole number ≥ 1"),
    ("grasp", "normal_axis", [0, 0, 0], "grasp.normal_axis must be a nonzero vector"),
    ("grasp", "normal_axis", [0, 1], "grasp.normal_axis must be a list of 3 numbers"),
    ("task_wrench", "force", [0, 0, math.nan], "task_wrench.force must be 3 finite numbers"),
    ("task_wrench", "torque", [0, 0, 0, 1], "task_wrench.torque must be a list of 3 numbers"),
    ("base_limits", "max_force", -400.0, "base_limits.max_force must be a finite number > 0"),
    ("base_limits", "max_moment", math.inf, "base_limits.max_moment must be a finite number > 0"),
    ("base_limits", "base_mass", -1.0, "base_limits.base_mass must be a finite number ≥ 0"),
    ("base_limits", "base_com", [0, 0], "base_limits.base_com must be a list of 3 numbers"),
    ("robot_limits", "max_kinetic_energy", "5 J",
     "robot_limits.max_kinetic_energy must be a finite number > 0"),
])
def test_bad_values_are_rejected_naming_section_and_key(panda_links, section, key, value, message):
    assert message in str(_error(_with(section, **{key: value}), panda_links))


@pytest.mark.parametrize("key,value", [("max_linear_speed", 0.0), ("max_angular_speed", -3.0),
                                       ("max_linear_acceleration", math.nan),
                                       ("max_transferred_energy", False)])
def test_bad_frame_limits_name_the_frame(panda_links, key, value):
    data = yaml.safe_load(ISSUE_EXAMPLE)
    data["frame_limits"]["panda_link8"][key] = value
    assert f"frame_limits.panda_link8.{key} must be a finite number > 0" in str(
        _error(data, panda_links))


def test_sections_that_check_nothing_or_miss_keys(panda_links):
    e = _error("frame_limits: {panda_hand: {point: [0, 0, 0.1]}}", panda_links)
    assert "frame_limits.panda_hand configures no check" in str(e)
    assert "configures no check" in str(_error("robot_limits: {}", panda_links))
    assert "configures no check" in str(_error("task_wrench: {frame: panda_hand}", panda_links))
    assert "configures no check" in str(_error("base_limits: {base_mass: 3.0}", panda_links))
    assert "frame_limits must be a mapping" in str(_error("frame_limits: {}", panda_links))
    assert "grasp must be a mapping" in str(_error("grasp:", panda_links))
    e = _error("grasp: {frame: panda_hand, normal_axis: [0, 1, 0], friction_coefficient: 0.5}",
               panda_links)
    assert "grasp: missing grip_force, faces" in str(e)


def test_base_mass_without_tipping_or_com_is_an_error(panda_links):
    e = _error("base_limits: {max_force: 400.0, base_mass: 20.0, base_com: [0, 0, 0.1]}",
               panda_links)
    assert "used only for tipping" in str(e)
    e = _error("base_limits: {base_mass: 20.0, support_polygon: [[0, 0], [1, 0], [0, 1]]}",
               panda_links)
    assert "base_mass 20 kg needs base_com" in str(e)
    b = _parse("base_limits: {support_polygon: [[0, 0], [1, 0], [0, 1]]}", panda_links).base_limits
    assert b.base_mass == 0.0 and b.base_com.tolist() == [0, 0, 0] and math.isinf(b.max_force)


def test_grasp_normal_axis_is_normalised_and_mu_zero_is_frictionless(panda_links):
    g = _parse(_with("grasp", normal_axis=[0, 0, -2.0], friction_coefficient=0.0),
               panda_links).grasp
    assert g.normal_axis.tolist() == [0, 0, -1.0] and g.max_tangential_force == 0.0


# --- support polygon -----------------------------------------------------------------------------

W = "base_limits.support_polygon"


def test_clockwise_polygon_is_made_counter_clockwise():
    cw = [[-0.3, 0.3], [0.3, 0.3], [0.3, -0.3], [-0.3, -0.3]]
    p = support_polygon(cw, W)
    assert p.vertices.tolist() == cw[::-1]
    x, y = p.vertices[:, 0], p.vertices[:, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0       # positive area: CCW
    # outward normals: the centroid is on the inner side of every edge, by its half width
    np.testing.assert_allclose(p.offsets - p.normals @ p.centroid, 0.3, rtol=1e-15)


def test_collinear_vertices_are_kept():
    p = support_polygon([[0, 0], [0.5, 0], [1, 0], [1, 1], [0, 1]], W)
    assert len(p.vertices) == 5
    np.testing.assert_allclose(p.centroid, [0.5, 0.5], rtol=1e-15)


@pytest.mark.parametrize("points,message", [
    ([[0, 0], [1, 0]], "must be a list of at least 3 [x, y] points"),
    ([[0, 0], [1, 0], [1]], "must be a list of at least 3 [x, y] points"),
    ([[0, 0], [1, 0], [0, "a"]], "must be a list of at least 3 [x, y] points"),
    ([[0, 0], [1, 0], [0, math.nan]], "must be finite points"),
    ([[0, 0], [1, 0], [1, 0], [0, 1]], "the point [1.0, 0.0] is repeated"),
    ([[0, 0], [1, 0], [2, 0]], "collinear"),
    ([[0, 0], [2, 0], [2, 2], [1, 0.5], [0, 2]], "is not convex: it turns the other way at [1.0, 0.5]"),
    ([[0, 0], [1, 1], [1, 0], [0, 1]], "is not convex"),                     # a bow tie
    ([[0, 1], [0.588, -0.809], [-0.951, 0.309], [0.951, 0.309], [-0.588, -0.809]],
     "is not convex (it crosses itself)"),                                    # a pentagram
    ([[0, 0], [2, 0], [1, 0], [1, 1]], "is not convex"),                     # a spike back
])
def test_bad_polygons_are_rejected(points, message):
    with pytest.raises(ModelError) as e:
        support_polygon(points, W)
    assert message in str(e.value) and str(e.value).startswith(W)
    assert e.value.code == "limits_bad_polygon"


def test_bad_polygon_in_a_file_names_the_file_and_key(panda_links):
    e = _error(_with("base_limits", support_polygon=[[0, 0], [1, 0]]), panda_links)
    assert str(e).startswith(f"{SRC}: {W} must be a list of at least 3")


# --- gravity for tipping -------------------------------------------------------------------------

def test_tipping_needs_gravity_along_minus_z(panda_links):
    t = _parse(ISSUE_EXAMPLE, panda_links)
    check_tipping_gravity(t, [0.0, 0.0, -9.81], source=SRC)
    check_tipping_gravity(t, [0.0, 0.0, -1.62], source=SRC)        # the Moon is fine
    for g in ([9.81, 0, 0], [0, 0, 9.81], [0, 0.1, -9.81], [0, 0, 0], [0, 0, math.nan]):
        with pytest.raises(ModelError) as e:
            check_tipping_gravity(t, g, source=SRC)
        assert "tipping needs gravity along the root's −z" in str(e.value)
        assert e.value.code == "tipping_gravity"
    # no support polygon, no tipping: a wall mount keeps its base force and moment limits
    bolted = _parse("base_limits: {max_force: 400.0}", panda_links)
    check_tipping_gravity(bolted, [9.81, 0, 0], source=SRC)


def test_did_you_mean():
    assert did_you_mean("grasps", LIMITS_FILE_KEYS) == " (did you mean 'grasp'?)"
    assert did_you_mean("zzzz", LIMITS_FILE_KEYS) == ""


@pytest.mark.parametrize("section,entries,message", [
    ("grasp", {"friction_coefficient": -0.5},
     "grasp.friction_coefficient must be a finite number ≥ 0"),
    ("grasp", {"frame": "panda_hnd"}, "grasp.frame: frame 'panda_hnd' is not a link of the URDF"),
    ("base_limits", {"support_polygon": [[0, 0], [1, 0]]},
     "base_limits.support_polygon must be a list of at least 3 [x, y] points"),
    ("base_limits", {"support_polygon": [[0, 0], [2, 0], [2, 2], [1, 0.5], [0, 2]]},
     "base_limits.support_polygon is not convex"),
    ("base_limits", {"max_moment": math.nan}, "base_limits.max_moment must be a finite number > 0"),
])
def test_a_bad_limits_file_is_refused_by_the_model_naming_file_and_key(tmp_path, section,
                                                                       entries, message):
    """The same errors through load_model and with_limits from a file on disk: the message
    starts with the file's path and names the section and key."""
    path = tmp_path / "limits.yaml"
    path.write_text(yaml.safe_dump(_with(section, **entries)))
    for load in (lambda: load_model(builtin="panda", limits_yaml=path),
                 lambda: load_model(builtin="panda").with_limits(path)):
        with pytest.raises(ModelError) as e:
            load()
        assert str(path) in str(e.value) and message in str(e.value), str(e.value)


def test_the_model_refuses_tipping_under_tilted_gravity(tmp_path):
    """load_model, with_limits and with_gravity all run the tipping-gravity check; without a
    support polygon the base limits stay under any gravity."""
    tilted = [2.0, 0.0, -9.6]
    data = yaml.safe_load(ISSUE_EXAMPLE)
    with pytest.raises(ModelError, match="tipping needs gravity along the root's −z"):
        load_model(builtin="panda", limits_yaml=data, gravity=tilted)
    with pytest.raises(ModelError, match="tipping needs gravity along the root's −z"):
        load_model(builtin="panda", gravity=tilted).with_limits(data)
    upright = load_model(builtin="panda", limits_yaml=data)
    assert upright.task_limits.tipping
    with pytest.raises(ModelError, match="tipping needs gravity along the root's −z"):
        upright.with_gravity(tilted)
    del data["base_limits"]["support_polygon"], data["base_limits"]["base_mass"], \
        data["base_limits"]["base_com"]
    bolted = load_model(builtin="panda", limits_yaml=data, gravity=tilted)
    assert not bolted.task_limits.tipping and bolted.task_limits.base_limits.max_force == 400.0


def test_every_base_and_grasp_key_and_kind_is_in_the_limits_page():
    from pathlib import Path

    from dyn_node.core.robot.task_limits import BASE_LIMIT_KEYS, GRASP_KEYS

    page = (Path(__file__).resolve().parents[1] / "docs" / "limits.md").read_text()
    for section, keys in (("base_limits", BASE_LIMIT_KEYS), ("grasp", GRASP_KEYS)):
        for key in keys:
            assert f"| `{section}.{key}` |" in page, (section, key)
    for kind in ("base_force", "base_moment", "tipping", "grasp_slip"):
        assert f"kind `{kind}`" in page and f"| `{kind}` | yes, exact |" in page, kind
