"""Robot descriptions shared by the tests."""

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
