"""The plant and controller nodes under faults of their own making or of a peer's: they keep answering, and say what."""

import json
import re
import signal
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from ddarm_control.node import ControllerNode
from ddarm.physics.arm import Arm, ModelError
from ddarm_sim.node import RUNNING, PlantNode
from ddarm.ros.interface import DIAGNOSTICS_QOS, SAMPLE_QOS, joint_state_msg, sample_index
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from graph_helpers import InProcessGraph, overrides
from process_helpers import start_node, wait_for
from test_graph_equivalence import assert_same_episode

JOINTS = ['joint1', 'joint2', 'joint3']
SPEC = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3)
FAR_FUTURE = 2**31 - 1  # s: the largest stamp a builtin_interfaces/Time holds
UR5 = Path(__file__).resolve().parent.parent / 'config' / 'arms' / 'ur5'


def spin_until(executor, condition, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, 'condition not met in time'
        executor.spin_once(timeout_sec=0.02)


class Listener:
    """A node that hears the plant's diagnostics (and counts as a joint_states subscriber); without a controller
    it can stand in for one's command publisher: the plant starts once one matches."""

    def __init__(self, context, executor, namespace='', command_publisher=False):
        self.node = rclpy.create_node('listener', namespace=namespace, context=context)
        self.statuses = []
        self.node.create_subscription(DiagnosticArray, '/diagnostics', lambda msg: self.statuses.extend(msg.status),
                                      DIAGNOSTICS_QOS)
        self.node.create_subscription(JointState, 'joint_states', lambda msg: None, SAMPLE_QOS)
        if command_publisher:
            self.node.create_publisher(JointState, 'effort_command', SAMPLE_QOS)
        executor.add_node(self.node)

    def values(self):
        return [{pair.key: pair.value for pair in status.values} for status in self.statuses]

    def ends(self):
        return [values['event'] for values in self.values() if values['event'] != 'started']


def test_one_plant_node_ends_episodes_every_way_and_the_last_is_still_exact(ros_context):
    graph = InProcessGraph(ros_context, SPEC)
    listener = Listener(ros_context, graph.executor)
    reset = listener.node.create_client(Trigger, '/plant/reset')
    try:
        spin_until(graph.executor, lambda: graph.plant.diagnostics_publisher.get_subscription_count() >= 2)
        graph.run()
        spin_until(graph.executor, lambda: listener.ends() == ['complete'])

        diverging = EpisodeSpec(controller='computed_torque', kp=(1e6,) * 3, kv=(3e3,) * 3)
        assert graph.driver.run_episode(graph.executor, diverging).summary()['diverged_at'] is not None
        spin_until(graph.executor, lambda: listener.ends()[-1:] == ['diverged'])

        # With the controller no longer spun, sample 0 goes unanswered.
        graph.executor.remove_node(graph.controller)
        assert all(result.successful for result in graph.plant.set_parameters(
            [Parameter('command_timeout', value=0.2)]))
        spin_until(graph.executor, lambda: reset.service_is_ready())
        future = reset.call_async(Trigger.Request())
        spin_until(graph.executor, lambda: future.done() and listener.ends()[-1:] == ['timeout'])

        assert graph.plant.set_parameters([Parameter('required_subscribers', value=100)])[0].successful
        future = reset.call_async(Trigger.Request())
        spin_until(graph.executor, lambda: future.done() and listener.ends()[-1:] == ['no_start'])

        # The controller answers the unanswered sample 0 first: the plant, its episode over, ignores it.
        graph.executor.add_node(graph.controller)
        spin_until(graph.executor, lambda: graph.controller.last_sample == 0)
        assert_same_episode(graph.run(), run_episode(SPEC))
        spin_until(graph.executor, lambda: len(listener.ends()) == 5)
        assert listener.ends() == ['complete', 'diverged', 'timeout', 'no_start', 'complete']
    finally:
        listener.node.destroy_node()
        graph.close()


class Injector:
    """Follows the plant's state of one sample with a copy stamped in the far future, on the plant's own publisher.

    The driver fails an episode that a foreign publisher of joint_states joins: a stray message from the
    plant's publisher is one the graph checks let through.
    """

    def __init__(self, context, executor, plant, at_sample):
        self.node = rclpy.create_node('injector', context=context)
        self.node.create_subscription(JointState, 'joint_states', self._on_state, SAMPLE_QOS)
        self.plant, self.at_sample, self.sent = plant, at_sample, 0
        executor.add_node(self.node)

    def _on_state(self, msg):
        if sample_index(msg.header.stamp, SPEC.period) != self.at_sample:
            return
        msg.header.stamp.sec, msg.header.stamp.nanosec = FAR_FUTURE, 0
        self.plant.state_publisher.publish(msg)
        self.sent += 1


def test_one_stray_far_future_state_does_not_end_the_episode(ros_context):
    graph = InProcessGraph(ros_context, SPEC)
    injector = Injector(ros_context, graph.executor, graph.plant, at_sample=50)
    try:
        spin_until(graph.executor, lambda: graph.plant.state_publisher.get_subscription_count() >= 3)
        result = graph.run()
        assert injector.sent == 1 and graph.controller.refused_messages == 1
        assert_same_episode(result, run_episode(SPEC))
    finally:
        injector.node.destroy_node()
        graph.close()


def command(n, effort, period):
    return joint_state_msg(JOINTS, n * period, effort=np.array(effort, dtype=float))


def test_a_second_command_for_a_sample_is_counted_and_diagnostics_name_the_plant(ros_context):
    period = 0.05
    plant = PlantNode(context=ros_context, namespace='/arm', parameter_overrides=overrides(
        {'mode': 'realtime', 'period': period, 'max_samples': 3}))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(plant)
    listener = Listener(ros_context, executor, namespace='/arm', command_publisher=True)
    try:
        spin_until(executor, lambda: plant.phase == RUNNING)
        # Called directly, under the plant's lock: no real-time tick (a thread of its own) can fall between the two.
        with plant.lock:
            n = plant.plant.sample
            plant._on_command(serialize_message(command(n, [1.0, 2.0, 3.0], period)))
            plant._on_command(serialize_message(command(n, [4.0, 5.0, 6.0], period)))
        assert plant.counters['duplicate_commands'] == 1
        np.testing.assert_array_equal(plant.latest_command, [1.0, 2.0, 3.0])
        spin_until(executor, lambda: listener.ends() == ['complete'])
        report = listener.values()[-1]
        assert report['node'] == '/arm/plant' and report['duplicate_commands'] == '1'
        assert {'event', 'sample', 'mode', 'wall_time_s', 'refused_commands', 'stale_commands', 'deadline_misses',
                'period_jitter_p50_ms', 'period_jitter_p99_ms', 'period_jitter_max_ms'} <= set(report)
        assert all(values['node'] == '/arm/plant' for values in listener.values())
    finally:
        executor.shutdown()
        listener.node.destroy_node()
        plant.destroy_node()


def test_the_controller_status_counts_its_own_matched_side_of_the_state_and_command_topics(ros_context):
    # The driver starts sample 0 only once these hold: a command sent before its writer matched the plant's reader
    # is lost, and a lockstep plant then waits for it until its timeout.
    controller = ControllerNode('computed_torque', context=ros_context, namespace='/arm', parameter_overrides=overrides(
        {'kp': [225.0] * 3, 'kv': [30.0] * 3}))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(controller)
    peer = rclpy.create_node('peer', namespace='/arm', context=ros_context)
    executor.add_node(peer)
    client = peer.create_client(Trigger, '/arm/computed_torque/status')

    def status():
        future = client.call_async(Trigger.Request())
        spin_until(executor, future.done)
        return json.loads(future.result().message)
    try:
        spin_until(executor, client.service_is_ready)
        assert (status()['state_publishers'], status()['command_subscribers']) == (0, 0)
        peer.create_publisher(JointState, 'joint_states', SAMPLE_QOS)
        peer.create_subscription(JointState, 'effort_command', lambda msg: None, SAMPLE_QOS)
        peer.create_subscription(JointState, 'effort_command', lambda msg: None, SAMPLE_QOS)
        spin_until(executor, lambda: (status()['state_publishers'], status()['command_subscribers']) == (1, 2))
    finally:
        executor.shutdown()
        peer.destroy_node()
        controller.destroy_node()


@pytest.mark.parametrize('node_name, make, kind', [
    ('plant', lambda context: PlantNode(context=context, parameter_overrides=overrides({'autostart': False})),
     'plant'),
    ('computed_torque', lambda context: ControllerNode(
        'computed_torque', context=context, parameter_overrides=overrides({'kp': [225.0] * 3, 'kv': [30.0] * 3})),
     'computed_torque'),
])
def test_setting_an_undeclared_parameter_is_refused_by_name(ros_context, node_name, make, kind):
    node = make(ros_context)
    client_node = rclpy.create_node('parameter_client', context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for each in (node, client_node):
        executor.add_node(each)
    client = AsyncParameterClient(client_node, node_name)
    try:
        spin_until(executor, client.services_are_ready)
        future = client.set_parameters([Parameter('perod', value=0.02)])
        spin_until(executor, future.done)
        result = future.result().results[0]
        assert not result.successful
        assert f"['perod'] (not a {kind} parameter: a typo?)" in result.reason
        future = client.set_parameters_atomically([Parameter('period', value=0.02), Parameter('perod', value=0.02),
                                                   Parameter('kpp', value=1.0)])
        spin_until(executor, future.done)
        result = future.result().result
        assert not result.successful and f"['kpp', 'perod'] (not {kind} parameters" in result.reason
        assert node.get_parameter('period').value == 0.01
        with pytest.raises(ParameterNotDeclaredException, match=r"\['perod'\]"):
            node.set_parameters([Parameter('perod', value=0.02)])
    finally:
        executor.shutdown()
        client_node.destroy_node()
        node.destroy_node()


def test_a_directory_given_as_urdf_is_named_a_directory(ros_context, tmp_path):
    for make in (lambda: PlantNode(context=ros_context, parameter_overrides=overrides({'urdf': str(tmp_path)})),
                 lambda: ControllerNode('pd_gravity', context=ros_context,
                                        parameter_overrides=overrides({'urdf': str(tmp_path)}))):
        with pytest.raises(ModelError, match=re.escape(f'URDF {tmp_path} is a directory, not a URDF file')):
            make()


def test_a_file_that_is_no_urdf_or_cannot_be_read_is_refused_naming_it(tmp_path):
    text = tmp_path / 'notes.urdf'
    text.write_text('not a robot\n')
    with pytest.raises(ModelError, match=re.escape(f'URDF {text} is not readable XML')):
        Arm.from_urdf(text)
    # Even root cannot open a socket as a file.
    unopenable = tmp_path / 'arm.urdf'
    with socket.socket(socket.AF_UNIX) as listening:
        listening.bind(str(unopenable))
        with pytest.raises(ModelError, match=re.escape(f'URDF {unopenable} cannot be read: ')):
            Arm.from_urdf(unopenable)
    with pytest.raises(ModelError, match=re.escape(f'URDF {tmp_path / "nothing.urdf"} does not exist')):
        Arm.from_urdf(tmp_path / 'nothing.urdf')


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_timer_mode_controller_ends_without_a_fatal_log(tmp_path, signum):
    """The stop lands in a callback (the 100 Hz tick, the watchdog) more often than not; the executor must not
    see it there: rclpy's EventsExecutor logs any exception out of a callback as FATAL with a stack."""
    log = tmp_path / 'controller.log'
    process = start_node(['ddarm_control.node', 'computed_torque', '--ros-args', '-p', 'sampling:=timer',
                          '-p', 'command_type:=float64_multi_array', '-p', f'motion:={UR5 / "ur5-motion.yaml"}',
                          '-p', f'urdf:={UR5 / "ur5.urdf"}', '-p', 'omega:=10.0'], log)
    try:
        # The watchdog's line comes from a timer callback: the node spins, its tick firing at 100 Hz.
        wait_for(lambda: 'waiting for a state' in log.read_text() or process.poll() is not None, 120,
                 'the controller spinning')
        process.send_signal(signum)
        assert process.wait(timeout=30) == 0, log.read_text()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    text = log.read_text()
    assert 'FATAL' not in text and 'Traceback' not in text and 'Error occurred at' not in text, text
