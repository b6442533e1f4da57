"""The controller node as a managed (lifecycle) node: `autostart` false brings it up unconfigured, and the
lifecycle services configure, activate, deactivate and clean it up; only an active node sends commands.

Timer mode on simulated time: the test publishes /clock and the robot's states, so each tick is known exactly and
nothing here depends on how fast the machine is. That no command went out is told by the order of a reliable
topic: the first command after an activation is the first one on the topic.
"""

import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from ddarm.control.laws import GainError
from ddarm.motion.files import load_motion
from ddarm.motion.programmed import MotionError
from ddarm_control.node import ControllerNode
from graph_helpers import call_service, change_state, lifecycle_state, overrides, spin_until

ROOT = Path(__file__).resolve().parent.parent
UR5 = ROOT / 'config' / 'arms' / 'ur5'
URDF, MOTION = UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml'
pytestmark = pytest.mark.skipif(not URDF.is_file(), reason='config/arms/ur5 is not in the tree')
PERIOD = 10_000_000  # Δ in ns
START = 5_000_000_000  # the clock at the first tick, ns
COMMANDS = '/effort_controller/commands'
LAW = 'computed_torque'
# A node's own topics before configure: parameter events, and /clock under use_sim_time.
BASE_TOPICS = {'/parameter_events', '/clock'}
SYSTEM_DEFAULT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE)


def stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def controller(context, **extra) -> ControllerNode:
    joints = list(load_motion(MOTION).joint_names)
    gains = {f'gains.{joint}.{key}': value for joint in joints for key, value in (('p', 225.0), ('d', 30.0))}
    return ControllerNode(LAW, context=context, parameter_overrides=overrides({
        'use_sim_time': True, 'sampling': 'timer', 'command_type': 'float64_multi_array', 'command_topic': COMMANDS,
        'motion': str(MOTION), 'urdf': str(URDF), 'delay': 1, 'period': PERIOD * 1e-9,
        **gains, **extra}))


class Peer:
    """The robot's and the lifecycle manager's side: /clock, /joint_states, the commands and the lifecycle services."""

    def __init__(self, context, node: ControllerNode):
        self.node = node
        self.peer = rclpy.create_node('lifecycle_peer', context=context)
        self.clock = self.peer.create_publisher(Clock, '/clock', 10)
        self.states = self.peer.create_publisher(JointState, '/joint_states', SYSTEM_DEFAULT)
        self.commands = []
        self.command_subscription = self.peer.create_subscription(Float64MultiArray, COMMANDS, self.commands.append,
                                                                  SYSTEM_DEFAULT)
        name = node.get_name()
        self.change_client = self.peer.create_client(ChangeState, f'/{name}/change_state')
        self.state_client = self.peer.create_client(GetState, f'/{name}/get_state')
        self.executor = SingleThreadedExecutor(context=context)
        for each in (node, self.peer):
            self.executor.add_node(each)
        self.joints = list(load_motion(MOTION).joint_names)
        self.clock_ns = 0

    def spin_until(self, condition, resend=None, timeout=30.0):
        spin_until(self.executor, condition, resend, timeout)

    def call(self, client, request):
        return call_service(self.executor, client, request)

    def change(self, transition: int) -> bool:
        return change_state(self.executor, self.change_client, transition)

    def state(self) -> str:
        return lifecycle_state(self.executor, self.state_client)

    def wait_for_peers(self) -> None:
        """Configured: the node's command publisher and state subscription matched with ours, /clock heard."""
        self.spin_until(lambda: self.node.command_publisher.get_subscription_count()
                        and self.states.get_subscription_count() and self.clock.get_subscription_count())

    def tick(self, ns: int) -> None:
        """Advance the node's clock to `ns`, one period on: its timer fires once (counted active or not)."""
        ticks = self.node.ticks

        def send():
            self.clock.publish(Clock(clock=stamp(ns)))
        send()
        self.spin_until(lambda: self.node.get_clock().now().nanoseconds == ns and self.node.ticks == ticks + 1,
                        send)
        self.clock_ns = ns

    def state_msg(self, ns: int, q, v) -> JointState:
        msg = JointState(name=self.joints, position=[float(x) for x in q], velocity=[float(x) for x in v])
        msg.header.stamp = stamp(ns)
        return msg

    def send_state(self, ns: int, q, v) -> None:
        """A state stamped `ns`, spun until the node held it."""
        msg = self.state_msg(ns, q, v)
        self.states.publish(msg)
        self.spin_until(lambda: self.node.latest_state is not None and self.node.latest_state.stamp == ns,
                        lambda: self.states.publish(msg))

    def send_ignored_state(self, ns: int, q, v) -> None:
        """A state to a node that is not active: spun until it arrived and was ignored."""
        msg = self.state_msg(ns, q, v)
        ignored = self.node.ignored_messages
        self.states.publish(msg)
        self.spin_until(lambda: self.node.ignored_messages > ignored, lambda: self.states.publish(msg))
        assert self.node.latest_state is None

    def wait_for_commands(self, count: int) -> None:
        self.spin_until(lambda: len(self.commands) >= count)
        assert len(self.commands) == count

    def close(self) -> None:
        self.executor.shutdown()
        self.peer.destroy_node()


