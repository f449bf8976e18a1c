"""Settings: every parameter validated as a whole; the shipped YAML holds every default."""
from __future__ import annotations

import math
import re
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from dyn_node.errors import SettingsError
from dyn_node.core.robot.settings import PARAMETERS, Settings, parse_locked_joints, settings_from_mapping

CONFIG = Path(__file__).resolve().parents[1] / "config" / "dyn_node.yaml"


def test_yaml_holds_every_parameter_with_its_default():
    data = yaml.safe_load(CONFIG.read_text())
    params = data["dyn_node"]["ros__parameters"]
    assert params == {p.name: p.default for p in PARAMETERS}
    assert settings_from_mapping(params) == Settings()


def test_each_settings_field_declares_its_parameter_and_default():
    """One source: every Settings field is one parameter (same order, '.' → '_'), and the
    field's default is its parameter's default as settings_from_mapping reads it."""
    assert [p.name.replace(".", "_") for p in PARAMETERS] == [f.name for f in fields(Settings)]
    for p in PARAMETERS:
        assert settings_from_mapping({p.name: p.default}) == Settings(), p.name
    assert Settings().to_parameters() == {p.name: p.default for p in PARAMETERS}


def test_defaults_from_the_issue():
    s = Settings()
    assert s.gravity == (0.0, 0.0, -9.81) and s.effort_warn_ratio == 0.9 and s.stale_timeout == 0.5
    assert s.diagnostics_period == 1.0 and s.controller_status_period == 0.1
    assert s.tracking_tolerance == 0.05 and s.acceleration_filter_hz == 0.0
    assert s.acceleration_source == "finite_difference" and s.sample_period == 0.001
    assert settings_from_mapping(Settings().to_parameters()) == Settings()


@pytest.mark.parametrize("name,value,why", [
    ("effort_warn_ratio", math.nan, "finite"),
    ("effort_warn_ratio", 1.5, "outside"),
    ("stale_timeout", -1.0, "outside"),
    ("stale_timeout", "0.5", "number"),
    ("include_friction", 1, "true or false"),
    ("qos_depth", 0, "outside"),
    ("qos_depth", 2.5, "integer"),
    ("gravity", [0.0, -9.81], "3 numbers"),
    ("gravity", [0.0, 0.0, math.inf], "finite"),
    ("payload.com", ["a", 0.0, 0.0], "3 numbers"),
    ("payload.mass", -0.1, "outside"),
    ("acceleration_source", "central", "finite_difference"),
    ("locked_joints", "a=x", "not a number"),
    ("locked_joints", "a, a=1", "twice"),
    ("no_such_parameter", 1.0, "unknown"),
])
def test_invalid_values_rejected_with_reason(name, value, why):
    base = Settings(stale_timeout=0.7)
    with pytest.raises(SettingsError, match=why) as info:
        settings_from_mapping({"effort_warn_ratio": 0.8, name: value}, base=base)
    # the message leads with the parameter it rejects, whichever check rejected it
    assert re.match(rf"(unknown )?parameter '{re.escape(name)}'|{re.escape(name)}: ", str(info.value)), info.value
    assert info.value.code == "bad_parameter"
    # nothing half-applied: the valid effort_warn_ratio taken before the bad value left base as built
    assert base == Settings(stale_timeout=0.7)


def test_valid_update_over_base():
    s = settings_from_mapping({"payload.mass": 1.5, "payload.com": [0, 0, 0.1], "locked_joints": "j1, j2=0.5"},
                              base=Settings(robot_model="panda"))
    assert s.robot_model == "panda" and s.payload_mass == 1.5 and s.payload_com == (0.0, 0.0, 0.1)
    assert s.locked_joints == (("j1", 0.0), ("j2", 0.5))
    assert s.model_key() != Settings(robot_model="panda").model_key()


def test_locked_joints_parse_and_every_spec_has_description():
    assert parse_locked_joints("") == ()
    assert parse_locked_joints(" a = -0.25 ,b") == (("a", -0.25), ("b", 0.0))
    for spec in PARAMETERS:
        assert spec.description
        if spec.low is not None:
            for value in (spec.default if spec.kind == "double_array" else [spec.default]):
                assert spec.low <= value <= spec.high


def test_per_joint_arrays_and_contact_thresholds():
    """observer_gain and the thresholds take one value or several, each within its range;
    collision_threshold must be ≥ contact_threshold where the two pair up."""
    s = settings_from_mapping({"observer_gain": [10.0, 20.0], "contact_threshold": [0.1],
                               "collision_threshold": [0.3, 0.4]})
    assert s.observer_gain == (10.0, 20.0) and s.collision_threshold == (0.3, 0.4)
    for bad, why in (({"observer_gain": []}, "one or more numbers"),
                     ({"observer_gain": [50.0, -1.0]}, "has a value outside"),
                     ({"contact_threshold": [0.3]}, "must be ≥ contact_threshold"),
                     ({"contact_threshold": [0.1, 0.1], "collision_threshold": [0.3, 0.3, 0.3]},
                      "give one value or one per joint"),
                     ({"gravity": [0.0, -9.81]}, "must be 3 numbers")):
        with pytest.raises(SettingsError, match=why):
            settings_from_mapping(bad)
