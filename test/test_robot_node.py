"""`ddarm robot`: a MuJoCo robot behind ros2_control's topics, its realism (noise, latency, watchdog, refused
commands), its lifecycle, and ddarm's controller node driving it unchanged.

In lockstep the robot publishes /clock, so that which state each command answers is known exactly: the episode
then equals `ddarm episode --mjcf` in-process. Nothing here depends on how fast the machine is.
"""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec, plan_episode
from ddarm.physics.mujoco_plant import load_robot
from ddarm.physics.simulated_robot import Realism, RealismError, SimulatedRobot
from ddarm.ros.executors import node_executor
from ddarm.ros.interface import SAMPLE_QOS
from ddarm.ros.robot_session import counted_faults
from ddarm_control.node import ControllerNode
from ddarm_sim.robot_node import RobotNode, RobotNodeError
from graph_helpers import call_service, lifecycle_state, spin_until
from two_link import robot_mjcf, write_files

pytest.importorskip('mujoco')
ROOT = Path(__file__).resolve().parent.parent
PANDA = ROOT / 'config' / 'robots' / 'panda'
MJCF, URDF, MOTION = PANDA / 'panda.xml', PANDA / 'panda-menagerie.urdf', PANDA / 'panda-motion.yaml'
COMMANDS = '/effort_controller/commands'


@pytest.fixture
def two_link(tmp_path):
    return write_files(tmp_path, robot_mjcf(' damping="0.5"', ' damping="0.5"', actuators=(
        '<motor joint="shoulder" forcerange="-30 30" forcelimited="true"/>'
        '<motor joint="elbow" forcerange="-20 20" forcelimited="true"/>')))


def simulated(mjcf, realism=Realism(), q0=(0.0, 0.0)):
    robot = load_robot(mjcf, ('shoulder', 'elbow'), (False, False), 0.01)
    return SimulatedRobot(robot, q0, np.zeros(2), realism)


# The robot's hardware side, without ROS -------------------------------------------------------

def test_a_command_reaches_the_joints_after_the_latency_and_the_mjcf_bounds_the_effort(two_link):
    mjcf = two_link[0]
    robot = simulated(mjcf, Realism(command_latency=0.02))
    commands = [np.array([5.0 + n, -3.0 - n]) for n in range(5)]
    applied = []
    for n, command in enumerate(commands):
        assert robot.receive(command, n * 0.01) is None
        assert robot.step(n * 0.01)
        applied.append(robot.applied)
    np.testing.assert_array_equal(applied[0], [0.0, 0.0])
    np.testing.assert_array_equal(applied[1], [0.0, 0.0])
    for n in range(2, 5):
        np.testing.assert_array_equal(applied[n], commands[n - 2])
    robot.receive([100.0, -100.0], 0.05)
    robot.step(0.07)
    np.testing.assert_array_equal(robot.applied, [30.0, -20.0])  # the motors' force ranges


def test_a_latency_of_whole_periods_is_whole_periods_whatever_the_rounding(two_link):
    robot = simulated(two_link[0], Realism(command_latency=0.02))
    for n in range(20):  # sample instants as the node makes them, n Δ: 7 Δ + 0.02 rounds past 9 Δ
        robot.receive([float(n + 1), 0.0], n * 0.01)
        robot.step(n * 0.01)
        assert robot.applied[0] == (0.0 if n < 2 else n - 1)


def test_a_refused_command_holds_the_one_in_force(two_link):
    robot = simulated(two_link[0])
    robot.receive([1.0, 2.0], 0.0)
    robot.step(0.0)
    assert 'of 3 efforts for the 2 joints' in robot.receive([1.0, 2.0, 3.0], 0.01)
    assert 'not finite' in robot.receive([float('nan'), 1.0], 0.01)
    robot.step(0.01)
    np.testing.assert_array_equal(robot.applied, [1.0, 2.0])
    assert robot.counters == {'commands': 1, 'refused_commands': 2, 'timeouts': 0}


def test_no_command_for_the_timeout_zeroes_the_efforts_until_the_next(two_link):
    robot = simulated(two_link[0], Realism(command_timeout=0.05))
    for n in range(10):  # no command yet: nothing is overdue, the efforts are zero already
        robot.step(n * 0.01 - 0.1)
    assert not robot.timed_out
    robot.receive([4.0, 3.0], 0.0)
    for n in range(6):
        robot.step(n * 0.01)
    assert not robot.timed_out
    np.testing.assert_array_equal(robot.applied, [4.0, 3.0])
    robot.step(0.06)
    assert robot.timed_out and robot.counters['timeouts'] == 1
    np.testing.assert_array_equal(robot.applied, [0.0, 0.0])
    robot.step(0.07)
    assert robot.counters['timeouts'] == 1  # one time out, however long
    robot.receive([2.0, 1.0], 0.075)
    robot.step(0.08)
    assert not robot.timed_out
    np.testing.assert_array_equal(robot.applied, [2.0, 1.0])