def own_services(node) -> set:
    return {service.srv_name for service in node.services}


def own_topics(node) -> set:
    return {publisher.topic_name for publisher in node.publishers} | \
        {subscription.topic_name for subscription in node.subscriptions}


def test_without_autostart_only_the_lifecycle_services_configure_activate_deactivate_and_clean_up(ros_context):
    node = controller(ros_context, autostart=False)
    peer = Peer(ros_context, node)
    try:
        # Unconfigured: the parameters and the lifecycle services, no command publisher, nothing of configure.
        assert peer.state() == 'unconfigured'
        assert node.command_publisher is None and node.model is None and node.timer is None
        assert own_topics(node) <= BASE_TOPICS
        assert {'/computed_torque/change_state', '/computed_torque/get_state'} <= own_services(node)
        assert not {'~/reset', '~/status'} & own_services(node)
        assert node.has_parameter('kp') and node.get_parameter('autostart').value is False
        # A parameter set before configure is what configure reads.
        node.set_parameters([Parameter('max_clock_jump', value=0.25)])

        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert node.model is not None and node.max_clock_jump == 250_000_000
        assert {COMMANDS, '/joint_states', '/diagnostics'} <= own_topics(node)
        assert {'~/reset', '~/status'} <= own_services(node)
        peer.wait_for_peers()
        # Inactive: states are ignored, ticks send nothing.
        q0, v0 = load_motion(MOTION).motion.q0 + 0.01, np.full(6, 0.02)
        for n in range(3):
            peer.send_ignored_state(START + n * PERIOD, q0, v0)
            peer.tick(START + n * PERIOD)
        assert node.start_time is None and node.tick_sample is None

        assert peer.change(Transition.TRANSITION_ACTIVATE) and peer.state() == 'active'
        first = START + 10 * PERIOD
        peer.send_state(first, q0, v0)
        peer.tick(first)
        # Reliable and in order: had the inactive node sent anything, it would have come before this one.
        peer.wait_for_commands(1)
        assert node.start_time == first and node.tick_sample == 0
        peer.send_state(first + PERIOD, q0 + 0.01, v0)
        peer.tick(first + PERIOD)
        peer.wait_for_commands(2)
        assert node.tick_sample == 1

        configuration = node.configuration
        assert peer.change(Transition.TRANSITION_DEACTIVATE) and peer.state() == 'inactive'
        assert node.configuration == configuration + 1
        for n in range(2, 6):
            peer.send_ignored_state(first + n * PERIOD, q0, v0)
            peer.tick(first + n * PERIOD)
        # Activated again: a fresh motion, sample 0 at the next tick with a fresh state, the delay buffer empty,
        # so the same state at sample 0 gives the same command as the first activation's.
        assert peer.change(Transition.TRANSITION_ACTIVATE) and peer.state() == 'active'
        again = first + 10 * PERIOD
        peer.send_state(again, q0, v0)
        peer.tick(again)
        peer.wait_for_commands(3)  # none while inactive
        assert node.start_time == again and node.tick_sample == 0
        np.testing.assert_array_equal(peer.commands[2].data, peer.commands[0].data)
        assert all(np.isfinite(msg.data).all() for msg in peer.commands)

        assert peer.change(Transition.TRANSITION_DEACTIVATE)
        assert peer.change(Transition.TRANSITION_CLEANUP) and peer.state() == 'unconfigured'
        assert node.command_publisher is None and node.model is None and node.controller is None
        assert own_topics(node) <= BASE_TOPICS
        assert not {'~/reset', '~/status'} & own_services(node)
        peer.spin_until(lambda: peer.command_subscription.get_publisher_count() == 0)
        # Configured again from the parameters (the gains by joint declared at the first configure).
        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert node.command_publisher is not None and node.gains_ready
        assert peer.change(Transition.TRANSITION_INACTIVE_SHUTDOWN)
        assert peer.state() == 'finalized' and node.command_publisher is None and node.model is None
        assert len(peer.commands) == 3
    finally:
        peer.close()
        node.destroy_node()


