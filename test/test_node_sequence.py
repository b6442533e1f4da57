"""Nodes that survive any sequence of episodes (docs/faults.md 22): complete, diverged, timeout, no start and
refused input, in any order, on the same plant and controller processes; the next good episode is exact."""

import dataclasses
import math
import signal
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from ddarm.ros.interface import SAMPLE_QOS, joint_state_msg
from ddarm.ros import driver as ros_episode
from ddarm.ros import node_parameters
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec, check_episode
from ddarm.ros.driver import GraphDriver, GraphEpisodeError
from process_helpers import start_node, stop, wait_for

GOOD = EpisodeSpec(controller='computed_torque', kp=(900.0,) * 3, kv=(60.0,) * 3)
DIVERGING = dataclasses.replace(GOOD, kp=(1e6,) * 3, kv=(3e3,) * 3)
JOINTS = ['joint1', 'joint2', 'joint3']


class Sequence:
    """A driver of this test process on hand-started plant and controller processes."""

    def __init__(self, context, folder):
        self.processes = {
            'plant': start_node(['ddarm_sim.node', '--ros-args', '-p', 'autostart:=false'], folder / 'plant.log'),
            'controller': start_node(['ddarm_control.node', 'computed_torque', '--ros-args',
                                      '-p', 'kp:=[1.0,1.0,1.0]', '-p', 'kv:=[1.0,1.0,1.0]'],
                                     folder / 'controller.log')}
        self.folder = folder
        self.context = context
        self.driver = GraphDriver(context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.driver)

    def alive(self):
        for name, process in self.processes.items():
            assert process.poll() is None, (self.folder / f'{name}.log').read_text()

    def episode(self, spec, alive=None):
        return self.driver.run_episode(self.executor, spec, check_episode(spec), timeout=60.0,
                                       alive=alive or self.alive)

    def close(self):
        self.executor.shutdown()
        self.driver.destroy_node()
        stop(self.processes.values())


@pytest.fixture
def sequence(ros_context, tmp_path, monkeypatch):
    monkeypatch.setattr(node_parameters, 'COMMAND_TIMEOUT', 3.0)  # the plant gives up on a command after 3 s
    graph = Sequence(ros_context, tmp_path)
    yield graph
    graph.close()


def complete(sequence):
    result = sequence.episode(GOOD)
    expected = run_episode(GOOD)
    assert not result.diverged[0]
    for key in ('I1', 'I2', 'I'):
        assert result.indices()[key] == pytest.approx(expected.indices()[key], rel=1e-9)


def diverged(sequence):
    result = sequence.episode(DIVERGING)
    assert result.diverged[0] and result.diverged_at[0] == run_episode(DIVERGING).diverged_at[0]


def timeout(sequence):
    """The controller stops answering part way (SIGSTOP): the plant ends the episode, naming the sample."""
    controller = sequence.processes['controller']
    stopped = []

    def stop_the_controller_at_sample_5():
        sequence.alive()
        recording = sequence.driver.recording
        if recording is not None and recording.states:
            last_state.append(max(recording.states))
        if not stopped and recording is not None and len(recording.states) > 5:
            controller.send_signal(signal.SIGSTOP)
            stopped.append(True)

    last_state = []
    answers = []
    listener = rclpy.create_node('answers', context=sequence.context)
    listener.create_subscription(JointState, 'effort_command', lambda msg: answers.append(msg.header.stamp), SAMPLE_QOS)
    sequence.executor.add_node(listener)

    try:
        with pytest.raises(GraphEpisodeError, match='no command for sample'):
            sequence.episode(GOOD, alive=stop_the_controller_at_sample_5)
    finally:
        controller.send_signal(signal.SIGCONT)
    # Its late answers to the stopped episode come once it runs again, as late as the plant's next DDS
    # heartbeat re-sends the states it missed (seconds): the next episode starts once the last is answered
    # (one that lands in an episode fails it, as test_isolation shows).
    last = round(last_state[-1] * GOOD.period, 9)
    deadline = time.monotonic() + 30
    try:
        while not any(abs(stamp.sec + stamp.nanosec * 1e-9 - last) < 1e-9 for stamp in answers):
            assert time.monotonic() < deadline, 'the controller never answered the stopped episode'
            sequence.executor.spin_once(timeout_sec=0.05)
    finally:
        sequence.executor.remove_node(listener)
        listener.destroy_node()


def no_start(sequence):
    """More subscribers required than listen: the plant's episode never starts."""
    driver = sequence.driver
    wall = time.monotonic() + 30.0
    driver._configure(sequence.executor, 'plant', [Parameter('required_subscribers', value=50),
                                                  Parameter('command_timeout', value=0.5)], wall, sequence.alive)
    driver.recording = ros_episode.Recording(100, 'computed_torque')
    try:
        assert driver._trigger(sequence.executor, driver.reset_clients['plant'], wall, sequence.alive).success
        driver._spin_until(sequence.executor, lambda: driver.recording.error is not None, wall, 'no start',
                           sequence.alive)
        assert 'no start' in driver.recording.error
    finally:
        driver.recording = None


def refused_input(sequence):
    """A NaN state, a far-future state and a command with the wrong joint count, between episodes.

    The probe that sends them leaves the graph afterwards: while it is there, the driver would
    refuse to start an episode (a foreign publisher).
    """
    probe = rclpy.create_node('probe', context=sequence.context)
    states = probe.create_publisher(JointState, 'joint_states', SAMPLE_QOS)
    commands = probe.create_publisher(JointState, 'effort_command', SAMPLE_QOS)
    try:
        deadline = time.monotonic() + 10
        while states.get_subscription_count() < 2 or commands.get_subscription_count() < 2:
            assert time.monotonic() < deadline, 'the nodes never listened to the probe'
            rclpy.spin_once(probe, timeout_sec=0.02)
        states.publish(joint_state_msg(JOINTS, 0.0, [math.nan] * 3, [0.0] * 3))
        far = joint_state_msg(JOINTS, 0.0, [0.0] * 3, [0.0] * 3)
        far.header.stamp.sec = 2 ** 31 - 1
        states.publish(far)
        commands.publish(joint_state_msg(JOINTS[:2], 0.0, effort=[1.0, 2.0]))
        controller_log, plant_log = sequence.folder / 'controller.log', sequence.folder / 'plant.log'
        wait_for(lambda: controller_log.read_text().count('refused') >= 2 and 'refused' in plant_log.read_text(),
                 10, 'both nodes logged their refusals')
    finally:
        probe.destroy_node()
    sequence.alive()


def test_any_sequence_of_episode_endings_leaves_the_nodes_up_and_exact(sequence):
    for ending in (complete, diverged, complete, timeout, complete, no_start, refused_input, diverged, timeout,
                   no_start, complete):
        ending(sequence)
        sequence.alive()
