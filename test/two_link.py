"""The two-link arm (shoulder about z, elbow about y) of the MuJoCo tests: ddarm's model of it (URDF, motion) and
robots that differ from it (MJCF), each test's robot made by `robot_mjcf` with what it adds."""

from __future__ import annotations

from pathlib import Path

URDF = """<robot name="two">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0.2 0 0"/><mass value="2"/>
    <inertia ixx="0.01" iyy="0.02" izz="0.02" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.15 0 0"/><mass value="1"/>
    <inertia ixx="0.005" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="100" velocity="10"/></joint>
  <joint name="elbow" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.4 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="100" velocity="10"/></joint>
</robot>
"""
MOTION = """joint_names: [shoulder, elbow]
duration: 0.6
profile: bang_bang
start: [-0.4, 0.3]
goal: [0.5, -0.6]
"""
RK4 = '<option timestep="0.001" integrator="RK4"/>'


def robot_mjcf(shoulder: str = '', elbow: str = '', *, option: str = RK4, payload: float | None = None,
               actuators: str = '', model: str = 'two') -> str:
    """The arm as MuJoCo's robot: `shoulder` and `elbow` attributes added to each joint (armature, damping, …), a
    payload body of that mass 0.3 m out on the elbow link, and `actuators` (MJCF elements) if given."""
    load = ('' if payload is None else
            f'        <body name="payload" pos="0.3 0 0"><inertial pos="0 0 0" mass="{payload}" '
            'diaginertia="1e-4 1e-4 1e-4"/></body>\n')
    block = '' if not actuators else f'  <actuator>\n    {actuators}\n  </actuator>\n'
    return (f'<mujoco model="{model}">\n  {option}\n  <worldbody>\n    <body name="l1">\n'
            f'      <joint name="shoulder" type="hinge" axis="0 0 1"{shoulder}/>\n'
            '      <inertial pos="0.2 0 0" mass="2" diaginertia="0.01 0.02 0.02"/>\n'
            '      <body name="l2" pos="0.4 0 0">\n'
            f'        <joint name="elbow" type="hinge" axis="0 1 0"{elbow}/>\n'
            '        <inertial pos="0.15 0 0" mass="1" diaginertia="0.005 0.01 0.01"/>\n'
            f'{load}      </body>\n    </body>\n  </worldbody>\n{block}</mujoco>\n')


def write_files(folder: Path, mjcf: str) -> tuple[Path, Path, Path]:
    """The robot, the URDF and the motion as files in `folder`: (MJCF, URDF, motion)."""
    paths = folder / 'two.xml', folder / 'two.urdf', folder / 'two-motion.yaml'
    for path, text in zip(paths, (mjcf, URDF, MOTION)):
        path.write_text(text)
    return paths
