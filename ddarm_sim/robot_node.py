"""The robot node: a MuJoCo robot behind ros2_control's topics, as a managed (lifecycle) node.

It behaves as a robot running ros2_control does from outside: a joint state broadcaster's
`sensor_msgs/JointState` (position, velocity, effort) on /joint_states, and an effort
forward_command_controller's `std_msgs/Float64MultiArray` on `command_topic`, its efforts in the order of
`joints`. `mode` realtime runs free on the wall clock at `rate`, holding the effort in force; lockstep integrates
one period per command and publishes /clock, for exact and fast runs of a controller on use_sim_time. What a real
robot adds (noise, latency, a command watchdog) is `ddarm.physics.simulated_robot`; this node turns messages and
parameters into its calls.

Lifecycle: configure loads the MJCF, activate starts publishing (and integrating), deactivate stops both (the
robot holds its state), cleanup frees the robot. `autostart` (the default) configures and activates at launch.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidTopicNameException
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from ddarm.arrays import per_joint
from ddarm.physics.mujoco_plant import RobotError, load_robot, robot_joints, warm_up
from ddarm.physics.simulated_robot import Realism, RealismError, SimulatedRobot
from ddarm.realtime import SchedulingError, TickThread, period_ns
from ddarm.ros.cdr import JointStateEncoder, Stamp, encode_clock, stamp_of_ns
from ddarm.ros.executable import run_node
from ddarm.ros.lifecycle import ManagedNode
from ddarm.ros.interface import (CLOCK_QOS, CLOCK_TOPIC, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, JOINT_STATES_TOPIC,
                                 ROBOT_COMMAND_QOS, SAMPLE_QOS, declare_from_schema, proposed_values,
                                 refuse_undeclared_parameters, time_msg, undeclared_overrides)

MODES = ('realtime', 'lockstep')
# The command in force over each period, stamped at the period's start: the evidence of what the robot was asked
# for at each sample (a Float64MultiArray carries no stamp), recorded and scored as a plant's commands are.
COMMANDED_EFFORT_TOPIC = '~/commanded_effort'
WATCHDOG_PERIOD = 0.05  # wall s between checks of start-up and, in lockstep, of the command timeout
# Lockstep, before the first command: sample 0 is published again one period later this often (wall s). A
# controller on /clock ticks only when the clock moves, and its first tick may have come before its first state.
# Not sooner: a retry moves the clock, so a command already on its way for the earlier sample 0 would be taken
# for sample 0 and the controller's next for sample 1 (seen once in a loaded test run at 0.1 s: sample 1's command
# went missing).
START_RETRY = 0.5
# Lockstep: the robot's time of the first sample, in periods. Not 0: a node on use_sim_time reads 0 as "no time".
FIRST_SAMPLE = 1
LOG_EVERY = 1.0  # s: a recurring fault (a refused command) is logged at most this often; each is counted
IDLE, STARTING, RUNNING, ENDED = 'idle', 'starting', 'running', 'ended'


class RobotNodeError(RobotError):
    """A robot node configuration refused (joints, start state, realism)."""


def robot_joint_order(path: str, joints: list[str]) -> tuple[tuple[str, ...], tuple[bool, ...]]:
    """The commanded joints (`joints`, else every hinge and slide joint of the MJCF) and whether each is a slide;
    RobotNodeError naming the joints the MJCF lacks, or the MJCF's joints left out."""
    theirs = robot_joints(path)
    if not joints:
        return tuple(theirs), tuple(theirs.values())
    missing = [name for name in joints if name not in theirs]
    if missing:
        raise RobotNodeError(f'joints names {missing}, which the MJCF {path} does not have (its joints: '
                             f'{list(theirs)})')
    repeated = sorted({name for name in joints if joints.count(name) > 1})
    if repeated:
        raise RobotNodeError(f'joints names {repeated} more than once')
    left_out = [name for name in theirs if name not in joints]
    if left_out:
        raise RobotNodeError(f'joints leaves out {left_out} of the MJCF {path}: every joint of the robot takes '
                             'an effort, so name each once, in the order of the commands')
    return tuple(joints), tuple(theirs[name] for name in joints)


