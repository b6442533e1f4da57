"""The controller node against a robot it did not start: sampling on a timer, /joint_states with other joints in
any order, the efforts as a forward_command_controller takes them, the reference from the motion file.

Time is simulated: the test publishes /clock, and each tick comes from a /clock message, so which state each
command answers is known exactly; nothing here depends on how fast the machine is.
"""

import math
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from ddarm.control.laws import Measurement, ReferencePoint, SampledController, make_law
from ddarm.motion.files import load_motion
from ddarm.physics.arm import Arm
from ddarm.physics.dynamics import chain_from_model
from ddarm_control.node import ControllerError, ControllerNode
from graph_helpers import overrides

ROOT = Path(__file__).resolve().parent.parent
UR5 = ROOT / 'config' / 'arms' / 'ur5'
URDF, MOTION = UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml'
pytestmark = pytest.mark.skipif(not URDF.is_file(), reason='config/arms/ur5 is not in the tree')
PERIOD = 10_000_000  # Δ in ns
START = 5_000_000_000  # the clock at sample 0, ns
COMMANDS = '/effort_controller/commands'
# What a robot's side uses: joint_state_broadcaster publishes reliably, forward_command_controller listens so.
SYSTEM_DEFAULT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
EXTRA = {'finger_joint': 0.3, 'left_inner_knuckle_joint': -0.1, 'right_inner_knuckle_joint': 0.1}


def stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class Robot:
    """The robot's side: /clock, /joint_states with a gripper's joints in a shuffled order, and the commands."""

    def __init__(self, context, controller, command_type):
        self.node = rclpy.create_node('robot', context=context)
        self.controller = controller
        self.clock = self.node.create_publisher(Clock, '/clock', 10)
        self.states = self.node.create_publisher(JointState, '/joint_states', SYSTEM_DEFAULT)
        self.commands = []
        message = Float64MultiArray if command_type == 'float64_multi_array' else JointState
        self.node.create_subscription(message, COMMANDS if command_type == 'float64_multi_array' else
                                      'effort_command', self.commands.append, SYSTEM_DEFAULT)
        self.executor = SingleThreadedExecutor(context=context)
        for node in (controller, self.node):
            self.executor.add_node(node)
        self.rng = np.random.default_rng(7)
        simulated = controller.get_parameter('use_sim_time').value
        self.spin_until(lambda: (self.clock.get_subscription_count() or not simulated)
                        and self.states.get_subscription_count()
                        and controller.command_publisher.get_subscription_count())

    def spin_until(self, condition, resend=None, timeout=30.0):
        """Spin until `condition`; `resend` again now and then (/clock and the state are best effort)."""
        deadline, sent = time.monotonic() + timeout, time.monotonic()
        while not condition():
            assert time.monotonic() < deadline, 'condition not met in time (a hang guard, not a timing check)'
            self.executor.spin_once(timeout_sec=0.01)
            if resend is not None and time.monotonic() - sent > 0.5:
                resend()
                sent = time.monotonic()

    def tick(self, ns: int) -> None:
        """Advance the controller's clock to `ns` (a later sample instant): its timer fires once."""
        ticks = self.controller.ticks
        self.set_clock(ns)
        self.spin_until(lambda: self.controller.ticks == ticks + 1)

    def set_clock(self, ns: int) -> None:
        def send():
            self.clock.publish(Clock(clock=stamp(ns)))
        send()
        self.spin_until(lambda: self.controller.get_clock().now().nanoseconds == ns, send)

    def wait_for_commands(self, count: int) -> None:
        self.spin_until(lambda: len(self.commands) >= count)
        assert len(self.commands) == count

    def state(self, ns: int, q: np.ndarray, v: np.ndarray, joints, drop=None) -> JointState:
        """A robot's JointState stamped `ns`: our joints and a gripper's, shuffled; the controller holds it."""
        values = {**{name: (x, dx) for name, x, dx in zip(joints, q, v)},
                  **{name: (x, float('nan')) for name, x in EXTRA.items()}}  # NaN velocity: never read
        names = [name for name in values if name != drop]
        names = [names[i] for i in self.rng.permutation(len(names))]
        msg = JointState(name=names, position=[float(values[name][0]) for name in names],
                         velocity=[float(values[name][1]) for name in names])
        msg.header.stamp = stamp(ns)
        return msg

    def send_state(self, msg: JointState) -> None:
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

        def held():
            return self.controller.latest_state is not None and self.controller.latest_state.stamp == ns
        self.states.publish(msg)
        self.spin_until(held, lambda: self.states.publish(msg))

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


