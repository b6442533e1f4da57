"""Graphs on one domain (docs/faults.md 21): the graphs ddarm starts never hear each other or a user's graph,
and a foreign node on a hand-started graph fails the episode, naming it."""

import json
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from ddarm.ros.interface import SAMPLE_QOS, joint_state_msg
from ddarm.recording.bags import score_bag
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm_tuner.node import TunerNode
from ddarm.ros.driver import GraphEpisodeError
from process_helpers import ddarm, finished_json, start_node, stop

KP, KV = [900.0] * 3, [60.0] * 3


def assert_in_process_numbers(summary: dict) -> None:
    expected = run_episode(EpisodeSpec(**summary['spec'])).indices()
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
def hand_started(ros_context, tmp_path):
    """A plant and a computed-torque controller started by hand, in the root namespace, on the graph.

    Waited for here: on a loaded machine a node process can take longer to start than an episode's
    peer timeout. A node of the test's context is kept meanwhile: its DDS participant goes with its last
    node, and a new one would have to discover the graph again.
    """
    processes = [start_node(['ddarm_sim.node', '--ros-args', '-p', 'autostart:=false'], tmp_path / 'plant.log'),
                 start_node(['ddarm_control.node', 'computed_torque', '--ros-args', '-p', f'kp:={KP}',
                             '-p', f'kv:={KV}'], tmp_path / 'controller.log')]
    keep = rclpy.create_node('keep_participant', context=ros_context)
    try:
        wait_for_graph(ros_context, lambda node: all(node.count_publishers(topic) >= 1 for topic in
                                                     ('/joint_states', '/clock', '/effort_command')), timeout=60.0)
        yield processes
    finally:
        keep.destroy_node()
        stop(processes)


