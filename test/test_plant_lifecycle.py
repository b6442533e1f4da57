"""The plant node as a managed (lifecycle) node: `managed` true brings it up unconfigured, and the lifecycle services
configure it, activate it (an episode starts, as ~/reset starts one), deactivate it (the episode ends: no more
states, commands ignored, ~/reset refused) and clean it up. `managed` false (the default) starts as it always has.

Nothing here depends on how fast the machine is: messages are counted, and that nothing was published while the
plant was inactive is told by the order of a reliable topic (the first state after an activation is sample 0).
"""


import pytest
import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from ddarm.physics.plant import PlantError
from ddarm.ros.interface import EFFORT_COMMAND_TOPIC, JOINT_STATES_TOPIC, SAMPLE_QOS, time_msg
from ddarm_sim.node import IDLE, RUNNING, STARTING, PlantNode
from graph_helpers import call_service, change_state, lifecycle_state, overrides, spin_until

PERIOD = 0.02  # s: set before configure, which reads it
BASE_TOPICS = {'/parameter_events'}  # a node's own topic before configure
LIFECYCLE_SERVICES = {'/plant/change_state', '/plant/get_state'}


def stamp_seconds(msg: JointState) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def own_topics(node) -> set:
    return {publisher.topic_name for publisher in node.publishers} | \
        {subscription.topic_name for subscription in node.subscriptions}


def own_services(node) -> set:
    return {service.srv_name for service in node.services}


class Peer:
    """The controller's and the lifecycle manager's side: /joint_states read, commands sent, the services called."""

    def __init__(self, context, node: PlantNode):
        self.node = node
        self.peer = rclpy.create_node('plant_lifecycle_peer', context=context)
        self.states: list[JointState] = []
        self.state_subscription = self.peer.create_subscription(JointState, JOINT_STATES_TOPIC, self.states.append,
                                                                SAMPLE_QOS)
        self.commands = self.peer.create_publisher(JointState, EFFORT_COMMAND_TOPIC, SAMPLE_QOS)
        self.change_client = self.peer.create_client(ChangeState, '/plant/change_state')
        self.state_client = self.peer.create_client(GetState, '/plant/get_state')
        self.reset_client = self.peer.create_client(Trigger, '/plant/reset')
        self.executor = SingleThreadedExecutor(context=context)
        for each in (node, self.peer):
            self.executor.add_node(each)

    def spin_until(self, condition, resend=None, timeout=30.0):
        spin_until(self.executor, condition, resend, timeout)

    def call(self, client, request):
        return call_service(self.executor, client, request)

    def change(self, transition: int) -> bool:
        return change_state(self.executor, self.change_client, transition)

    def state(self) -> str:
        return lifecycle_state(self.executor, self.state_client)

    def reset(self) -> Trigger.Response:
        return self.call(self.reset_client, Trigger.Request())

    def matched(self) -> None:
        """Configured: the plant's state publisher and command subscription matched with ours."""
        self.spin_until(lambda: self.node.state_publisher.get_subscription_count() >= 1
                        and self.node.command_subscription.get_publisher_count() >= 1
                        and self.state_subscription.get_publisher_count() >= 1)

    def command(self, sample: int, names=None) -> None:
        """A zero effort command for `sample`, as the controller answers a state."""
        names = list(self.node.joints) if names is None else names
        msg = JointState(name=names, effort=[0.0] * len(names))
        msg.header.stamp = time_msg(sample * PERIOD)
        self.commands.publish(msg)

    def wait_for_states(self, count: int) -> None:
        self.spin_until(lambda: len(self.states) >= count)
        assert len(self.states) == count

    def close(self) -> None:
        self.executor.shutdown()
        self.peer.destroy_node()


def managed_plant(context, **extra) -> PlantNode:
    return PlantNode(context=context, parameter_overrides=overrides({'managed': True, **extra}))


