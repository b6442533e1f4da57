"""Bad input on the graph (docs/faults.md 1-11, 13): refused with the problem named, nothing integrated, no crash."""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ddarm.control.laws import ComputedTorqueLaw, Measurement, ReferencePoint
from ddarm_control.node import ControllerNode
from ddarm.physics.arm import Arm
from ddarm.physics.dynamics import chain_from_model
from ddarm_sim.node import ENDED, RUNNING, PlantNode
from ddarm.ros.interface import (DIAGNOSTICS_QOS, REFERENCE_QOS, SAMPLE_QOS, joint_state_msg,
                                     reference_msg)
from ddarm.episodes.spec import EpisodeSpec, plan_episode
from conftest import claim_domain_id
from graph_helpers import overrides

JOINTS = ['joint1', 'joint2', 'joint3']
ROOT = Path(__file__).resolve().parent.parent
FAR_FUTURE = 2**31 - 1  # s: the largest stamp a builtin_interfaces/Time holds


class Probe:
    """A test node that talks to the graph like a peer would, and hears what comes back."""

    def __init__(self, context, *nodes):
        self.node = rclpy.create_node('probe', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        for node in (self.node, *nodes):
            self.executor.add_node(node)
        self.states, self.commands, self.diagnostics = [], [], []
        self.state_publisher = self.node.create_publisher(JointState, 'joint_states', SAMPLE_QOS)
        self.command_publisher = self.node.create_publisher(JointState, 'effort_command', SAMPLE_QOS)
        self.reference_publisher = self.node.create_publisher(JointTrajectory, 'reference', REFERENCE_QOS)
        self.node.create_subscription(JointState, 'joint_states', self.states.append, SAMPLE_QOS)
        self.node.create_subscription(JointState, 'effort_command', self.commands.append, SAMPLE_QOS)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, DIAGNOSTICS_QOS)

    def spin_until(self, condition, timeout=10.0):
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, 'condition not met in time'
            self.executor.spin_once(timeout_sec=0.02)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def controller(ros_context):
    node = ControllerNode('computed_torque', context=ros_context,
                          parameter_overrides=overrides({'kp': [225.0] * 3, 'kv': [30.0] * 3,
                                                         'delay': 0}))
    probe = Probe(ros_context, node)
    plan = plan_episode(EpisodeSpec(controller='computed_torque', kp=(1, 1, 1), kv=(1, 1, 1)))
    probe.reference_publisher.publish(reference_msg(JOINTS, plan.times, plan.q_ref, plan.v_ref, plan.a_ref,
                                                    plan.nominal))
    probe.spin_until(lambda: node.reference is not None)
    yield node, probe, plan
    probe.close()
    node.destroy_node()


def good_state(plan, n, names=JOINTS):
    q, v = plan.q_ref[n] + 0.01, plan.v_ref[n] - 0.02
    order = [JOINTS.index(name) for name in names]
    return joint_state_msg(names, n * 0.01, q[order], v[order])


def expected_command(plan, n, kp=225.0):
    law = ComputedTorqueLaw(chain_from_model(Arm.from_urdf().model), [kp] * 3, [30.0] * 3)
    q, v = plan.q_ref[n] + 0.01, plan.v_ref[n] - 0.02
    return law.torque(Measurement(q, v, plan.q_ref[n], plan.v_ref[n]),
                      ReferencePoint(plan.q_ref[n], plan.v_ref[n], plan.a_ref[n]))


def bad_states(plan):
    nan = good_state(plan, 1)
    nan.position[1] = float('nan')
    short = good_state(plan, 1)
    short.velocity = short.velocity[:2]
    unknown = good_state(plan, 1)
    unknown.name = ['joint1', 'joint2', 'wrist']
    duplicate = good_state(plan, 1)
    duplicate.name = ['joint1', 'joint1', 'joint3']
    off_sample = good_state(plan, 1)
    off_sample.header.stamp.nanosec += 3_000_000
    return [nan, short, unknown, duplicate, off_sample]