def test_an_out_of_order_transition_is_refused_and_changes_nothing(ros_context):
    node = controller(ros_context, autostart=False)
    peer = Peer(ros_context, node)
    try:
        with pytest.raises(_rclpy.RCLError):  # rclpy's state machine has no activate from unconfigured
            node.trigger_activate()
        assert peer.state() == 'unconfigured'
        # Through the service: answered success False (the executor goes on), the state unchanged.
        assert not peer.change(Transition.TRANSITION_ACTIVATE)
        assert not peer.change(Transition.TRANSITION_DEACTIVATE)
        assert peer.state() == 'unconfigured' and node.command_publisher is None and not node.active
        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert not peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert node.command_publisher is not None
    finally:
        peer.close()
        node.destroy_node()


def test_a_failed_configure_leaves_the_node_unconfigured_and_says_why_and_refuses_it_at_autostart(ros_context,
                                                                                                 tmp_path):
    missing = tmp_path / 'no-such-motion.yaml'
    watcher = rclpy.create_node('watcher', context=ros_context)
    node = controller(ros_context, autostart=False, motion=str(missing))
    peer = Peer(ros_context, node)
    try:
        peer.spin_until(lambda: LAW in watcher.get_node_names())
        assert not peer.change(Transition.TRANSITION_CONFIGURE)
        assert peer.state() == 'unconfigured'
        assert isinstance(node.configure_error, MotionError)
        assert str(missing) in str(node.configure_error) and 'cannot read the motion file' in str(node.configure_error)
        assert node.command_publisher is None and node.model is None
        assert own_topics(node) <= BASE_TOPICS
    finally:
        peer.close()
        node.destroy_node()
    # With autostart (the default), as before the lifecycle: the constructor raises the same error.
    with pytest.raises(MotionError, match='cannot read the motion file') as refused:
        controller(ros_context, motion=str(missing))
    assert str(missing) in str(refused.value)
    # The node destroyed above (and the refused one) are gone from the graph, not left to the garbage collector.
    try:
        deadline = time.monotonic() + 30.0
        while LAW in watcher.get_node_names():
            assert time.monotonic() < deadline, 'a destroyed controller stayed in the graph (a hang guard)'
            time.sleep(0.05)
    finally:
        watcher.destroy_node()


def test_a_configure_refused_after_the_model_is_built_makes_nothing(ros_context):
    """A refusal late in configure (the command topic) leaves no publisher, subscription, timer or service."""
    node = controller(ros_context, autostart=False, command_topic='not a topic')
    peer = Peer(ros_context, node)
    try:
        assert not peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'unconfigured'
        assert "command_topic 'not a topic' is no topic name" in str(node.configure_error)
        assert own_topics(node) <= BASE_TOPICS and not {'~/reset', '~/status'} & own_services(node)
        assert node.model is None
    finally:
        peer.close()
        node.destroy_node()


def test_an_unknown_parameter_is_still_refused_at_construction(ros_context):
    with pytest.raises(GainError, match=r"unknown parameters \['kpp'\]"):
        controller(ros_context, autostart=False, kpp=[1.0])
    joints = list(load_motion(MOTION).joint_names)
    # gains for a joint the controller does not control: known only at configure, which refuses them.
    node = controller(ros_context, autostart=False, **{'gains.finger_joint.p': 5.0})
    try:
        assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert "gains for joint 'finger_joint'" in str(node.configure_error)
        assert str(joints) in str(node.configure_error)
    finally:
        node.destroy_node()
