"""Any URDF and motion file through the ROS graph: the UR5 (6 joints), the Panda (7 joints controlled, its
fingers locked, one a mimic joint) and the SCARA (continuous and prismatic joints) run in lockstep over DDS,
recorded as bags, give the in-process episode's numbers; a plant refuses a motion its URDF cannot run, the
driver refuses nodes started with another arm than the episode's, and the tuner sweeps its parameters' arm."""

import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from ddarm.episodes.engine import run_episode
from ddarm.episodes.indices import INDICES
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, gains_from_omega
from ddarm.physics.plant import PlantError
from ddarm.ros.driver import GraphDriver, GraphEpisodeError
from ddarm.ros.session import GraphSession
from ddarm_control.node import ControllerNode
from ddarm_sim.node import PlantNode
from ddarm_tuner.node import TunerNode

ARMS = Path(__file__).resolve().parents[1] / 'config' / 'arms'
# name: (URDF, motion file, controlled joints)
ARM_FILES = {'ur5': (ARMS / 'ur5' / 'ur5.urdf', ARMS / 'ur5' / 'ur5-motion.yaml', 6),
             'panda': (ARMS / 'panda' / 'panda.urdf', ARMS / 'panda' / 'panda-motion.yaml', 7),
             'scara': (ARMS / 'scara' / 'scara.urdf', ARMS / 'scara' / 'scara-motion.yaml', 4)}
# Short episodes keep the file fast: each arm's bang-bang motion is stretched to T.
DURATION = 0.3
OMEGA = 15.0
# Per arm, plant options that go through the graph too: limits, and a plant heavier than its model, with friction.
OPTIONS = {'ur5': dict(torque_limit='urdf'), 'panda': dict(torque_limit='paper'),
           'scara': dict(mass_scale=(1.1, 0.9, 1.2, 1.0), viscous_friction=(0.5, 0.5, 2.0, 0.1))}


def arm_spec(arm: str, controller: str, **options) -> EpisodeSpec:
    """An episode of `arm`'s motion under `controller`, with the ω rule's gains for it."""
    urdf, motion, dof = ARM_FILES[arm]
    template = EpisodeSpec(controller=controller, kp=(1.0,) * dof, kv=(1.0,) * dof, urdf=str(urdf),
                           motion=str(motion), duration=DURATION, tau=0.05, **options)
    kp, kv = gains_from_omega(template, OMEGA)
    return replace(template, kp=tuple(kp), kv=tuple(kv))


def assert_same_episode(graph, reference, scored: dict) -> None:
    """The graph's episode, the in-process one and the bag's score agree (1e-9 on the samples, relative on I)."""
    assert graph.scored('errors').shape == reference.scored('errors').shape
    np.testing.assert_allclose(graph.scored('errors'), reference.scored('errors'), rtol=0, atol=1e-9)
    np.testing.assert_allclose(graph.scored('torque'), reference.scored('torque'), rtol=0, atol=1e-9)
    for key in INDICES:
        assert graph.indices()[key] == pytest.approx(reference.indices()[key], rel=1e-9)
        assert scored[key] == pytest.approx(reference.indices()[key], rel=1e-9)
        assert scored[key] == pytest.approx(graph.indices()[key], rel=1e-9)


@pytest.fixture(scope='module')
def session(tmp_path_factory):
    """One graph session for the file: its nodes restart only when the arm or the law changes."""
    with GraphSession(tmp_path_factory.mktemp('nodes'), timeout=60.0) as graph:
        yield graph


# Law-minor order: each arm's plant starts once.
@pytest.mark.parametrize('arm, controller', [(arm, law) for arm in ARM_FILES
                                             for law in ('computed_torque', 'pd_gravity')])
