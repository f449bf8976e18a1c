"""Model loading, joint-name mapping and malformed robot descriptions."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import STATE_ERROR, InputError, ModelError
from dyn_node.core.robot.model import BUILTIN_MODELS, builtin_urdf, load_model, model_from_source, urdf_hash

PANDA_ARM = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGERS = ("panda_finger_joint1", "panda_finger_joint2")


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def test_builtins_load():
    expected = {"planar_2link": ("joint1", "joint2"), "panda": PANDA_ARM,
                "ur5": ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                        "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")}
    assert set(BUILTIN_MODELS) == set(expected)
    for name, joints in expected.items():
        m = load_model(builtin=name)
        assert m.joint_names == joints and m.nv == len(joints)
        assert m.source == f"builtin:{name}" and m.urdf_hash == urdf_hash(builtin_urdf(name))
        assert m.pin_model.nq == m.pin_model.nv == m.nv
        assert m.warnings == ()
    p = load_model(builtin="panda")
    assert dict(p.locked_joints) == {f: 0.0 for f in FINGERS}
    # Locking keeps the fingers' mass (merged into the hand): total = every <mass> in the URDF.
    assert p.total_mass == pytest.approx(
        sum(float(e.get("value")) for e in ET.fromstring(p.urdf).iter("mass")), abs=1e-9)
    ur5 = load_model(builtin="ur5")
    # UR5's <transmission> tags repeat the joint names; limits still come from the <joint>s.
    np.testing.assert_array_equal(ur5.limits.effort, [150, 150, 150, 28, 28, 28])
    np.testing.assert_array_equal(ur5.limits.velocity, [3.15, 3.15, 3.15, 3.2, 3.2, 3.2])


def test_sources_equivalent(tmp_path, panda):
    f = tmp_path / "panda.urdf"
    f.write_text(panda.urdf)
    by_file = load_model(urdf_file=f, locked_joints=dict(panda.locked_joints))
    by_text = model_from_source(robot_description=panda.urdf, locked_joints=dict(panda.locked_joints))
    by_name = model_from_source(robot_model="panda")
    q = np.linspace(-1, 1, 7)
    for m in (by_file, by_text, by_name):
        assert m.joint_names == PANDA_ARM and m.urdf_hash == panda.urdf_hash
        np.testing.assert_array_equal(Dynamics(m).gravity(q), Dynamics(panda).gravity(q))
    assert by_file.source == f"file:{f}"
    assert model_from_source(robot_description_file=str(f),
                             locked_joints=dict(panda.locked_joints)).joint_names == PANDA_ARM


# --- name mapping --------------------------------------------------------------------------

def test_shuffled_extra_and_locked(panda):
    rng = np.random.default_rng(3)
    q = rng.uniform(-1, 1, 7)
    v = rng.uniform(-1, 1, 7)
    e = rng.uniform(-5, 5, 7)
    names = list(PANDA_ARM) + list(FINGERS) + ["conveyor_joint"]
    perm = rng.permutation(len(names))
    shuffled = [names[i] for i in perm]
    # Locked and unknown joints carry junk (even NaN): ignored, counted.
    pos = np.concatenate([q, [np.nan, 0.5, np.inf]])[perm]
    vel = np.concatenate([v, [np.nan, 1.0, 2.0]])[perm]
    eff = np.concatenate([e, [np.inf, 1.0, np.nan]])[perm]
    s = panda.to_model_order(shuffled, pos, vel, eff)
    np.testing.assert_array_equal(s.q, q)
    np.testing.assert_array_equal(s.v, v)
    np.testing.assert_array_equal(s.effort, e)
    assert s.ignored == 3
    s2 = panda.to_model_order(shuffled, pos, [], [])
    assert s2.v is None and s2.effort is None and s2.ignored == 3
    idx, ignored = panda.mapping(shuffled)
    assert [shuffled[i] for i in idx] == list(PANDA_ARM) and ignored == 3


def expect_input_error(code, fn, *names):
    with pytest.raises(InputError) as e:
        fn()
    assert e.value.code == code, str(e.value)
    assert e.value.failure_label == STATE_ERROR
    for n in names:
        assert n in str(e.value)
    return e.value


def test_mapping_errors(panda):
    ok = np.zeros(7)
    names = list(PANDA_ARM)
    tom = panda.to_model_order
    expect_input_error("empty", lambda: tom([], [], [], []))
    expect_input_error("length_mismatch", lambda: tom(names, np.zeros(6)))
    expect_input_error("length_mismatch", lambda: tom(names, ok, np.zeros(3)))
    expect_input_error("length_mismatch", lambda: tom(names, ok, ok, np.zeros(8)))
    expect_input_error("duplicate_names", lambda: tom(names + ["panda_joint3"], np.zeros(8)),
                       "panda_joint3")
    expect_input_error("no_model_joints", lambda: tom(["a", "b"], [0.0, 0.0]), "panda_joint1")
    expect_input_error("missing_joints", lambda: tom(names[:5] + ["x"], np.zeros(6)),
                       "panda_joint6", "panda_joint7")
    # Locked joints do not satisfy a missing arm joint.
    expect_input_error("missing_joints", lambda: tom(names[1:] + list(FINGERS), np.zeros(8)),
                       "panda_joint1")
    for bad in (np.nan, np.inf, -np.inf):
        p = ok.copy()
        p[4] = bad
        expect_input_error("non_finite", lambda: tom(names, p), "panda_joint5")
        expect_input_error("non_finite", lambda: tom(names, ok, p), "panda_joint5")
    eff = ok.copy()
    eff[2] = np.inf
    expect_input_error("non_finite", lambda: tom(names, ok, ok, eff), "panda_joint3")


def test_effort_nan_handling(panda):
    names = list(PANDA_ARM)
    ok = np.zeros(7)
    assert panda.to_model_order(names, ok, ok, np.full(7, np.nan)).effort is None
    part = np.arange(7.0)
    part[[1, 5]] = np.nan
    s = panda.to_model_order(names, ok, ok, part)
    assert np.isnan(s.effort[[1, 5]]).all()
    np.testing.assert_array_equal(s.effort[[0, 2, 3, 4, 6]], [0, 2, 3, 4, 6])


# --- malformed descriptions ----------------------------------------------------------------

ARM = """<robot name="t">
  <link name="base"/>
  <link name="l1"><inertial><mass value="1"/><origin xyz="0.3 0 0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <link name="l2"><inertial><mass value="0.5"/><origin xyz="0.2 0 0.05"/>
    <inertia ixx="0.003" ixy="0.0001" ixz="0" iyy="0.004" iyz="0" izz="0.005"/></inertial></link>
  <joint name="j1" type="{t1}"><parent link="base"/><child link="l1"/><axis xyz="0 1 0"/>
    {lim1}</joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="{c2}"/><origin xyz="0.5 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="{eff}" velocity="3"/></joint>