def controller_node(context, law, command_type, kp, kv, delay, **extra):
    joints = list(load_motion(MOTION).joint_names)
    gains = {f'gains.{joint}.{key}': value for joint, p, d in zip(joints, kp, kv)
             for key, value in (('p', p), ('d', d))}
    return ControllerNode(law, context=context, parameter_overrides=overrides({
        'use_sim_time': True, 'sampling': 'timer', 'command_type': command_type,
        'command_topic': COMMANDS if command_type == 'float64_multi_array' else 'effort_command',
        'motion': str(MOTION), 'urdf': str(URDF), 'delay': delay, 'period': PERIOD * 1e-9,
        **gains, **extra}))


def efforts(robot, command_type, index):
    msg = robot.commands[index]
    if command_type == 'float64_multi_array':
        return np.array(msg.data)
    order = [list(msg.name).index(joint) for joint in robot.controller.joints]
    return np.array(msg.effort)[order]


@pytest.mark.parametrize('law, command_type, delay', [
    ('computed_torque', 'float64_multi_array', 1),
    ('pd_gravity', 'float64_multi_array', 0),
    ('computed_torque', 'joint_state', 2),
])
def test_timer_mode_sends_the_law_for_the_states_sent_and_the_motion(ros_context, law, command_type, delay):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    kp, kv = [400.0, 300.0, 200.0, 100.0, 50.0, 20.0], [40.0, 35.0, 28.0, 20.0, 14.0, 9.0]
    node = controller_node(ros_context, law, command_type, kp, kv, delay)
    robot = Robot(ros_context, node, command_type)
    try:
        # The law computed directly, on the model the node must have built from the URDF and the motion's joints.
        model = Arm.from_urdf(URDF, None, joints)
        expected = SampledController(make_law(law, chain_from_model(model.model), kp, kv), delay)
        # Ticks before any state send nothing and start nothing.
        robot.tick(START - 2 * PERIOD)
        robot.tick(START - PERIOD)
        assert robot.commands == [] and node.start_time is None
        samples = 105  # past T = 1 s: the goal is held
        rng = np.random.default_rng(3)
        wanted = []
        for n in range(samples):
            q_ref, v_ref, a_ref = file.motion.sample(n * PERIOD * 1e-9)
            q, v = q_ref + rng.normal(0, 0.01, 6), v_ref + rng.normal(0, 0.05, 6)
            robot.send_state(robot.state(START + n * PERIOD, q, v, joints))
            robot.tick(START + n * PERIOD)
            robot.wait_for_commands(n + 1)
            wanted.append(expected.step(Measurement(q, v, q_ref, v_ref), ReferencePoint(q_ref, v_ref, a_ref),
                                        model.gravity(q_ref)))
        assert node.tick_sample == samples - 1
        got = np.array([efforts(robot, command_type, i) for i in range(samples)])
        np.testing.assert_allclose(got, np.array(wanted), rtol=1e-12, atol=1e-9)
        if command_type == 'joint_state':
            assert [msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec for msg in robot.commands] == \
                [START + n * PERIOD for n in range(samples)]
        assert not any(node.counters.values()) and node.refused_messages == 0
    finally:
        robot.close()
        node.destroy_node()


