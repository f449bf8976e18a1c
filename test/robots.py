"""Robot descriptions shared by the tests, and the planar 2-link arm's closed-form dynamics."""
from __future__ import annotations

import math

import numpy as np

# A branched tree with every joint kind a loaded model can hold: revolute about a principal and a
# non-principal axis, prismatic along both, a continuous joint (loaded as revolute), a fixed joint
# merged into its parent, rotated joint origins, inertial frames rotated and offset from the link.
BRANCHED_URDF = """<robot name="branched">
  <link name="base"/>
  <link name="a"><inertial><origin xyz="0.1 0.02 -0.03" rpy="0.3 -0.2 0.5"/><mass value="2.0"/>
    <inertia ixx="0.05" iyy="0.04" izz="0.03" ixy="0.002" ixz="-0.001" iyz="0.003"/></inertial></link>
  <link name="b"><inertial><origin xyz="0.0 0.2 0.1" rpy="0 0.4 0"/><mass value="1.2"/>
    <inertia ixx="0.02" iyy="0.03" izz="0.01" ixy="0" ixz="0.001" iyz="0"/></inertial></link>
  <link name="c"><inertial><origin xyz="0.05 0 0.02"/><mass value="0.7"/>
    <inertia ixx="0.004" iyy="0.005" izz="0.006" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="d"><inertial><origin xyz="0 0 0.1"/><mass value="0.4"/>
    <inertia ixx="0.001" iyy="0.001" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="a"/>
    <origin xyz="0 0 0.3" rpy="0.1 0.2 0.3"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="100" velocity="3"/></joint>
  <joint name="j2" type="prismatic"><parent link="a"/><child link="b"/>
    <origin xyz="0.2 0 0" rpy="0 0.5 0"/><axis xyz="0.6 0 0.8"/><limit lower="-0.5" upper="0.5" effort="100" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="b"/><child link="c"/>
    <origin xyz="0 0.3 0" rpy="-0.4 0 0.2"/><axis xyz="0.267261 0.534522 0.801784"/><limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
  <joint name="j4" type="revolute"><parent link="a"/><child link="d"/>
    <origin xyz="0 -0.2 0.1"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
  <link name="c_tool"><inertial><origin xyz="0 0.05 0.1" rpy="0.2 0 0"/><mass value="0.3"/>
    <inertia ixx="0.001" iyy="0.002" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="e"><inertial><origin xyz="0.03 0 0.2"/><mass value="0.6"/>
    <inertia ixx="0.002" iyy="0.002" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="f"><inertial><origin xyz="0 0.05 0.05"/><mass value="0.5"/>
    <inertia ixx="0.001" iyy="0.001" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j3_tool" type="fixed"><parent link="c"/><child link="c_tool"/>
    <origin xyz="0.1 0.1 0.1" rpy="0.5 0 0"/></joint>
  <joint name="j5" type="prismatic"><parent link="d"/><child link="e"/>
    <origin xyz="0 0 0.1" rpy="-0.4 0 0.9"/><axis xyz="1 0 0"/><limit lower="-0.5" upper="0.5" effort="100" velocity="1"/></joint>
  <joint name="j6" type="continuous"><parent link="e"/><child link="f"/>
    <origin xyz="0 0.1 0.1"/><axis xyz="0 1 0"/><limit effort="10" velocity="2"/></joint>
</robot>"""


# The built-in planar_2link: point masses M1, M2 at the tips of links L1, L2 (m, kg), joints about
# the same horizontal axis, gravity G (m/s²).
M1, M2, L1, L2, G = 1.5, 1.0, 0.5, 0.4, 9.81


def two_link_terms(q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, C, g) of the point-mass arm in the textbook closed form, with Pinocchio's C
    factorisation (Ṁ = C + Cᵀ), so τ = M a + C v + g."""
    c1, c2, s2 = math.cos(q[0]), math.cos(q[1]), math.sin(q[1])
    c12 = math.cos(q[0] + q[1])
    M = np.array([[M1 * L1**2 + M2 * (L1**2 + L2**2 + 2 * L1 * L2 * c2), M2 * (L2**2 + L1 * L2 * c2)],
                  [M2 * (L2**2 + L1 * L2 * c2), M2 * L2**2]])
    h = -M2 * L1 * L2 * s2
    C = np.array([[h * v[1], h * (v[0] + v[1])], [-h * v[0], 0.0]])
    g = np.array([(M1 + M2) * G * L1 * c1 + M2 * G * L2 * c12, M2 * G * L2 * c12])
    return M, C, g


def with_friction_urdf(text: str) -> str:
    """The URDF with distinct damping and Coulomb friction on every moving joint's <dynamics>."""
    import xml.etree.ElementTree as ET
    root = ET.fromstring(text)
    for i, j in enumerate(root.findall("joint")):
        if j.get("type") in ("revolute", "continuous", "prismatic"):
            for d in j.findall("dynamics"):
                j.remove(d)
            ET.SubElement(j, "dynamics", damping=str(0.1 + 0.02 * i), friction=str(0.3 + 0.05 * i))
    return ET.tostring(root, encoding="unicode")


def fast_panda_points(limits, ready: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(times, positions) of a fast Panda motion: 0.6 s segments out, back and the other way, at
    90 % of the speed limits when interpolated as quintics (a quintic's peak speed is 1.875·Δ/T)."""
    sign = np.array([1.0, -0.6, -1.0, 1.0, 1.0, -1.0, 1.0])
    seg = 0.6
    big = 0.9 * limits.velocity * seg / 1.875 * sign
    times = np.array([0.1, 0.1 + seg, 0.1 + 2 * seg, 0.1 + 3 * seg])
    return times, np.vstack([ready, ready + big, ready, ready - 0.5 * big])