def wait_for_graph(context, condition, timeout=30.0):
    """Until `condition(node)` holds on the graph, asked through a node of `context`."""
    node = rclpy.create_node('graph_watch', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + timeout
        while not condition(node):
            assert time.monotonic() < deadline, 'the graph never got there'
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()


def assert_episode_fails(context, problem, *others, peer_timeout=5.0):
    """The tuner's first episode, with `others` (intruder nodes) spun beside it, fails matching `problem`."""
    node = TunerNode(context=context, parameter_overrides=[Parameter('kp', value=KP), Parameter('kv', value=KV)])
    executor = SingleThreadedExecutor(context=context)
    for each in (node, *others):
        executor.add_node(each)
    try:
        with pytest.raises(GraphEpisodeError, match=problem):
            node.run_episode(executor, node.specs[0][1], node.specs[0][2], peer_timeout=peer_timeout)
    finally:
        executor.shutdown()
        for each in (node, *others):
            each.destroy_node()


@pytest.mark.parametrize('law, problem', [
    # Whichever comes first: the graph shows the second node or its publisher, or its first command arrives.
    ('computed_torque', '2 nodes are named /computed_torque: a second controller|two commands for sample'
                        '|/effort_command is published by'),
    ('pd_gravity', '/pd_gravity is running too: two laws would answer the same states|two commands for sample'
                   '|/effort_command is published by'),
])
def test_a_second_controller_fails_the_episode_naming_it(ros_context, hand_started, tmp_path, law, problem):
    hand_started.append(start_node(['ddarm_control.node', law, '--ros-args', '-p', f'kp:={KP}', '-p', f'kv:={KV}'],
                                   tmp_path / 'second.log'))
    # Only once it is on the graph, its command publisher discovered too: an episode that ends before the second
    # node joins is a good one, and under load discovery can name a node well before its endpoints match.
    wait_for_graph(ros_context, lambda node: node.get_node_names_and_namespaces().count((law, '/'))
                   == (2 if law == 'computed_torque' else 1) and node.count_publishers('/effort_command') == 2)
    assert_episode_fails(ros_context, problem)


def test_a_foreign_command_publisher_fails_the_episode_naming_it(ros_context, hand_started):
    intruder = rclpy.create_node('intruder', context=ros_context)
    intruder.create_publisher(JointState, 'effort_command', SAMPLE_QOS)
    assert_episode_fails(ros_context, r"only /computed_torque may publish it \(foreign: \['/intruder'\]", intruder)


def test_a_publisher_that_joins_during_the_episode_fails_it(ros_context, hand_started):
    """It slips past the check before the episode; its commands, or the graph check during it, give it away."""
    intruder = rclpy.create_node('late_intruder', context=ros_context)
    publisher = []

    def on_state(msg):
        if not publisher:
            publisher.append(intruder.create_publisher(JointState, 'effort_command', SAMPLE_QOS))
        if msg.position:  # answer every state with a command of its own, as a second controller would
            publisher[0].publish(joint_state_msg(msg.name, msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                                                 effort=[0.0] * len(msg.name)))

    intruder.create_subscription(JointState, 'joint_states', on_state, SAMPLE_QOS)
    assert_episode_fails(ros_context, None, intruder)


def test_a_missing_peer_is_named_before_any_episode(ros_context):
    assert_episode_fails(ros_context, 'no plant node /plant on the graph.*no controller node /computed_torque',
                         peer_timeout=1.0)


def intruder_at_sample(context, sample, act):
    """A node that does `act(node)` once, when it hears the state of `sample`.

    Its service clients are made with it, before the episode: one made in the act would still be discovering
    the controller's services when a fast episode has ended, and its call would come after the episode.
    """
    from rclpy.parameter_client import AsyncParameterClient
    from std_srvs.srv import Trigger

    intruder = rclpy.create_node('visitor', context=context)
    intruder.parameter_client = AsyncParameterClient(intruder, 'computed_torque')
    intruder.reset_client = intruder.create_client(Trigger, 'computed_torque/reset')
    done = []

    def on_state(msg):
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if not done and msg.position and round(t / 0.01) >= sample:
            done.append(act(intruder, msg))

    intruder.create_subscription(JointState, 'joint_states', on_state, SAMPLE_QOS)
    return intruder, done


def change_gains(node, msg):
    return node.parameter_client.set_parameters([Parameter('kp', value=[400.0] * 3)])


def reset_controller(node, msg):
    from std_srvs.srv import Trigger

    return node.reset_client.call_async(Trigger.Request())


def replace_reference(node, msg):
    from ddarm.ros.interface import REFERENCE_QOS, reference_msg
    from ddarm.episodes.spec import check_episode
    from trajectory_msgs.msg import JointTrajectory

    plan = check_episode(EpisodeSpec(controller='computed_torque', kp=KP, kv=KV))
    publisher = node.create_publisher(JointTrajectory, 'reference', REFERENCE_QOS)
    publisher.publish(reference_msg(msg.name, plan.times, plan.q_ref + 0.05, plan.v_ref, plan.a_ref, plan.nominal))
    return publisher


def state_ahead(node, msg):
    publisher = node.create_publisher(JointState, 'joint_states', SAMPLE_QOS)
    t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 + 0.5
    publisher.publish(joint_state_msg(msg.name, t, list(msg.position), list(msg.velocity)))
    return publisher


@pytest.mark.parametrize('act, problem', [
    (change_gains, 'was reconfigured, reset or sent another reference during the episode'),
    (reset_controller, 'was reconfigured, reset or sent another reference during the episode'),
    (replace_reference, 'was reconfigured, reset or sent another reference during the episode'
                        "|/reference is published by \\['/tuner', '/visitor'\\]"),
    # The intruder's publisher is new: its state reaches the driver once discovery has matched it, which on a loaded
    # machine can come after the plant has passed that sample (seen once in a full run), and then it is the second.
    (state_ahead, r'a joint state for sample \d+ where sample \d+ was due'
                  r'|two joint states for sample \d+: a second publisher on /joint_states\?'),
])
def test_a_node_that_meddles_once_during_the_episode_fails_it(ros_context, hand_started, act, problem):
    """Services and one-shot publishers slip past any graph check: the controller's configuration count
    and the order of the states give them away."""
    intruder, done = intruder_at_sample(ros_context, 30, act)
    assert_episode_fails(ros_context, problem, intruder)
    assert done, 'the intruder never acted'


def test_a_forged_plant_report_is_a_named_failure_not_a_crash(ros_context, hand_started):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from ddarm.ros.interface import DIAGNOSTICS_QOS

    def forge(node, msg):
        publisher = node.create_publisher(DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        values = {'event': 'complete', 'node': '/plant', 'refused_commands': 'notanumber'}
        publisher.publish(DiagnosticArray(status=[DiagnosticStatus(
            name='ddarm/plant', values=[KeyValue(key=k, value=v) for k, v in values.items()])]))
        return publisher

    intruder, _ = intruder_at_sample(ros_context, 5, forge)
    # Judged as it comes, not at the episode's end, when the plant's own report may have replaced it.
    assert_episode_fails(ros_context, 'report of /plant does not parse', intruder)


@pytest.mark.parametrize('target, parameter, value', [
    ('plant', 'mass_scale', [2.0, 2.0, 2.0]),
    ('computed_torque', 'coulomb_friction', [50.0, 50.0, 50.0]),
])
def test_parameters_another_node_sets_before_the_start_fail_the_episode(ros_context, hand_started, monkeypatch,
                                                                       target, parameter, value):
    """Set between the driver's configuration and the reset that starts the episode: the nodes' replies say
    what they start with, and the driver compares."""
    from rclpy.parameter_client import AsyncParameterClient

    intruder = rclpy.create_node('meddler', context=ros_context)
    client = AsyncParameterClient(intruder, target)
    configure = TunerNode._configure

    def configure_then_meddle(self, executor, node, parameters, deadline, alive):
        configure(self, executor, node, parameters, deadline, alive)
        if node == 'computed_torque':  # the driver's last configuration before the resets
            future = client.set_parameters([Parameter(parameter, value=value)])
            self._spin_until(executor, future.done, deadline, 'the meddler', alive)
            assert future.result().results[0].successful

    monkeypatch.setattr(TunerNode, '_configure', configure_then_meddle)
    assert_episode_fails(ros_context, f'/{target} started the episode with parameters that another node set '
                                      f'after this driver: {parameter} is', intruder)