def test_managed_the_lifecycle_services_configure_activate_deactivate_and_clean_up(ros_context):
    node = managed_plant(ros_context)
    peer = Peer(ros_context, node)
    try:
        # Unconfigured: the parameters and the lifecycle services; no /joint_states publisher, no ~/reset.
        assert peer.state() == 'unconfigured'
        assert node.state_publisher is None and node.arm is None and node.watchdog is None
        assert own_topics(node) <= BASE_TOPICS
        assert LIFECYCLE_SERVICES <= own_services(node) and '~/reset' not in own_services(node)
        assert node.get_parameter('managed').value is True and node.get_parameter('autostart').value is True
        assert peer.state_subscription.get_publisher_count() == 0
        # A parameter set before configure is what configure reads.
        assert node.set_parameters([Parameter('period', value=PERIOD)])[0].successful

        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert node.settings.period == PERIOD and node.phase == IDLE and node.plant is None
        assert {'/joint_states', '/effort_command', '/clock', '/diagnostics'} <= own_topics(node)
        assert '~/reset' in own_services(node)
        peer.matched()
        # Inactive: ~/reset refused, no episode.
        refused = peer.reset()
        assert not refused.success and 'the plant is inactive: activate it first' in refused.message
        assert node.phase == IDLE and node.plant is None

        # Active: an episode starts; sample 0 goes out (matched already). Reliable and in order: had the inactive
        # plant published anything, it would have come first.
        assert peer.change(Transition.TRANSITION_ACTIVATE) and peer.state() == 'active'
        peer.wait_for_states(1)
        assert stamp_seconds(peer.states[0]) == 0.0 and list(peer.states[0].name) == list(node.joints)
        for n in range(3):  # lockstep: each command integrates one period
            peer.command(n)
            peer.wait_for_states(n + 2)
        assert [round(stamp_seconds(msg) / PERIOD) for msg in peer.states] == [0, 1, 2, 3]
        assert node.phase == RUNNING and node.plant.sample == 3

        # Deactivated: the episode ends; a command for the next sample is ignored. A refused one sent after it is
        # counted, and the topic is reliable and in order: the valid one arrived first, and was ignored.
        assert peer.change(Transition.TRANSITION_DEACTIVATE) and peer.state() == 'inactive'
        assert node.phase == IDLE
        peer.command(3)
        refused_commands = node.counters['refused_commands']
        peer.command(4, names=['no_such_joint'] * len(node.joints))
        peer.spin_until(lambda: node.counters['refused_commands'] == refused_commands + 1)
        assert node.plant.sample == 3 and node.phase == IDLE
        refused = peer.reset()
        assert not refused.success and 'inactive' in refused.message

        # Activated again: a new episode from sample 0, the first state since the deactivation.
        assert peer.change(Transition.TRANSITION_ACTIVATE) and peer.state() == 'active'
        peer.wait_for_states(5)
        assert stamp_seconds(peer.states[4]) == 0.0
        # Active, ~/reset starts episodes as it always has.
        answer = peer.reset()
        assert answer.success and 'episode starts in lockstep mode' in answer.message
        peer.wait_for_states(6)
        assert stamp_seconds(peer.states[5]) == 0.0

        assert peer.change(Transition.TRANSITION_DEACTIVATE)
        assert peer.change(Transition.TRANSITION_CLEANUP) and peer.state() == 'unconfigured'
        assert node.state_publisher is None and node.arm is None and node.plant is None and node.watchdog is None
        assert own_topics(node) <= BASE_TOPICS and '~/reset' not in own_services(node)
        peer.spin_until(lambda: peer.state_subscription.get_publisher_count() == 0)
        # Configured again from the parameters, then shut down: freed.
        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert node.state_publisher is not None and node.settings.period == PERIOD
        assert peer.change(Transition.TRANSITION_INACTIVE_SHUTDOWN) and peer.state() == 'finalized'
        assert node.state_publisher is None and node.arm is None
        assert len(peer.states) == 6
    finally:
        peer.close()
        node.destroy_node()


def test_deactivating_while_waiting_for_subscribers_ends_the_start(ros_context):
    node = managed_plant(ros_context)
    peer = Peer(ros_context, node)
    try:
        peer.peer.destroy_publisher(peer.commands)  # no command publisher: the episode waits to start
        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.change(Transition.TRANSITION_ACTIVATE)
        assert node.phase == STARTING
        assert peer.change(Transition.TRANSITION_DEACTIVATE) and node.phase == IDLE
        assert peer.state() == 'inactive' and peer.states == []
    finally:
        peer.close()
        node.destroy_node()