</robot>"""


def arm_urdf(t1="revolute", lim1='<limit lower="-1" upper="1" effort="50" velocity="2"/>',
             c2="l2", eff="20"):
    return ARM.format(t1=t1, lim1=lim1, c2=c2, eff=eff)


def expect_model_error(code, *fragments, **kw):
    with pytest.raises(ModelError) as e:
        load_model(**kw)
    assert e.value.code == code, str(e.value)
    for f in fragments:
        assert f in str(e.value), str(e.value)
    return e.value


def test_malformed_urdf(tmp_path):
    assert load_model(urdf=arm_urdf()).joint_names == ("j1", "j2")
    expect_model_error("urdf_bad_xml", "not valid XML", urdf="<robot><link name='a'></robot>")
    expect_model_error("urdf_not_robot", "<sdf>", urdf="<sdf><model/></sdf>")
    expect_model_error("urdf_no_joints", urdf="<robot name='x'><link name='a'/></robot>")
    expect_model_error("urdf_joint_type", "j1", "floating", urdf=arm_urdf(t1="floating"))
    expect_model_error("urdf_joint_type", "j1", "planar", urdf=arm_urdf(t1="planar"))
    expect_model_error("urdf_bad_link", "j2", "ghost", urdf=arm_urdf(c2="ghost"))
    expect_model_error("urdf_bad_number", "j2", "effort", "'lots'", urdf=arm_urdf(eff="lots"))
    expect_model_error("urdf_file_missing", "nope.urdf", urdf_file=tmp_path / "nope.urdf")
    expect_model_error("unknown_builtin", "pandas", "panda", builtin="pandas")
    expect_model_error("unknown_locked_joint", "j9", urdf=arm_urdf(), locked_joints={"j9": 0.0})
    expect_model_error("bad_lock", "j1", urdf=arm_urdf(), locked_joints={"j1": math.nan})
    expect_model_error("no_joints", urdf=arm_urdf(), locked_joints={"j1": 0.0, "j2": 0.0})
    expect_model_error("no_source")
    expect_model_error("no_source", builtin="panda", urdf=arm_urdf())
    with pytest.raises(ModelError) as e:
        model_from_source()
    assert e.value.code == "no_source"


def test_continuous_joint_equals_revolute():
    rev = load_model(urdf=arm_urdf())
    cont = load_model(urdf=arm_urdf(t1="continuous", lim1='<limit effort="50" velocity="2"/>'))
    nolim = load_model(urdf=arm_urdf(t1="continuous", lim1=""))
    for m in (cont, nolim):
        assert m.nv == 2 and m.pin_model.nq == m.pin_model.nv == 2
        assert m.limits.continuous.tolist() == [True, False]
        assert m.limits.position_lower[0] == -np.inf and m.limits.position_upper[0] == np.inf
    assert cont.limits.effort[0] == 50 and nolim.limits.effort[0] == np.inf
    assert nolim.limits.velocity[0] == np.inf
    rng = np.random.default_rng(8)
    d_rev, d_cont, d_nolim = Dynamics(rev), Dynamics(cont), Dynamics(nolim)
    for _ in range(20):
        q = rng.uniform(-7, 7, 2)  # beyond ±π: the angle is plain, not wrapped
        v, a = rng.uniform(-3, 3, 2), rng.uniform(-9, 9, 2)
        expected = d_rev.rnea(q, v, a)
        np.testing.assert_allclose(d_cont.rnea(q, v, a), expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(d_nolim.rnea(q, v, a), expected, rtol=0, atol=1e-12)


def test_locking_a_joint_equals_fixing_it():
    """The reduced model at a locked angle equals a URDF with that joint fixed at the angle."""
    locked = load_model(urdf=arm_urdf(), locked_joints={"j1": 0.0})
    fixed = load_model(urdf=arm_urdf(t1="fixed", lim1=""))
    assert locked.joint_names == fixed.joint_names == ("j2",)
    q, v, a = np.array([0.3]), np.array([1.0]), np.array([2.0])
    np.testing.assert_allclose(Dynamics(locked).rnea(q, v, a), Dynamics(fixed).rnea(q, v, a),
                               rtol=0, atol=1e-12)
    assert locked.to_model_order(["j1", "j2"], [np.nan, 0.3]).ignored == 1