def test_timer_mode_refuses_bad_states_and_sends_nothing_on_a_stale_one(ros_context):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    kp, kv = [225.0] * 6, [30.0] * 6
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', kp, kv, 1)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        model = Arm.from_urdf(URDF, None, joints)
        expected = SampledController(make_law('computed_torque', chain_from_model(model.model), kp, kv), 1)

        def step(n, q, v):
            q_ref, v_ref, a_ref = file.motion.sample(n * PERIOD * 1e-9)
            return expected.step(Measurement(q, v, q_ref, v_ref), ReferencePoint(q_ref, v_ref, a_ref))

        q0, v0 = file.motion.q0 + 0.01, np.full(6, 0.02)
        robot.send_state(robot.state(START, q0, v0, joints))
        robot.tick(START)
        robot.wait_for_commands(1)
        # A state without one of our joints: refused, counted, the held state unchanged.
        robot.states.publish(robot.state(START + PERIOD, q0, v0, joints, drop='elbow_joint'))
        robot.spin_until(lambda: node.counters['refused_states'] == 1)
        assert node.latest_state.stamp == START
        # A state older than the one held: refused.
        robot.states.publish(robot.state(START - PERIOD, q0, v0, joints))
        robot.spin_until(lambda: node.counters['out_of_order_states'] == 1)
        # Sample 1 still has the state of sample 0 (one period old): used; sample 3 (sample 2's tick missed)
        # finds it three periods old: stale, no command.
        robot.tick(START + PERIOD)
        robot.wait_for_commands(2)
        robot.tick(START + 3 * PERIOD)
        assert node.counters['stale_ticks'] == 1 and node.counters['missed_ticks'] == 1
        # A fresh state: commands again, the delay buffer holding the states that were used.
        q4, v4 = file.motion.q0 - 0.02, np.full(6, -0.01)
        robot.send_state(robot.state(START + 4 * PERIOD, q4, v4, joints))
        robot.tick(START + 4 * PERIOD)
        robot.wait_for_commands(3)  # exactly 3: the stale tick sent nothing
        wanted = [step(0, q0, v0), step(1, q0, v0), step(4, q4, v4)]
        np.testing.assert_allclose([msg.data for msg in robot.commands], wanted, rtol=1e-12, atol=1e-9)
    finally:
        robot.close()
        node.destroy_node()


def test_the_motion_starts_only_at_a_tick_with_a_fresh_state(ros_context):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    kp, kv = [225.0] * 6, [30.0] * 6
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', kp, kv, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0 + 0.01, np.zeros(6)
        robot.send_state(robot.state(START - 10 * PERIOD, q, v, joints))
        robot.tick(START)
        assert node.start_time is None and node.counters['stale_ticks'] == 1
        robot.send_state(robot.state(START + PERIOD, q, v, joints))
        robot.tick(START + PERIOD)
        robot.wait_for_commands(1)
        assert node.start_time == START + PERIOD and node.tick_sample == 0
        model = Arm.from_urdf(URDF, None, joints)
        law = make_law('computed_torque', chain_from_model(model.model), kp, kv)
        q_ref, v_ref, a_ref = file.motion.sample(0.0)
        np.testing.assert_allclose(robot.commands[0].data, law.torque(Measurement(q, v, q_ref, v_ref),
                                                                      ReferencePoint(q_ref, v_ref, a_ref)),
                                   rtol=1e-12, atol=1e-9)
    finally:
        robot.close()
        node.destroy_node()


def test_timer_mode_on_the_wall_clock_sends_commands(ros_context):
    """Without use_sim_time the timer runs on the wall clock: commands come while fresh states do."""
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 1,
                           use_sim_time=False)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        def publish():
            now = node.get_clock().now().nanoseconds
            robot.states.publish(robot.state(now, file.motion.q0, np.zeros(6), joints))

        deadline = time.monotonic() + 30
        while len(robot.commands) < 3:
            assert time.monotonic() < deadline, 'no commands on the wall clock'
            publish()
            robot.executor.spin_once(timeout_sec=0.001)
        assert all(len(msg.data) == 6 and np.all(np.isfinite(msg.data)) for msg in robot.commands)
    finally:
        robot.close()
        node.destroy_node()


def test_timer_mode_needs_a_motion_and_the_joints_must_agree(ros_context):
    with pytest.raises(ControllerError, match="sampling 'timer' needs a motion file"):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(
            {'sampling': 'timer', 'kp': [1.0] * 3, 'kv': [1.0] * 3}))
    with pytest.raises(ControllerError, match='disagree with the joint_names'):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(
            {'motion': str(MOTION), 'urdf': str(URDF), 'joints': ['shoulder_pan_joint'], 'kp': [1.0] * 6,
             'kv': [1.0] * 6}))
    with pytest.raises(ControllerError, match="command_type must be one of"):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(
            {'command_type': 'float64', 'kp': [1.0] * 3, 'kv': [1.0] * 3}))
    with pytest.raises(ControllerError, match="command_topic 'bad topic' is no topic name: Invalid topic name"):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(
            {'command_topic': 'bad topic', 'kp': [1.0] * 3, 'kv': [1.0] * 3}))
    with pytest.raises(ControllerError, match="sampling must be one of"):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(
            {'sampling': 'wall', 'kp': [1.0] * 3, 'kv': [1.0] * 3}))