def test_an_out_of_order_transition_is_refused_and_the_node_lives_on(ros_context):
    node = managed_plant(ros_context)
    peer = Peer(ros_context, node)
    try:
        for transition in (Transition.TRANSITION_ACTIVATE, Transition.TRANSITION_DEACTIVATE,
                           Transition.TRANSITION_CLEANUP):
            assert not peer.change(transition)
        assert peer.state() == 'unconfigured' and node.state_publisher is None
        assert peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert not peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'inactive'
        assert not peer.change(Transition.TRANSITION_DEACTIVATE) and peer.state() == 'inactive'
        assert node.state_publisher is not None and node.phase == IDLE
    finally:
        peer.close()
        node.destroy_node()


def test_a_failed_configure_leaves_the_plant_unconfigured_and_says_why(ros_context, tmp_path):
    missing = tmp_path / 'no-such-motion.yaml'
    node = managed_plant(ros_context, motion=str(missing))
    peer = Peer(ros_context, node)
    try:
        assert not peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'unconfigured'
        assert isinstance(node.configure_error, PlantError)
        assert f'parameter motion = {str(missing)!r}' in str(node.configure_error)
        assert node.state_publisher is None and node.arm is None and own_topics(node) <= BASE_TOPICS
        assert '~/reset' not in own_services(node)
    finally:
        peer.close()
        node.destroy_node()
    # Unmanaged (the default), as before the lifecycle: the constructor raises the same error.
    with pytest.raises(PlantError, match='parameter motion = ') as refused:
        PlantNode(context=ros_context, parameter_overrides=overrides({'motion': str(missing)}))
    assert str(refused.value) == str(node.configure_error)


def test_parameters_are_checked_once_configured_and_by_configure_before(ros_context):
    node = managed_plant(ros_context)
    peer = Peer(ros_context, node)
    try:
        # Unconfigured: nothing to check against yet (the arm is built at configure); configure refuses it.
        assert node.set_parameters([Parameter('mode', value='bogus')])[0].successful
        assert not peer.change(Transition.TRANSITION_CONFIGURE) and peer.state() == 'unconfigured'
        assert 'mode must be one of' in str(node.configure_error)
        assert node.set_parameters([Parameter('mode', value='lockstep')])[0].successful
        assert peer.change(Transition.TRANSITION_CONFIGURE) and node.configure_error is None
        # Configured: checked as always.
        result = node.set_parameters([Parameter('mode', value='bogus')])[0]
        assert not result.successful and 'mode must be one of' in result.reason
        assert node.get_parameter('mode').value == 'lockstep'
    finally:
        peer.close()
        node.destroy_node()


def test_unknown_parameters_are_refused_at_construction_managed_or_not(ros_context):
    for managed in (True, False):
        with pytest.raises(PlantError, match=r"unknown parameters \['perod'\] \(not plant parameters: a typo\?\)"):
            PlantNode(context=ros_context, parameter_overrides=overrides({'managed': managed, 'perod': 0.02}))


def test_unmanaged_the_plant_is_configured_and_active_at_launch_idle_without_autostart(ros_context):
    node = PlantNode(context=ros_context, parameter_overrides=overrides({'autostart': False}))
    peer = Peer(ros_context, node)
    try:
        assert peer.state() == 'active' and node.phase == IDLE and node.plant is None
        assert LIFECYCLE_SERVICES | {'~/reset'} <= own_services(node)
        peer.matched()
        answer = peer.reset()  # the graph driver's way: ~/reset starts each episode
        assert answer.success
        peer.wait_for_states(1)
        assert stamp_seconds(peer.states[0]) == 0.0
    finally:
        peer.close()
        node.destroy_node()
    node = PlantNode(context=ros_context)  # autostart: the episode waits for its peers at once
    try:
        assert node.phase == STARTING and node.active
    finally:
        node.destroy_node()