def test_controller_sends_nothing_for_bad_states_and_recovers(controller):
    node, probe, plan = controller
    probe.state_publisher.publish(good_state(plan, 0))
    probe.spin_until(lambda: len(probe.commands) == 1)
    for message in bad_states(plan):
        probe.state_publisher.publish(message)
    probe.state_publisher.publish(good_state(plan, 1, names=['joint3', 'joint1', 'joint2']))
    probe.spin_until(lambda: len(probe.commands) == 2)
    second = probe.commands[1]
    assert second.header.stamp.sec == 0 and second.header.stamp.nanosec == 10_000_000
    np.testing.assert_allclose(second.effort, expected_command(plan, 1), rtol=1e-12)
    probe.state_publisher.publish(good_state(plan, 1))  # sample 1 again: from the past now
    probe.state_publisher.publish(good_state(plan, 2))
    probe.spin_until(lambda: len(probe.commands) == 3)
    assert probe.commands[2].header.stamp.nanosec == 20_000_000
    assert node.refused_messages == len(bad_states(plan)) + 1


def test_a_state_from_the_far_future_is_refused_and_the_next_real_one_commanded(controller, capfd):
    node, probe, plan = controller
    probe.state_publisher.publish(good_state(plan, 0))
    probe.spin_until(lambda: len(probe.commands) == 1)
    far = good_state(plan, 1)
    far.header.stamp.sec, far.header.stamp.nanosec = FAR_FUTURE, 0
    probe.state_publisher.publish(far)
    probe.spin_until(lambda: node.refused_messages == 1)
    assert node.last_sample == 0
    assert ('refused a state for sample 214748364700: more than max_sample_gap = 100 samples after the '
            'expected sample 1') in capfd.readouterr().err
    probe.state_publisher.publish(good_state(plan, 1))
    probe.spin_until(lambda: len(probe.commands) == 2)
    assert probe.commands[1].header.stamp.sec == 0 and probe.commands[1].header.stamp.nanosec == 10_000_000
    np.testing.assert_allclose(probe.commands[1].effort, expected_command(plan, 1), rtol=1e-12)
    # Refused beyond max_sample_gap past the expected sample: with 5, after sample 1 the bound is 2 + 5 = 7.
    assert node.set_parameters([Parameter('max_sample_gap', value=5)])[0].successful
    assert not node.set_parameters([Parameter('max_sample_gap', value=0)])[0].successful
    probe.state_publisher.publish(good_state(plan, 8))
    probe.spin_until(lambda: node.refused_messages == 2)
    probe.state_publisher.publish(good_state(plan, 7))
    probe.spin_until(lambda: len(probe.commands) == 3)
    assert probe.commands[2].header.stamp.nanosec == 70_000_000 and node.last_sample == 7
    probe.state_publisher.publish(good_state(plan, 13))
    probe.spin_until(lambda: len(probe.commands) == 4)
    assert node.refused_messages == 2


def test_a_reference_for_another_robot_is_refused(controller):
    node, probe, plan = controller
    before = node.reference
    wrong = reference_msg(['joint1', 'joint2'], plan.times, plan.q_ref[:, :2], plan.v_ref[:, :2],
                          plan.a_ref[:, :2], plan.nominal[:, :2])
    probe.reference_publisher.publish(wrong)
    probe.spin_until(lambda: node.refused_messages == 1)
    assert node.reference is before


def test_gains_are_validated_and_a_changed_gain_changes_the_next_command(controller):
    node, probe, plan = controller
    for kp, problem in (([1.0, 2.0], 'kp needs 3'), ([1.0, -2.0, 3.0], 'positive'),
                        ([1.0, float('nan'), 3.0], 'finite')):
        result = node.set_parameters([Parameter('kp', value=kp)])[0]
        assert not result.successful and problem in result.reason
    result = node.set_parameters([Parameter('delay', value=500)])[0]
    assert not result.successful
    np.testing.assert_array_equal(node.controller.law.kp, [225.0] * 3)
    probe.state_publisher.publish(good_state(plan, 0))
    probe.spin_until(lambda: len(probe.commands) == 1)
    assert node.set_parameters([Parameter('kp', value=[400.0] * 3)])[0].successful
    probe.state_publisher.publish(good_state(plan, 1))
    probe.spin_until(lambda: len(probe.commands) == 2)
    np.testing.assert_allclose(probe.commands[1].effort, expected_command(plan, 1, kp=400.0), rtol=1e-12)


@pytest.fixture
def plant(ros_context):
    node = PlantNode(context=ros_context, parameter_overrides=overrides(
        {'command_timeout': 2.0, 'torque_limit': [300.0, 300.0, 100.0]}))
    probe = Probe(ros_context, node)
    probe.spin_until(lambda: len(probe.states) == 1)
    yield node, probe
    probe.close()
    node.destroy_node()


def command(n, effort, names=JOINTS):
    return joint_state_msg(names, n * 0.01, effort=np.array(effort, dtype=float))