def test_an_arm_of_any_urdf_and_motion_runs_through_the_graph_like_in_process(session, tmp_path, arm, controller):
    spec = arm_spec(arm, controller, **OPTIONS[arm])
    graph, scored = session.record_and_score(spec, tmp_path / 'bag')
    reference = run_episode(spec)
    assert graph.plan.joint_names == reference.plan.joint_names
    assert len(graph.plan.joint_names) == ARM_FILES[arm][2]
    assert_same_episode(graph, reference, scored)
    assert scored['spec']['urdf'] == spec.urdf and scored['spec']['motion'] == spec.motion


def test_a_waypoint_motion_on_the_z1_runs_through_the_graph_like_in_process(session, tmp_path):
    """JointTrajectory-shaped waypoints (mixed segment types: cubic, quintic, linear), the Z1's gripper locked."""
    motion = tmp_path / 'z1-waypoints.yaml'
    motion.write_text(
        'joint_names: [joint1, joint2, joint3, joint4, joint5, joint6]\n'
        'start: [-0.5, 2.1, -1.5, 0.97, 0.0, 0.3]\n'
        'points:\n'
        '  - {positions: [-0.3, 2.0, -1.4, 0.9, 0.1, 0.1], velocities: [0.6, -0.3, 0.3, -0.2, 0.3, -0.6],\n'
        '     time_from_start: 0.15}\n'
        '  - {positions: [0.0, 1.85, -1.25, 0.85, 0.2, -0.2], velocities: [0.8, -0.3, 0.3, -0.1, 0.2, -0.8],\n'
        '     accelerations: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], time_from_start: 0.3}\n'
        '  - {positions: [0.5, 1.7, -1.1, 0.77, 0.3, -0.5], time_from_start: {sec: 0, nanosec: 500000000}}\n'
        'locked: {jointGripper: -0.2}\n')
    template = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 6, kv=(1.0,) * 6, urdf=str(ARMS / 'z1' / 'z1.urdf'),
                           motion=str(motion), tau=0.1, torque_limit='urdf')
    kp, kv = gains_from_omega(template, OMEGA)
    spec = replace(template, kp=tuple(kp), kv=tuple(kv))
    graph, scored = session.record_and_score(spec, tmp_path / 'bag')
    reference = run_episode(spec)
    assert spec.duration == 0.5 and len(graph.plan.joint_names) == 6
    assert_same_episode(graph, reference, scored)


def test_a_plant_other_than_the_controllers_model_runs_through_the_graph_like_in_process(session, tmp_path):
    urdf, _, _ = ARM_FILES['ur5']
    heavier = tmp_path / 'ur5-heavier-forearm.urdf'
    text = urdf.read_text()
    forearm = text.index('<link name="forearm_link">')
    mass = re.compile(r'<mass value="2\.275"\s*/>')
    assert mass.search(text, forearm)
    heavier.write_text(text[:forearm] + mass.sub('<mass value="3.0" />', text[forearm:], count=1))
    spec = replace(arm_spec('ur5', 'computed_torque'), urdf=str(heavier), model_urdf=str(urdf))
    graph, scored = session.record_and_score(spec, tmp_path / 'bag')
    reference = run_episode(spec)
    matched = run_episode(replace(spec, urdf=str(urdf), model_urdf=None))
    assert reference.indices()['I'] != pytest.approx(matched.indices()['I'], rel=1e-6)  # the mismatch matters
    assert_same_episode(graph, reference, scored)