def test_the_period_is_fixed_in_timer_mode(ros_context):
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 1)
    try:
        result = node.set_parameters([rclpy.parameter.Parameter('period', value=0.02)])[0]
        assert not result.successful and 'fixed' in result.reason
        assert node.set_parameters([rclpy.parameter.Parameter('delay', value=2)])[0].successful
    finally:
        node.destroy_node()


# The safety layer of robot mode: the UR5's <limit effort> (N m) and <limit velocity> (rad/s).
UR5_EFFORT = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])
FAR_FUTURE = (2**31 - 1) * 1_000_000_000  # ns: the largest stamp a builtin_interfaces/Time holds


def refuse(robot, msg, counter):
    """Publish a state the controller must refuse: wait until `counter` counts it."""
    before = robot.controller.counters[counter]
    robot.states.publish(msg)
    robot.spin_until(lambda: robot.controller.counters[counter] > before, lambda: robot.states.publish(msg))


def law_at(law, file, n, q, v):
    q_ref, v_ref, a_ref = file.motion.sample(n * PERIOD * 1e-9)
    return law.torque(Measurement(q, v, q_ref, v_ref), ReferencePoint(q_ref, v_ref, a_ref))


def ur5_law(file, kp, kv):
    return make_law('computed_torque', chain_from_model(Arm.from_urdf(URDF, None, file.joint_names).model), kp, kv)


@pytest.mark.parametrize('ahead', [PERIOD * 11, 60 * 10**9, FAR_FUTURE - START])
def test_a_state_stamped_ahead_of_the_clock_is_refused_and_the_next_sane_one_commands(ros_context, ahead):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0, np.zeros(6)
        robot.tick(START)
        refuse(robot, robot.state(START + ahead, q, v, joints), 'future_states')
        assert node.latest_state is None
        robot.send_state(robot.state(START + PERIOD, q, v, joints))
        robot.tick(START + PERIOD)
        robot.wait_for_commands(1)
        np.testing.assert_allclose(robot.commands[0].data, law_at(ur5_law(file, [225.0] * 6, [30.0] * 6), file,
                                                                  0, q, v), rtol=1e-12, atol=1e-9)
    finally:
        robot.close()
        node.destroy_node()


def test_after_the_clock_goes_back_the_state_held_is_dropped_and_the_motion_goes_on(ros_context):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0 + 0.01, np.zeros(6)
        for n in range(2):
            robot.send_state(robot.state(START + n * PERIOD, q, v, joints))
            robot.tick(START + n * PERIOD)
        robot.wait_for_commands(2)
        back = START - 3_000_000_000  # a simulation restarted: /clock and the states 3 s back
        robot.set_clock(back)  # no tick: after a jump back, rcl's timer counts its period from there
        robot.tick(back + PERIOD)
        assert node.latest_state is None and node.counters['future_states'] == 1
        robot.send_state(robot.state(back + 2 * PERIOD, q, v, joints))
        robot.tick(back + 2 * PERIOD)
        robot.wait_for_commands(3)
        assert node.tick_sample == 2 and node.counters['clock_faults'] == 1 and node.counters['missed_ticks'] == 0
        np.testing.assert_allclose(robot.commands[2].data, law_at(ur5_law(file, [225.0] * 6, [30.0] * 6), file,
                                                                  2, q, v), rtol=1e-12, atol=1e-9)
        assert node.counters['out_of_order_states'] == 0
    finally:
        robot.close()
        node.destroy_node()