def test_plant_refuses_bad_commands_and_never_integrates_them(plant):
    node, probe = plant
    q0 = node.plant.q.copy()
    bad = [command(0, [np.nan, 0, 0]), command(0, [0, np.inf, 0]), command(0, [1.0, 2.0]),
           command(0, [1, 2, 3], names=['joint1', 'joint2', 'wrist']), command(5, [1, 2, 3])]
    for message in bad:
        probe.command_publisher.publish(message)
    probe.spin_until(lambda: node.counters['refused_commands'] == len(bad))
    assert node.plant.sample == 0 and len(probe.states) == 1
    np.testing.assert_array_equal(node.plant.q, q0)
    probe.command_publisher.publish(command(0, [900.0, -50.0, 20.0], names=['joint3', 'joint1', 'joint2']))
    probe.spin_until(lambda: len(probe.states) == 2)
    # Mapped by name (joint1 = -50, joint2 = 20, joint3 = 900), then clamped to the limit with its sign.
    np.testing.assert_array_equal(probe.states[1].effort, [-50.0, 20.0, 100.0])
    probe.command_publisher.publish(command(0, [1.0, 1.0, 1.0]))  # sample 0 again: stale
    probe.spin_until(lambda: node.counters['stale_commands'] == 1)
    assert node.plant.sample == 1 and node.counters['duplicate_commands'] == 0


def test_plant_refuses_a_command_from_the_far_future_and_applies_the_next_real_one(plant, capfd):
    node, probe = plant
    far = command(0, [9.0, 9.0, 9.0])
    far.header.stamp.sec = FAR_FUTURE
    probe.command_publisher.publish(far)
    probe.spin_until(lambda: node.counters['refused_commands'] == 1)
    assert node.phase == RUNNING and node.plant.sample == 0 and len(probe.states) == 1
    assert 'refused a command for sample 214748364700 from the future (expected sample 0)' in capfd.readouterr().err
    probe.command_publisher.publish(command(0, [1.0, 2.0, 3.0]))
    probe.spin_until(lambda: len(probe.states) == 2)
    np.testing.assert_array_equal(probe.states[1].effort, [1.0, 2.0, 3.0])
    assert node.plant.sample == 1


def test_a_missing_command_ends_the_lockstep_episode_naming_the_sample(ros_context):
    node = PlantNode(context=ros_context, parameter_overrides=overrides({'command_timeout': 0.2,
                                                                        'autostart': False}))
    probe = Probe(ros_context, node)
    try:
        probe.spin_until(lambda: node.diagnostics_publisher.get_subscription_count() > 0)
        node.start_episode()
        probe.spin_until(lambda: node.phase == ENDED)
        probe.spin_until(lambda: any('no command for sample 0' in status.message
                                     for array in probe.diagnostics for status in array.status))
    finally:
        probe.close()
        node.destroy_node()


def test_plant_parameters_are_validated_on_set(plant):
    node, _ = plant
    for name, value, problem in (('torque_limit', [1.0, 2.0], 'torque_limit needs 3'),
                                 ('torque_limit', [1.0, -2.0, 3.0], 'positive'),
                                 ('external_torque', [0.0, float('nan'), 0.0], 'finite'),
                                 ('mode', 'turbo', 'mode must be one of'),
                                 ('tau', 5.0, 'tau must be within')):
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and problem in result.reason
    for name, value in (('period', 0.0), ('period', -0.01), ('period', 5.0), ('substeps', 0)):
        assert not node.set_parameters([Parameter(name, value=value)])[0].successful
    assert node.get_parameter('period').value == 0.01


def test_an_incompatible_qos_peer_is_detected(plant):
    node, probe = plant
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    probe.node.create_publisher(JointState, 'effort_command', best_effort)
    probe.spin_until(lambda: node.incompatible_qos_events > 0)