def test_a_plant_refuses_a_motion_naming_a_joint_its_urdf_lacks(tmp_path):
    urdf, motion, _ = ARM_FILES['ur5']
    bad = tmp_path / 'elbow-typo.yaml'
    bad.write_text(motion.read_text().replace('elbow_joint', 'elbow_jiont'))
    done = subprocess.run([sys.executable, '-m', 'ddarm_sim.node', '--ros-args', '-p', f'urdf:={urdf}',
                           '-p', f'motion:={bad}'], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stdout + done.stderr
    assert 'plant: refused to start: parameter motion' in done.stdout
    assert str(bad) in done.stdout and "'elbow_jiont'" in done.stdout and str(urdf) in done.stdout


def test_a_plant_refuses_a_motion_file_it_cannot_read(ros_context, tmp_path):
    urdf, _, _ = ARM_FILES['ur5']
    short = tmp_path / 'short.yaml'
    short.write_text('joint_names: [shoulder_pan_joint, shoulder_lift_joint]\nduration: 1.0\nprofile: bang_bang\n'
                     'start: [0.0]\ngoal: [0.5, 0.5]\n')
    for motion in (short, tmp_path / 'missing.yaml'):
        with pytest.raises(PlantError, match=r'parameter motion = .*' + re.escape(str(motion))):
            PlantNode(context=ros_context, parameter_overrides=[
                Parameter('urdf', value=str(urdf)), Parameter('motion', value=str(motion)),
                Parameter('autostart', value=False)])


def test_the_plant_publishes_the_reduced_models_joints(ros_context):
    urdf, motion, _ = ARM_FILES['panda']
    node = PlantNode(context=ros_context, parameter_overrides=[
        Parameter('urdf', value=str(urdf)), Parameter('motion', value=str(motion)),
        Parameter('autostart', value=False)])
    try:
        assert node.joints == [f'panda_joint{i}' for i in range(1, 8)]  # the fingers are locked
        np.testing.assert_array_equal(node.settings.q0, run_episode(arm_spec('panda', 'pd_gravity')).plan.q0)
    finally:
        node.destroy_node()


def test_the_driver_refuses_nodes_started_with_another_arm(ros_context):
    spec = arm_spec('ur5', 'computed_torque')
    plant = PlantNode(context=ros_context, parameter_overrides=[Parameter('autostart', value=False)])
    controller = ControllerNode('computed_torque', context=ros_context, parameter_overrides=[
        Parameter('kp', value=[225.0] * 3), Parameter('kv', value=[30.0] * 3)])
    driver = GraphDriver(context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (plant, controller, driver):
        executor.add_node(node)
    try:
        with pytest.raises(GraphEpisodeError, match=r"/plant runs another arm than the episode \(urdf is '', the "
                                                     rf"episode's '{re.escape(spec.urdf)}'; motion is ''"):
            driver.run_episode(executor, spec, timeout=30.0)
        assert plant.phase == 'idle'  # refused before anything was set or started
    finally:
        executor.shutdown()
        for node in (plant, controller, driver):
            node.destroy_node()


def test_the_tuner_sweeps_the_arm_and_motion_of_its_parameters(ros_context, tmp_path):
    urdf, motion, dof = ARM_FILES['scara']
    gains = {'kp': [225.0] * dof, 'kv': [30.0] * dof}
    tuner = TunerNode(context=ros_context, parameter_overrides=[
        Parameter('urdf', value=str(urdf)), Parameter('motion', value=str(motion)),
        *(Parameter(name, value=value) for name, value in gains.items())])
    try:
        (_, spec, plan), = tuner.specs
        assert (spec.urdf, spec.model_urdf, spec.motion) == (str(urdf), None, str(motion))
        assert spec.duration == 1.0  # duration 0: the motion's own
        assert plan.joint_names == ('shoulder_joint', 'elbow_joint', 'quill_joint', 'wrist_joint')
    finally:
        tuner.destroy_node()
    # Gains tuned for another arm are other gains: refused like gains of another period.
    gains_file = tmp_path / 'gains.yaml'
    gains_file.write_text(yaml.safe_dump({'computed_torque': {'ros__parameters': {
        **gains, 'period': 0.01, 'urdf': str(ARM_FILES['ur5'][0])}}}))
    with pytest.raises(EpisodeError, match=r"holds gains for the controller's urdf .*ur5\.urdf'; the sweep's is "
                                           rf"'{re.escape(str(urdf))}'"):
        TunerNode(context=ros_context, parameter_overrides=[
            Parameter('urdf', value=str(urdf)), Parameter('motion', value=str(motion)),
            Parameter('gains_file', value=str(gains_file))])
