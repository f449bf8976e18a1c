"""ModelCache (a fleet worker's models between bags): a hit only where a fresh build gives the same
model, so a cached audit cannot differ from an uncached one."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dyn_node.errors import ModelError
from dyn_node.core.robot.model import builtin_urdf, load_model
from dyn_node.core.robot.model_source import ModelCache, build_model, model_cache_key
from dyn_node.core.robot.settings import settings_from_mapping

LIMITS = "joint_limits:\n  joint2:\n    has_effort_limits: true\n    max_effort: {}\n"


def planar(payload_mass: float = 0.0, **values):
    """The planar arm's settings; ``values`` by parameter name (validated as the node does)."""
    return replace(settings_from_mapping({"robot_model": "planar_2link", **values}),
                   payload_mass=payload_mass)


def test_a_hit_is_the_model_built_before_and_equals_a_fresh_build():
    cache = ModelCache()
    first = build_model(planar(), cache=cache)
    again = build_model(planar(), cache=cache)
    assert again is first and (cache.hits, cache.misses, len(cache)) == (1, 1, 1)
    fresh = load_model(builtin="planar_2link")  # the uncached path, written independently
    assert fresh.limits.to_dict() == again.limits.to_dict() and fresh.urdf_hash == again.urdf_hash
    q = np.array([0.3, -0.7])
    import pinocchio as pin

    assert np.array_equal(pin.computeGeneralizedGravity(fresh.pin_model, fresh.pin_model.createData(), q),
                          pin.computeGeneralizedGravity(again.pin_model, again.pin_model.createData(), q))


@pytest.mark.parametrize("change", [
    dict(gravity=[0.0, 0.0, -9.80]), dict(gravity=[-0.0, 0.0, -9.81]), dict(payload_mass=0.5),
    dict(locked_joints="joint1:0.1"), dict(robot_model="ur5"),
], ids=lambda c: next(iter(c)) + "=" + str(next(iter(c.values()))))
def test_every_model_input_is_in_the_key(change):
    # -0.0 is its own key: a tuple key would equal 0.0's, while the evidence prints it apart
    assert model_cache_key(planar()) != model_cache_key(planar(**change))


def test_the_urdf_text_and_the_files_bytes_are_in_the_key(tmp_path):
    urdf = builtin_urdf("planar_2link")
    s = settings_from_mapping({"robot_description": urdf})
    assert model_cache_key(s) != model_cache_key(replace(s, robot_description=urdf + " "))
    f = tmp_path / "arm.urdf"
    f.write_text(urdf)
    by_file = settings_from_mapping({"robot_description_file": str(f)})
    k = model_cache_key(by_file)
    f.write_text(urdf + "\n")
    assert model_cache_key(by_file) != k
    assert model_cache_key(s, "<robot/>") != model_cache_key(s)  # the topic's URDF too


def test_a_limits_file_edited_between_bags_is_built_again(tmp_path):
    lim = tmp_path / "limits.yaml"
    lim.write_text(LIMITS.format(7.0))
    cache = ModelCache()
    a = build_model(planar(limits_file=str(lim)), cache=cache)
    lim.write_text(LIMITS.format(9.0))  # same path, other content
    b = build_model(planar(limits_file=str(lim)), cache=cache)
    assert (a.limits.effort[1], b.limits.effort[1]) == (7.0, 9.0)
    assert (cache.hits, cache.misses) == (0, 2)


def test_failures_are_not_cached_and_say_what_an_uncached_build_says(tmp_path):
    cache = ModelCache()
    missing = planar(limits_file=str(tmp_path / "gone.yaml"))
    with pytest.raises(ModelError) as uncached:
        build_model(missing)
    with pytest.raises(ModelError) as cached:
        build_model(missing, cache=cache)
    assert str(cached.value) == str(uncached.value) and len(cache) == 0
    with pytest.raises(ModelError):
        build_model(planar(robot_model="no_such_robot"), cache=cache)
    assert len(cache) == 0


def test_least_recently_used_is_dropped():
    cache = ModelCache(size=2)
    a = build_model(planar(), cache=cache)
    build_model(planar(payload_mass=0.5), cache=cache)
    assert build_model(planar(), cache=cache) is a  # a is now the most recent
    build_model(planar(payload_mass=1.0), cache=cache)  # drops payload 0.5
    assert len(cache) == 2 and build_model(planar(), cache=cache) is a
    misses = cache.misses
    build_model(planar(payload_mass=0.5), cache=cache)
    assert cache.misses == misses + 1