def test_a_clock_jump_ahead_beyond_the_bound_re_anchors_and_one_within_it_skips(ros_context):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0, np.zeros(6)
        for now in (START, START + PERIOD):
            robot.send_state(robot.state(now, q, v, joints))
            robot.tick(now)
        later = START + 10 * 10**9
        robot.tick(later)  # 10 s ahead: sample 2, not sample 1000 (the goal); the state held is stale
        assert node.tick_sample == 2 and node.counters['clock_faults'] == 1 and node.counters['stale_ticks'] == 1
        for now in (later + PERIOD, later + 4 * PERIOD):  # then 3 periods: sample 6, 2 ticks missed
            robot.send_state(robot.state(now, q, v, joints))
            robot.tick(now)
        robot.wait_for_commands(4)
        assert node.tick_sample == 6 and node.counters['clock_faults'] == 1 and node.counters['missed_ticks'] == 2
        law = ur5_law(file, [225.0] * 6, [30.0] * 6)
        np.testing.assert_allclose([msg.data for msg in robot.commands], [law_at(law, file, n, q, v)
                                                                          for n in (0, 1, 3, 6)],
                                   rtol=1e-12, atol=1e-9)
    finally:
        robot.close()
        node.destroy_node()


@pytest.mark.parametrize('joint, position, velocity', [
    (1, 1e300, 0.0),  # far outside shoulder_lift's ±2π
    (2, math.pi + 0.11, 0.0),  # just beyond the elbow's ±π by more than the margin of 0.1 rad
    (3, -1.9708 + 1.0, 0.0),  # 1 rad in one period: no velocity within 2 × 3.2 rad/s moves that far
    (0, -0.5, 50.0),  # 50 rad/s: beyond 2 × 3.15 rad/s
    (4, -1.5708, -1e300),
])
def test_a_state_beyond_the_limits_is_refused_and_sends_no_command(ros_context, capfd, joint, position, velocity):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0.copy(), np.zeros(6)
        robot.send_state(robot.state(START, q, v, joints))
        robot.tick(START)
        robot.wait_for_commands(1)
        bad_q, bad_v = q.copy(), v.copy()
        bad_q[joint], bad_v[joint] = position, velocity
        capfd.readouterr()
        refuse(robot, robot.state(START + PERIOD, bad_q, bad_v, joints), 'unsafe_states')
        assert node.latest_state.stamp == START
        logged = capfd.readouterr().err
        assert f'refused a state stamped 5.010000000 s, no command from it: {joints[joint]} ' in logged, logged
        robot.tick(START + 2 * PERIOD)  # the state held is two periods old: nothing for this sample
        assert node.counters['stale_ticks'] == 1 and len(robot.commands) == 1
        robot.send_state(robot.state(START + 3 * PERIOD, q, v, joints))
        robot.tick(START + 3 * PERIOD)
        robot.wait_for_commands(2)
    finally:
        robot.close()
        node.destroy_node()


def test_a_move_refused_as_too_fast_is_taken_once_the_time_since_allows_it(ros_context):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0.copy(), np.zeros(6)
        robot.send_state(robot.state(START, q, v, joints))
        moved = q + np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
        refuse(robot, robot.state(START + PERIOD, moved, v, joints), 'unsafe_states')
        robot.send_state(robot.state(START + 20 * PERIOD, moved, v, joints))  # 0.2 s: 2 × 3.2 × 0.2 + 0.1 > 1
        assert node.latest_state.stamp == START + 20 * PERIOD and node.counters['unsafe_states'] == 1
    finally:
        robot.close()
        node.destroy_node()


def test_a_continuous_joint_has_no_position_limit(ros_context, tmp_path):
    urdf = tmp_path / 'ur5-continuous-pan.urdf'
    text = URDF.read_text()
    pan = '<joint name="shoulder_pan_joint" type="revolute">'
    assert pan in text
    urdf.write_text(text.replace(pan, '<joint name="shoulder_pan_joint" type="continuous">'))
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0,
                           urdf=str(urdf))
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q = file.motion.q0 + np.array([50.0, 0, 0, 0, 0, 0])  # 8 turns on: a continuous joint's angle
        robot.send_state(robot.state(START, q, np.zeros(6), joints))
        robot.tick(START)
        robot.wait_for_commands(1)
        assert np.all(np.abs(robot.commands[0].data) <= UR5_EFFORT)
    finally:
        robot.close()
        node.destroy_node()