@pytest.mark.parametrize('module, law, yaml_text, problem', [
    ('ddarm_control.node', 'computed_torque', 'computed_torque:\n  ros__parameters:\n    kpp: [1.0, 1.0, 1.0]\n'
     '    kp: [1.0, 1.0, 1.0]\n    kv: [1.0, 1.0, 1.0]\n', "unknown parameters ['kpp']"),
    ('ddarm_control.node', 'pd_gravity', 'pd_gravity:\n  ros__parameters:\n    delay: 500\n'
     '    kp: [1.0, 1.0, 1.0]\n    kv: [1.0, 1.0, 1.0]\n', 'delay'),
    ('ddarm_control.node', 'pd_gravity', 'pd_gravity:\n  ros__parameters:\n    kp: [1.0, 1.0]\n'
     '    kv: [1.0, 1.0, 1.0]\n', 'kp needs 3'),
    ('ddarm_sim.node', None, 'plant:\n  ros__parameters:\n    perod: 0.01\n', "unknown parameters ['perod']"),
    ('ddarm_sim.node', None, 'plant:\n  ros__parameters:\n    substeps: 0\n', 'substeps'),
    ('ddarm_sim.node', None, 'plant:\n  ros__parameters:\n    urdf: /\n', 'URDF / is a directory, not a URDF file'),
])
def test_bad_parameter_files_are_refused_at_start(tmp_path, module, law, yaml_text, problem):
    parameters = tmp_path / 'parameters.yaml'
    parameters.write_text(yaml_text)
    done = subprocess.run([sys.executable, '-m', module, *([law] if law else []), '--ros-args', '--params-file',
                           str(parameters)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert problem in done.stdout + done.stderr


@pytest.mark.parametrize('module, law, arguments, key, node', [
    ('ddarm_sim.node', None, [], 'plnat', '/plant'),
    ('ddarm_control.node', 'computed_torque', [], 'computed_torqe', '/computed_torque'),
    # rcl reads a key without a leading slash as absolute: `plant` is not /arm/plant.
    ('ddarm_sim.node', None, ['-r', '__ns:=/arm'], 'plant', '/arm/plant'),
])
def test_a_parameter_file_for_no_such_node_is_refused_at_start(tmp_path, module, law, arguments, key, node):
    parameters = tmp_path / 'misspelled.yaml'
    parameters.write_text(f'{key}:\n  ros__parameters:\n    period: 0.01\n')
    done = subprocess.run([sys.executable, '-m', module, *([law] if law else []), '--ros-args', *arguments,
                           '--params-file', str(parameters)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert f'refused to start: {parameters} configures no node named {node} (its node keys: {key})' in done.stdout


@pytest.mark.parametrize('yaml_text', [None, '/**:\n  ros__parameters:\n    autostart: false\n'])
def test_a_parameter_file_that_configures_the_plant_starts_it(ros_context, tmp_path, yaml_text):
    parameters = ROOT / 'config' / 'plant.yaml'
    if yaml_text is not None:
        parameters = tmp_path / 'every_node.yaml'
        parameters.write_text(yaml_text)
    process = subprocess.Popen([sys.executable, '-m', 'ddarm_sim.node', '--ros-args', '--params-file',
                                str(parameters)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    node = rclpy.create_node('start_probe', context=ros_context)
    try:
        assert node.create_client(Trigger, '/plant/reset').wait_for_service(timeout_sec=30)
        assert process.poll() is None
    finally:
        node.destroy_node()
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=20)
    assert process.returncode == 0, output


@pytest.mark.parametrize('law', ['pd_gravity', 'computed_torque'])
def test_the_config_files_load(law):
    context = rclpy.Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(ROOT / 'config' / f'{law}.yaml'),
                                      '--params-file', str(ROOT / 'config' / 'plant.yaml')])
    try:
        controller = ControllerNode(law, context=context)
        plant = PlantNode(context=context, parameter_overrides=overrides({'autostart': False}))
        assert controller.controller.law.kp.tolist() == (
            [225.0] * 3 if law == 'computed_torque' else [2800.0, 2700.0, 350.0])
        assert controller.controller.delay == 1
        assert plant.settings.period == 0.01 and plant.settings.mode == 'lockstep'
        controller.destroy_node()
        plant.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)



def test_a_graph_on_another_domain_is_never_heard(ros_context, tmp_path):
    """docs/faults.md 14: with localhost discovery, distinct domain IDs do not cross."""
    parameters = tmp_path / 'plant.yaml'
    parameters.write_text('plant:\n  ros__parameters:\n    command_timeout: 2.0\n')
    environment = {**os.environ, 'ROS_DOMAIN_ID': str(claim_domain_id())}
    process = subprocess.Popen([sys.executable, '-m', 'ddarm_sim.node', '--ros-args', '--params-file',
                                str(parameters)], env=environment, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(process.stdout), daemon=True)
    reader.start()
    probe = Probe(ros_context)  # subscribes to joint_states on this process's domain
    try:
        probe.spin_until(lambda: any('no start: 0 of 1' in line for line in lines), timeout=30)
    finally:
        process.send_signal(signal.SIGINT)
        process.wait(timeout=20)
        probe.close()
    assert probe.states == []