def test_the_noise_is_seeded_and_of_the_deviation_asked(two_link):
    realism = Realism(position_noise=0.01, velocity_noise=0.1, seed=3)
    first, second, exact = simulated(two_link[0], realism), simulated(two_link[0], realism), simulated(two_link[0])
    samples = np.array([np.concatenate(first.measured()) for _ in range(4000)])
    again = np.array([np.concatenate(second.measured()) for _ in range(4000)])
    np.testing.assert_array_equal(samples, again)
    errors = samples - np.concatenate(exact.measured())
    np.testing.assert_allclose(errors.std(axis=0), [0.01, 0.01, 0.1, 0.1], rtol=0.05)
    np.testing.assert_array_equal(np.concatenate(exact.measured()), [0.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize('setting', ['position_noise', 'command_latency', 'command_timeout'])
def test_a_realism_setting_must_be_finite_and_not_negative(setting):
    for value in (-1.0, float('inf')):
        with pytest.raises(RealismError, match=setting):
            Realism(**{setting: value})


# The node ------------------------------------------------------------------------------------

def robot_node(context, mjcf, **parameters):
    return RobotNode(context=context, parameter_overrides=[
        Parameter('mjcf', value=str(mjcf)), *(Parameter(name, value=value) for name, value in parameters.items())])


class Graph:
    """The nodes of one test on one executor, and a recorder of /joint_states."""

    def __init__(self, context, *nodes):
        self.context = context
        self.client_node = rclpy.create_node('test_client', context=context)
        self.states = []
        self.client_node.create_subscription(JointState, '/joint_states', self.states.append, SAMPLE_QOS)
        self.commands = self.client_node.create_publisher(Float64MultiArray, COMMANDS, 10)
        self.executor = node_executor(context)
        for node in (*nodes, self.client_node):
            self.executor.add_node(node)

    def spin_until(self, condition, timeout=30.0):
        spin_until(self.executor, condition, timeout=timeout)

    def call(self, service_type, name, request):
        client = self.client_node.create_client(service_type, name)
        try:
            return call_service(self.executor, client, request)
        finally:
            self.client_node.destroy_client(client)

    def status(self, node='/robot'):
        return json.loads(self.call(Trigger, f'{node}/status', Trigger.Request()).message)

    def close(self):
        self.executor.shutdown()
        self.client_node.destroy_node()


def episode_on_the_robot(context, law, delay, gains, **robot_parameters):
    """The Panda robot in lockstep driven by the controller node in robot mode (a timer on /clock, the efforts as
    a Float64MultiArray), and the same episode in-process: the states the robot published from its first
    commanded sample, and the in-process episode."""
    spec = EpisodeSpec(controller=law, kp=(gains[0],) * 7, kv=(gains[1],) * 7, delay=delay, urdf=str(URDF),
                       motion=str(MOTION), mjcf=str(MJCF))
    plan = plan_episode(spec)
    expected = run_episode(spec, plan)
    robot = robot_node(context, MJCF, mode='lockstep', initial_position=plan.q0.tolist(),
                       initial_velocity=plan.v0.tolist(), **robot_parameters)
    controller = ControllerNode(law, context=context, parameter_overrides=[
        Parameter('urdf', value=str(URDF)), Parameter('motion', value=str(MOTION)),
        Parameter('sampling', value='timer'), Parameter('command_type', value='float64_multi_array'),
        Parameter('command_topic', value=COMMANDS), Parameter('use_sim_time', value=True),
        Parameter('delay', value=delay), Parameter('velocity_limit_factor', value=1e6),
        *[Parameter(f'gains.{joint}.{key}', value=gain) for joint in plan.joint_names
          for key, gain in zip('pd', gains)]])
    graph = Graph(context, robot, controller)
    try:
        graph.spin_until(lambda: len(graph.states) > plan.k_max + 2)
        # Clamped to the URDF's effort limits, which are the MJCF's force ranges: the robot applies the same.
        faults = {name: count for name, count in controller.counters.items() if name != 'clamped_commands'}
        assert sum(faults.values()) == 0, faults
        assert robot.robot.counters['timeouts'] == 0 and robot.robot.counters['refused_commands'] == 0
        stamps = [msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec for msg in graph.states]
        # Sample 0 may have gone out more than once, a period apart, before the controller's first command.
        first = max(i for i in range(len(stamps)) if np.allclose(graph.states[i].position, plan.q0, atol=0))
        states = graph.states[first:first + plan.k_max + 1]
        assert np.diff(stamps[first:first + plan.k_max + 1]).tolist() == [10_000_000] * plan.k_max
        return states, expected
    finally:
        graph.close()
        for node in (robot, controller):
            node.destroy_node()


@pytest.mark.parametrize('law, delay, gains', [('computed_torque', 1, (400.0, 40.0)),
                                               ('computed_torque', 2, (225.0, 30.0)),
                                               ('pd_gravity', 1, (600.0, 60.0))])
def test_in_lockstep_the_controller_node_on_the_robot_is_the_in_process_episode(ros_context, law, delay, gains):
    states, expected = episode_on_the_robot(ros_context, law, delay, gains)
    q = np.array([msg.position for msg in states])
    v = np.array([msg.velocity for msg in states])
    effort = np.array([msg.effort for msg in states])
    np.testing.assert_allclose(q, expected.q[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(v, expected.v[0], rtol=0, atol=1e-9)
    # A state carries the effort applied over the period before it.
    np.testing.assert_allclose(effort[1:], expected.torque[0][:-1], rtol=0, atol=1e-9)
    assert [msg.name for msg in states[:1]] == [list(expected.joint_names)]


def test_joints_the_mjcf_lacks_are_refused_at_configure_naming_them(ros_context):
    with pytest.raises(RobotNodeError, match=r"\['wrist'\], which the MJCF .* does not have"):
        robot_node(ros_context, MJCF, joints=['panda_joint1', 'wrist'])
    node = robot_node(ros_context, MJCF, autostart=False, joints=['panda_joint1'])
    try:
        graph = Graph(ros_context, node)
        reply = graph.call(ChangeState, '/robot/change_state',
                           ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE)))
        assert not reply.success
        assert 'leaves out' in str(node.configure_error)
        state = graph.call(GetState, '/robot/get_state', GetState.Request()).current_state.label
        assert state == 'unconfigured'
        graph.close()
    finally:
        node.destroy_node()


def test_the_lifecycle_configure_activate_deactivate_cleanup(ros_context, two_link):
    node = robot_node(ros_context, two_link[0], autostart=False, command_timeout=0.0)
    graph = Graph(ros_context, node)
    try:
        def change(transition):
            return graph.call(ChangeState, '/robot/change_state',
                              ChangeState.Request(transition=Transition(id=transition))).success

        def state():
            return graph.call(GetState, '/robot/get_state', GetState.Request()).current_state.label

        assert state() == 'unconfigured' and node.robot is None
        with pytest.raises(Exception):  # out of order: rclpy's state machine refuses it
            node.trigger_activate()
        assert not change(Transition.TRANSITION_ACTIVATE)  # refused through the service, the node lives on
        assert state() == 'unconfigured'
        assert change(Transition.TRANSITION_CONFIGURE) and state() == 'inactive'
        deadline = time.monotonic() + 0.3
        graph.spin_until(lambda: time.monotonic() > deadline)
        assert graph.states == []  # configured, not active: nothing published
        assert change(Transition.TRANSITION_ACTIVATE) and state() == 'active'
        graph.spin_until(lambda: len(graph.states) > 5)
        graph.commands.publish(Float64MultiArray(data=[1.0, 2.0]))
        graph.spin_until(lambda: graph.status()['commands'] == 1)
        assert change(Transition.TRANSITION_DEACTIVATE) and state() == 'inactive'
        count = len(graph.states)
        graph.commands.publish(Float64MultiArray(data=[1.0, 2.0]))
        deadline = time.monotonic() + 0.3
        graph.spin_until(lambda: time.monotonic() > deadline)
        assert len(graph.states) == count  # deactivated: no more states, no command taken
        assert graph.status()['commands'] == 1
        assert change(Transition.TRANSITION_CLEANUP) and state() == 'unconfigured' and node.robot is None
        assert change(Transition.TRANSITION_CONFIGURE) and change(Transition.TRANSITION_ACTIVATE)
        graph.spin_until(lambda: len(graph.states) > count + 3)
    finally:
        graph.close()
        node.destroy_node()


def test_free_running_the_robot_publishes_on_its_own_and_zeroes_efforts_without_commands(ros_context, two_link):
    node = robot_node(ros_context, two_link[0], command_timeout=0.05, position_noise=0.001)
    graph = Graph(ros_context, node)
    try:
        graph.spin_until(lambda: len(graph.states) > 3)
        graph.commands.publish(Float64MultiArray(data=[3.0, -2.0]))
        graph.spin_until(lambda: any(list(msg.effort) == [3.0, -2.0] for msg in graph.states))
        graph.commands.publish(Float64MultiArray(data=[1.0]))  # the wrong length: refused, the one in force held
        graph.spin_until(lambda: graph.status()['refused_commands'] == 1)
        graph.spin_until(lambda: graph.status()['timeouts'] == 1)
        graph.spin_until(lambda: list(graph.states[-1].effort) == [0.0, 0.0])
        stamps = [msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 for msg in graph.states]
        assert np.all(np.diff(stamps) > 0)
    finally:
        graph.close()
        node.destroy_node()


def test_ddarm_robot_refuses_a_missing_mjcf_in_one_line():
    result = subprocess.run([sys.executable, '-m', 'ddarm.cli.main', 'robot', '--ros-args', '-p', 'autostart:=true'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stdout + result.stderr
    assert 'robot: refused to start: mjcf is not set' in result.stdout


def test_the_faults_the_nodes_counted_are_said_and_the_clean_counters_are_not():
    counters = {'robot': {'state': 'active', 'commands': 51, 'refused_commands': 0, 'timeouts': 1, 'late_periods': 3},
                'computed_torque': {'stale_ticks': 0, 'clamped_commands': 4, 'ticks': 60}, 'pd_gravity': {}}
    assert counted_faults(counters) == ['the robot node counted timeouts 1, late_periods 3']


# Each managed node as its executable starts it: the command line, its name on the graph, and the parameter that
# starts it unconfigured (the plant's `autostart` starts an episode: `managed` says it waits for the services).
MANAGED_NODES = {'robot': (['robot', '--ros-args', '-p', f'mjcf:={MJCF}'], '/robot', 'autostart:=false'),
                 'computed_torque': (['controller', 'computed_torque', '--ros-args', '-p', 'kp:=[100.0, 100.0, 100.0]',
                                      '-p', 'kv:=[20.0, 20.0, 20.0]'], '/computed_torque', 'autostart:=false'),
                 'plant': (['plant', '--ros-args'], '/plant', 'managed:=true')}


@pytest.mark.parametrize('node', sorted(MANAGED_NODES))
@pytest.mark.parametrize('state', ['unconfigured', 'inactive', 'active'])
@pytest.mark.parametrize('stop', [signal.SIGINT, signal.SIGTERM])
def test_sigint_or_sigterm_in_any_state_ends_a_managed_node_cleanly(ros_context, node, state, stop):
    command, name, unconfigured = MANAGED_NODES[node]
    process = subprocess.Popen([sys.executable, '-m', 'ddarm.cli.main', *command,
                                *(['-p', unconfigured] if state != 'active' else [])],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    client_node = rclpy.create_node('signal_probe', context=ros_context)
    executor = node_executor(ros_context)
    executor.add_node(client_node)
    try:
        state_client = client_node.create_client(GetState, f'{name}/get_state')
        spin_until(executor, lambda: state_client.service_is_ready() or process.poll() is not None, timeout=60)
        assert process.poll() is None, f'{name} ended: {process.communicate()[0]}'
        if state == 'inactive':
            change = client_node.create_client(ChangeState, f'{name}/change_state')
            spin_until(executor, change.service_is_ready)
            change.call_async(ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE)))
            # Its reply may be lost (see call_service); the state it leads to is what counts.
            spin_until(executor, lambda: lifecycle_state(executor, state_client) == 'inactive', timeout=60)
        assert lifecycle_state(executor, state_client) == state
        process.send_signal(stop)
        output, _ = process.communicate(timeout=30)
        assert process.returncode == 0, output
        assert 'Traceback' not in output
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        executor.shutdown()
        client_node.destroy_node()


def test_ddarm_robot_takes_its_mjcf_as_an_option(ros_context, tmp_path):
    process = subprocess.Popen([sys.executable, '-m', 'ddarm.cli.main', 'robot', '--mjcf', str(MJCF), '--ros-args',
                                '-p', 'mode:=realtime'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    node = rclpy.create_node('option_probe', context=ros_context)
    executor = node_executor(ros_context)
    executor.add_node(node)
    states = []
    node.create_subscription(JointState, '/joint_states', states.append, SAMPLE_QOS)
    try:
        deadline = time.monotonic() + 60
        while not states:
            assert time.monotonic() < deadline and process.poll() is None, 'no state from the robot'
            executor.spin_once(timeout_sec=0.05)
        assert list(states[0].name) == [f'panda_joint{n}' for n in range(1, 8)]
    finally:
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=30)
        executor.shutdown()
        node.destroy_node()
    assert process.returncode == 0, output