@pytest.mark.parametrize('extra, limits', [
    ({}, UR5_EFFORT),
    ({'effort_limits': [10.0, 20.0, 30.0, 4.0, 5.0, 6.0]}, np.array([10.0, 20.0, 30.0, 4.0, 5.0, 6.0])),
    ({'clamp_efforts': False}, None),
])
def test_efforts_are_clamped_to_the_urdf_limits_unless_told_otherwise(ros_context, extra, limits):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    kp, kv = [2500.0] * 6, [100.0] * 6
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', kp, kv, 0, **extra)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0 + 0.5, np.zeros(6)  # half a radian off on every joint, within its limits
        robot.send_state(robot.state(START, q, v, joints))
        robot.tick(START)
        robot.wait_for_commands(1)
        law = law_at(ur5_law(file, kp, kv), file, 0, q, v)
        assert np.any(np.abs(law) > UR5_EFFORT)
        wanted = law if limits is None else np.clip(law, -limits, limits)
        np.testing.assert_allclose(robot.commands[0].data, wanted, rtol=1e-12, atol=1e-9)
        assert node.counters['clamped_commands'] == (0 if limits is None else 1)
    finally:
        robot.close()
        node.destroy_node()


def test_effort_limits_that_cannot_be_clamped_to_are_refused_naming_the_joint(ros_context, tmp_path):
    with pytest.raises(ControllerError, match=r'effort_limits has 2 values for the 6 joints'):
        controller_node(ros_context, 'computed_torque', 'float64_multi_array', [1.0] * 6, [1.0] * 6, 0,
                        effort_limits=[1.0, 2.0])
    with pytest.raises(ControllerError, match=r"effort_limits must be finite and > 0 for each joint: got "
                                              r"\{'elbow_joint': 0.0\}"):
        controller_node(ros_context, 'computed_torque', 'float64_multi_array', [1.0] * 6, [1.0] * 6, 0,
                        effort_limits=[1.0, 1.0, 0.0, 1.0, 1.0, 1.0])
    urdf = tmp_path / 'ur5-wrists-of-no-effort.urdf'
    limit = '<limit effort="28.0" lower="-6.28318530718" upper="6.28318530718" velocity="3.2" />'
    assert URDF.read_text().count(limit) == 3
    urdf.write_text(URDF.read_text().replace(limit, limit.replace('28.0', '0.0')))
    with pytest.raises(ControllerError, match=r"gives no effort limit > 0 to clamp the efforts of "
                                              r"\['wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint'\]"):
        controller_node(ros_context, 'computed_torque', 'float64_multi_array', [1.0] * 6, [1.0] * 6, 0,
                        urdf=str(urdf))
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [1.0] * 6, [1.0] * 6, 0,
                           urdf=str(urdf), effort_limits=[150.0] * 3 + [28.0] * 3)
    try:
        result = node.set_parameters([rclpy.parameter.Parameter('effort_limits', value=[-1.0] * 6)])[0]
        assert not result.successful and "'shoulder_pan_joint': -1.0" in result.reason
        result = node.set_parameters([rclpy.parameter.Parameter('effort_limits', value=[5.0] * 6)])[0]
        assert result.successful and node.limits.effort.tolist() == [5.0] * 6
    finally:
        node.destroy_node()


def test_reset_forgets_the_state_held(ros_context):
    file = load_motion(MOTION)
    joints = list(file.joint_names)
    node = controller_node(ros_context, 'computed_torque', 'float64_multi_array', [225.0] * 6, [30.0] * 6, 0)
    robot = Robot(ros_context, node, 'float64_multi_array')
    try:
        q, v = file.motion.q0, np.zeros(6)
        for n in range(2):
            robot.send_state(robot.state(START + n * PERIOD, q, v, joints))
            robot.tick(START + n * PERIOD)
        robot.wait_for_commands(2)
        node._on_reset(Trigger.Request(), Trigger.Response())
        robot.tick(START + 2 * PERIOD)  # the state of sample 1 is fresh still, but forgotten: no start
        assert len(robot.commands) == 2 and node.start_time is None
        robot.send_state(robot.state(START, q, v, joints))  # before the one forgotten: taken
        robot.send_state(robot.state(START + 3 * PERIOD, q, v, joints))
        robot.tick(START + 3 * PERIOD)
        robot.wait_for_commands(3)
        assert node.tick_sample == 0 and node.counters['out_of_order_states'] == 0
    finally:
        robot.close()
        node.destroy_node()
