"""Graphs on one domain (FAULTS.md 21): the graphs ddarm starts never hear each other or a user's graph,
and a foreign node on a hand-started graph fails the episode, naming it."""

import json

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from ddarm_sim.ros_interface import SAMPLE_QOS, joint_state_msg
from ddarm_tuner.bags import score_bag
from ddarm_tuner.episodes import EpisodeSpec, run_episode
from ddarm_tuner.node import TunerNode
from ddarm_tuner.ros_episode import GraphEpisodeError
from process_helpers import ddarm, finished_json, start_node, stop

KP, KV = [900.0] * 3, [60.0] * 3


def assert_in_process_numbers(summary: dict) -> None:
    expected = run_episode(EpisodeSpec(**summary['spec'])).indices
    for key in ('I1', 'I2', 'I'):
        assert summary[key] == pytest.approx(expected[key], rel=1e-9), key


def test_two_lockstep_episodes_at_once_each_give_their_own_numbers(tmp_path):
    runs = {omega: ddarm('episode', '--controller', 'computed_torque', '--omega', str(omega), '--ros', '--json',
                         '--bag', str(tmp_path / f'omega{omega}'))
            for omega in (10, 25)}
    for omega, process in runs.items():
        summary = finished_json(process)
        assert summary['spec']['kp'] == [omega ** 2] * 3
        assert_in_process_numbers(summary)
        scored = score_bag(tmp_path / f'omega{omega}')
        assert all(scored[key] == summary[key] for key in ('I1', 'I2', 'I'))


def test_two_realtime_episodes_at_once_hear_only_their_own_commands():
    runs = [ddarm('episode', '--controller', 'computed_torque', '--omega', str(omega), '--realtime', '--json')
            for omega in (10, 25)]
    for process in runs:
        report = finished_json(process)['plant_report']
        assert report['event'] == 'complete'
        assert int(report['refused_commands']) == 0 and int(report['duplicate_commands']) == 0


def test_a_tuner_sweep_beside_an_episode_gives_only_correct_numbers(tmp_path):
    nodes = [start_node(['ddarm_sim.node', '--ros-args', '-p', 'autostart:=false'], tmp_path / 'plant.log'),
             start_node(['ddarm_control.node', 'computed_torque', '--ros-args', '-p', f'kp:={KP}',
                         '-p', f'kv:={KV}'], tmp_path / 'controller.log')]
    try:
        tuner = ddarm('tuner', '--ros-args', '-p', f'kp:={KP}', '-p', f'kv:={KV}',
                      '-p', 'taus:=[0.0,0.02,0.04,0.06,0.08,0.1]', '-p', "torque_limits:=['none','paper']",
                      '-p', f'output_root:={tmp_path / "runs"}', '-p', 'run_name:=sweep')
        episodes = [ddarm('episode', '--controller', 'computed_torque', '--omega', str(omega), '--ros', '--json')
                    for omega in (10, 25)]
        for process in episodes:
            assert_in_process_numbers(finished_json(process))
        _, err = tuner.communicate(timeout=300)
        assert tuner.returncode == 0, err
    finally:
        stop(nodes)
    summary = json.loads((tmp_path / 'runs' / 'sweep' / 'summary.json').read_text())
    assert summary['status'] == 'complete' and len(summary['episodes']) == 12
    for episode in summary['episodes']:
        assert_in_process_numbers(episode)


@pytest.fixture
def hand_started(tmp_path):
    """A plant and a computed-torque controller started by hand, in the root namespace."""
    processes = [start_node(['ddarm_sim.node', '--ros-args', '-p', 'autostart:=false'], tmp_path / 'plant.log'),
                 start_node(['ddarm_control.node', 'computed_torque', '--ros-args', '-p', f'kp:={KP}',
                             '-p', f'kv:={KV}'], tmp_path / 'controller.log')]
    yield processes
    stop(processes)


def tuner_node(context):
    node = TunerNode(context=context, parameter_overrides=[
        Parameter('kp', value=KP), Parameter('kv', value=KV), Parameter('peer_timeout', value=5.0)])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return node, executor


@pytest.mark.parametrize('law, problem', [
    ('computed_torque', '2 nodes are named /computed_torque: a second controller'),
    ('pd_gravity', '/pd_gravity is running too: two laws would answer the same states'),
])
def test_a_second_controller_fails_the_episode_naming_it(ros_context, hand_started, tmp_path, law, problem):
    hand_started.append(start_node(['ddarm_control.node', law, '--ros-args', '-p', f'kp:={KP}', '-p', f'kv:={KV}'],
                                   tmp_path / 'second.log'))
    node, executor = tuner_node(ros_context)
    try:
        with pytest.raises(GraphEpisodeError, match=problem):
            node.run_episode(executor, node.specs[0][1], node.specs[0][2], peer_timeout=5.0)
    finally:
        executor.shutdown()
        node.destroy_node()


def test_a_foreign_command_publisher_fails_the_episode_naming_it(ros_context, hand_started):
    node, executor = tuner_node(ros_context)
    intruder = rclpy.create_node('intruder', context=ros_context)
    intruder.create_publisher(JointState, 'effort_command', SAMPLE_QOS)
    executor.add_node(intruder)
    try:
        with pytest.raises(GraphEpisodeError, match=r"only /computed_torque may publish it \(foreign: \['/intruder'\]"):
            node.run_episode(executor, node.specs[0][1], node.specs[0][2], peer_timeout=5.0)
    finally:
        executor.shutdown()
        intruder.destroy_node()
        node.destroy_node()


def test_a_publisher_that_joins_during_the_episode_fails_it(ros_context, hand_started):
    """It slips past the check before the episode; its commands, or the graph check during it, give it away."""
    node, executor = tuner_node(ros_context)
    intruder = rclpy.create_node('late_intruder', context=ros_context)
    publisher = []

    def on_state(msg):
        if not publisher:
            publisher.append(intruder.create_publisher(JointState, 'effort_command', SAMPLE_QOS))
        if msg.position:  # answer every state with a command of its own, as a second controller would
            publisher[0].publish(joint_state_msg(msg.name, msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                                                 effort=[0.0] * len(msg.name)))

    intruder.create_subscription(JointState, 'joint_states', on_state, SAMPLE_QOS)
    executor.add_node(intruder)
    try:
        with pytest.raises(GraphEpisodeError):
            node.run_episode(executor, node.specs[0][1], node.specs[0][2], peer_timeout=5.0)
    finally:
        executor.shutdown()
        intruder.destroy_node()
        node.destroy_node()


def test_a_missing_peer_is_named_before_any_episode(ros_context):
    node, executor = tuner_node(ros_context)
    try:
        with pytest.raises(GraphEpisodeError, match='no plant node /plant on the graph.*no controller node '
                                                    '/computed_torque'):
            node.run_episode(executor, node.specs[0][1], node.specs[0][2], peer_timeout=1.0)
    finally:
        executor.shutdown()
        node.destroy_node()