class RobotNode(ManagedNode):
    """A MuJoCo robot publishing its joint states and taking effort commands, managed by the lifecycle.

    realtime: a thread of its own ticks at t0 + kΔ on the wall clock (Δ = 1/rate), holds the effort in force over
    the period and publishes the state, stamped with the node's clock. lockstep: the state of t_n and /clock t_n go
    out, and [t_n, t_{n+1}) is integrated when the next command arrives; a command missing for `command_timeout`
    wall seconds zeroes the efforts for that period (said, counted), so that the clock, and the controller, go on.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('robot', **kwargs)
        self._declare_parameters()
        refuse_undeclared_parameters(self, 'robot')
        unknown = undeclared_overrides(self, kwargs.get('parameter_overrides') or ())
        if unknown:
            raise RobotNodeError(f'unknown parameters {unknown} (not robot parameters: a typo?)')
        self.lock = threading.Lock()  # the real-time ticks and the executor's callbacks share the robot
        self.robot: SimulatedRobot | None = None
        self.phase = IDLE
        self.ticks = TickThread('robot-ticks', self._realtime_tick, self._ticks_failed)
        self.sample = 0
        self.first_sample = FIRST_SAMPLE
        self.start_ns = 0  # realtime: the node's clock at sample 0 of the robot's ticks
        self.late_periods = 0  # realtime: periods whose tick came late, integrated at the next
        self.deadline = 0.0
        self.status_service = self.create_service(Trigger, '~/status', self._on_status)
        if self.get_parameter('autostart').value:
            self.launch(RobotNodeError)

    def _declare_parameters(self) -> None:
        declare_from_schema(self, 'robot', RobotNodeError)

    # Lifecycle ---------------------------------------------------------------------------------

    def _configure(self) -> None:
        values = proposed_values(self, ())
        if not values['mjcf']:
            raise RobotNodeError('mjcf is not set: give the MuJoCo robot (-p mjcf:=FILE)')
        if values['mode'] not in MODES:
            raise RobotNodeError(f"mode must be one of {list(MODES)}, got {values['mode']!r}")
        self.mode = values['mode']
        self.period = 1.0 / values['rate']
        joints, prismatic = robot_joint_order(values['mjcf'], list(values['joints'] or []))
        robot = load_robot(values['mjcf'], joints, prismatic, self.period)
        warm_up()
        for warning in robot.warnings():
            self.get_logger().warning(warning)
        latency = values['command_latency']
        if self.mode == 'lockstep' and abs(latency / self.period - round(latency / self.period)) > 1e-9:
            raise RobotNodeError(f'command_latency = {latency} s is not a whole number of periods of {self.period} '
                                 's: in lockstep a command waits whole periods')
        # In lockstep the wall clock judges the timeout (the watchdog), not the robot's time.
        self.realism = Realism(values['position_noise'], values['velocity_noise'], values['noise_seed'], latency,
                               values['command_timeout'] if self.mode == 'realtime' else 0.0,
                               values['hold_until_commanded'])
        self.command_timeout = values['command_timeout']
        self.required_subscribers = values['required_subscribers']
        self.model = robot
        self.joints = joints
        self.start_state(values)  # checked now, taken again at each activation
        self.encoder = JointStateEncoder(joints)
        try:
            self.command_subscription = self.create_subscription(
                Float64MultiArray, values['command_topic'], self._on_command, ROBOT_COMMAND_QOS)
        except InvalidTopicNameException as error:
            raise RobotNodeError(f'command_topic {values["command_topic"]!r} is no topic name: '
                                 f'{str(error).splitlines()[0]}') from None
        # Reliable, deep: a recorder keeps every sample, and a best-effort subscriber (a controller's) still matches.
        self.state_publisher = self.create_publisher(JointState, JOINT_STATES_TOPIC, SAMPLE_QOS)
        self.commanded_publisher = self.create_publisher(JointState, COMMANDED_EFFORT_TOPIC, SAMPLE_QOS)
        self.clock_publisher = self.create_publisher(ClockMsg, CLOCK_TOPIC, CLOCK_QOS) \
            if self.mode == 'lockstep' else None
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS)
        self.watchdog = self.create_timer(WATCHDOG_PERIOD, self._locked(self._watch),
                                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'robot {values["mjcf"]}: joints {list(joints)}, {self.mode} at {values["rate"]:g} '
                               f'Hz, commands on {self.command_subscription.topic_name}')

    def start_state(self, values: dict) -> tuple[np.ndarray, np.ndarray]:
        """q, q̇ at activation: initial_position (else the MJCF's qpos0) and initial_velocity (else zero)."""
        dof = len(self.joints)
        given = {name: values[name] for name in ('initial_position', 'initial_velocity')
                 if values[name] is not None and len(values[name])}
        q = (per_joint('initial_position', given['initial_position'], dof, RobotNodeError)
             if 'initial_position' in given else self.model.model.qpos0[self.model.qpos_address].copy())
        v = (per_joint('initial_velocity', given['initial_velocity'], dof, RobotNodeError)
             if 'initial_velocity' in given else np.zeros(dof))
        return q, v

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            q, v = self.start_state(proposed_values(self, ()))
        except RobotNodeError as error:
            self.get_logger().error(f'activate refused: {error}')
            return TransitionCallbackReturn.FAILURE
        with self.lock:
            self.robot = SimulatedRobot(self.model, q, v, self.realism)
            self.sample, self.first_sample, self.late_periods = 0, FIRST_SAMPLE, 0
            self.phase = STARTING
            if self.mode == 'realtime':
                self._begin()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_ticks()
        with self.lock:
            self.phase = IDLE
        self.get_logger().info(f'deactivated at sample {self.sample}: no more states, commands ignored')
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        """Back to unconfigured: the ticks stopped, the topics and timer made at configure destroyed, the robot freed."""
        self._stop_ticks()  # no tick may publish on a destroyed publisher
        with self.lock:
            self.phase = IDLE
            self.robot = None
            self.destroy_entities('command_subscription', 'state_publisher', 'commanded_publisher', 'clock_publisher',
                                  'diagnostics_publisher', 'watchdog')

    def destroy_node(self) -> None:
        self._stop_ticks()  # no tick may publish on a destroyed publisher
        super().destroy_node()

    # Samples -----------------------------------------------------------------------------------

    def _locked(self, callback):
        def locked(*args):
            with self.lock:
                return callback(*args)
        return locked

    def _stamp(self, sample: int) -> Stamp:
        """The stamp of a sample: lockstep, the robot's own time (sample 0 at `first_sample` periods); realtime, its
        tick on the node's clock, t0 + nΔ (a robot stamps by its control cycle), exact in integer nanoseconds."""
        if self.mode == 'lockstep':
            return stamp_of_ns(round((self.first_sample + sample) * self.period * 1e9))
        return stamp_of_ns(self.start_ns + sample * period_ns(self.period))

    def _time(self) -> float:
        """The time of the current sample, s."""
        stamp = self._stamp(self.sample)
        return stamp.sec + stamp.nanosec * 1e-9

    def _publish_state(self) -> None:
        stamp = self._stamp(self.sample)
        q, v = self.robot.measured()
        self.state_publisher.publish(self.encoder.encode(stamp, q, v, self.robot.applied))
        if self.clock_publisher is not None:
            self.clock_publisher.publish(encode_clock(stamp))

    def _begin(self) -> None:
        self.phase = RUNNING
        now = time.monotonic_ns()
        self.deadline = time.monotonic() + START_RETRY
        if self.mode == 'lockstep':
            self._publish_state()
            return
        self.start_ns = self.get_clock().now().nanoseconds
        self._publish_state()
        self._integrate(now * 1e-9)  # period 0, under the effort in force at the start (none yet): out at tick 1
        self.ticks.start(now, period_ns(self.period))

    def _ticks_failed(self, error: Exception) -> None:
        if self.context.ok():
            self.get_logger().error(f'the real-time ticks stopped: {type(error).__name__}: {error}')

    def _stop_ticks(self) -> None:
        self.ticks.stop()

    def _realtime_tick(self, index: int, deadline: int) -> bool:
        """Tick `index`, due at `deadline` (ns), as a robot's control cycle runs: the state of this sample goes out,
        then the effort in force now is held over the next period (integrated now, published at the next tick).
        The robot's time goes on whether or not a tick comes on time: the periods of ticks skipped are integrated
        first, each under the effort in force at its start, and counted as late."""
        with self.lock:
            if self.phase != RUNNING:
                return False
            was_timed_out = self.robot.timed_out
            period = period_ns(self.period)
            self.late_periods += max(0, index - self.sample)
            while self.phase == RUNNING and self.sample < index:
                self._publish_state()  # a skipped tick's state, late, stamped at its sample: the robot went through it
                self._integrate((deadline - (index - self.sample) * period) * 1e-9)
            if self.phase == RUNNING:
                self._publish_state()
                self._integrate(deadline * 1e-9)
            if self.robot is not None and self.robot.timed_out and not was_timed_out:
                self._say_timeout(f'no command for more than command_timeout = {self.command_timeout} s')
            return self.phase == RUNNING

    def _integrate(self, now: float) -> None:
        """Hold the effort in force at `now` over the current sample's period (its command, if it is one, published
        stamped at the period's start): the robot moves on to the next sample."""
        moved = self.robot.step(now)
        if self.robot.commanded:
            self.commanded_publisher.publish(self.encoder.encode(self._stamp(self.sample), effort=self.robot.effort))
        if not moved:
            self.phase = ENDED
            self._report(DiagnosticStatus.ERROR, 'diverged', f'diverged during sample {self.sample}: the robot is '
                         'frozen (deactivate and activate to start again)')
            self.get_logger().error(f'diverged during sample {self.sample}: the robot is frozen')
            return
        self.sample += 1
        if self.sample % max(1, round(1.0 / self.period)) == 0:
            self._report(DiagnosticStatus.WARN if self.robot.counters['refused_commands']
                         or self.robot.counters['timeouts'] or self.late_periods else DiagnosticStatus.OK,
                         'running', 'running')

    def _step_and_publish(self, now: float) -> None:
        """Lockstep: integrate the current period, then publish the state it ends in (and /clock)."""
        self._integrate(now)
        if self.phase == RUNNING:
            self._publish_state()

    def _on_command(self, msg: Float64MultiArray) -> None:
        with self.lock:
            if self.phase != RUNNING:
                return
            lockstep = self.mode == 'lockstep'
            now = self._time() if lockstep else time.monotonic()
            refused = self.robot.receive(msg.data, now)
            if refused is not None:
                self.get_logger().error(f'refused {refused}; the command in force is held '
                                        f'({self.robot.counters["refused_commands"]} refused so far)',
                                        throttle_duration_sec=LOG_EVERY)
            if lockstep:
                self._step_and_publish(now)
                self.deadline = time.monotonic() + self.command_timeout

    def _watch(self) -> None:
        now = time.monotonic()
        if self.mode != 'lockstep' or self.robot is None:
            return
        if self.phase == STARTING:
            if (self.state_publisher.get_subscription_count() >= self.required_subscribers
                    and self.clock_publisher.get_subscription_count() >= 1
                    and self.command_subscription.get_publisher_count() >= 1):
                self._begin()
        elif self.phase == RUNNING and now > self.deadline:
            if self.sample == 0 and self.robot.counters['commands'] + self.robot.counters['refused_commands'] == 0:
                self.first_sample += 1
                self._publish_state()
                self.deadline = now + START_RETRY
            elif self.command_timeout > 0:
                self.robot.time_out()
                self._say_timeout(f'no command for sample {self.sample} within command_timeout = '
                                  f'{self.command_timeout} s: the period runs with zero efforts')
                self._step_and_publish(self._time())
                self.deadline = now + self.command_timeout

    def _say_timeout(self, message: str) -> None:
        self.get_logger().warning(f'{message} ({self.robot.counters["timeouts"]} time(s) so far)',
                                  throttle_duration_sec=LOG_EVERY)
        self._report(DiagnosticStatus.WARN, 'timeout', message)

    def _report(self, level: bytes, event: str, message: str) -> None:
        """The robot's counters on /diagnostics: about once a second of samples, and at each fault."""
        values = {'event': event, 'node': self.get_fully_qualified_name(), 'mode': self.mode, 'sample': self.sample,
                  'late_periods': self.late_periods, **self.robot.counters}
        status = DiagnosticStatus(level=level, name='ddarm/robot', message=message, hardware_id='ddarm',
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = time_msg(self._time())
        self.diagnostics_publisher.publish(array)

    def _on_status(self, request, response):
        """The lifecycle state, the sample and the counters, as JSON."""
        with self.lock:
            robot = self.robot
            response.success = robot is not None and self.phase == RUNNING
            response.message = json.dumps({
                'state': self._state_machine.current_state[1], 'phase': self.phase, 'sample': self.sample,
                'time': self._time() if robot is not None else None,
                'timed_out': robot is not None and robot.timed_out, 'late_periods': self.late_periods,
                **(robot.counters if robot is not None else {})})
        return response


def main(args=None) -> int:
    return run_node(RobotNode, 'robot', (RobotError, RealismError, SchedulingError), args)


if __name__ == '__main__':
    raise SystemExit(main())
