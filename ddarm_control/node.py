"""The controller nodes: PD + gravity or computed torque on /joint_states, publishing the effort for each sample.

Two ways to sample (`sampling`): `state`, one command per stamped state of ddarm's plant in lockstep
(sample n = stamp / Δ, the reference from /reference); `timer`, a timer at 1/Δ on the node's clock
against a plant or robot the node did not start (the latest /joint_states, the reference from the
`motion` file). The commands go out as a stamped JointState (ddarm's plant) or as the bare
Float64MultiArray a ros2_control forward_command_controller on effort interfaces takes.

On a timer (robot mode) the node guards the robot as far as the URDF tells it: every effort clamped to the
joint's effort limit, a state beyond the position or velocity limits (or moving faster than they allow) refused,
and stamps and clock jumps bounded so that none blocks the commands after it (`ddarm.ros.interface.RobotLimits`).

Lifecycle (a managed node): configure reads the parameters, loads the URDF and the motion, builds and compiles the
law and makes the topics, timers and the ~/reset and ~/status services; activate lets the commands flow; deactivate
stops them (no command at all, states and ticks ignored) and the next activate starts a fresh motion; cleanup frees
it all. `autostart` (the default) configures and activates at launch, refusing the node if configure fails.
"""

from __future__ import annotations

import json
import math
import sys
from collections import deque

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidTopicNameException
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ddarm.arrays import per_joint
from ddarm.control.gains import gains_from_parameters
from ddarm.control.laws import (CONTROLLERS, GainError, Measurement, ReferencePoint, SampledController,
                                checked_delay, checked_friction, gravity_feedforward, make_law, warm_up)
from ddarm.errors import DdarmError
from ddarm.motion.files import MotionFile, load_motion, motion_of_duration
from ddarm.motion.programmed import MotionError, nominal_torque
from ddarm.physics.arm import Arm, ModelError
from ddarm.physics.dynamics import chain_from_model
from ddarm.ros.lifecycle import ManagedNode
from ddarm.ros.interface import (COMMAND_TYPES, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, GAIN_KEYS,
                                     JOINT_STATES_TOPIC, REFERENCE_QOS, REFERENCE_TOPIC, ROBOT_COMMAND_QOS,
                                     ROBOT_STATE_QOS, SAMPLE_QOS, Reference, RobotLimits, RobotState, declare_from_schema,
                                     declare_joint_gains,
                                     effort_array_msg, gain_joint, gain_parameter, given_gains, keyed_gains_given,
                                     plain_parameters, POSITIONAL_GAINS, positional_gains, positional_gains_notice,
                                     proposed_values, read_joint_state, read_reference, read_robot_state,
                                     refuse_undeclared_parameters, undeclared_overrides,
                                     unknown_parameters_reason)
from ddarm.realtime import SchedulingError
from ddarm.ros.cdr import JointStateEncoder, decode_joint_state
from ddarm.ros.executable import REFUSED, non_utf8_argument, run_node
from ddarm.ros.scheduling import NodeScheduling
from ddarm.samples import MAX_REFERENCE_POINTS, MessageError

# States that arrive before the programmed motion wait for it, up to this many.
MAX_WAITING_STATES = 10_000
SAMPLINGS = ('state', 'timer')
# Timer mode logs a recurring fault (a stale state, a refused one) at most this often, s; each is counted.
LOG_EVERY = 1.0
# Timer mode says what it waits for (a /clock, a state) this often, wall s, until the motion starts.
WATCH_EVERY = 5.0


class ControllerError(DdarmError, ValueError):
    """A controller node configuration refused at start (sampling, command interface, motion and joints)."""


def effective_gains(law: str, values: dict, model: Arm, reference: Reference | None, given: tuple):
    """K_p, K_v from the parameters (`gains_from_parameters`); None while the PD + gravity rule waits for q_f.

    `given` is (kp, kv) as the parameters give them (`given_gains`): the ω rule overrides them when omega > 0.
    """
    return gains_from_parameters(law, values['omega'], *given, model, None if reference is None else reference.q[-1])


def checked_choice(name: str, value: str, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise ControllerError(f'{name} must be one of {list(choices)}, got {value!r}')
    return value


def motion_reference(model: Arm, file: MotionFile, period: float, duration: float = 0.0) -> Reference:
    """The motion file's q^d, q̇^d, q̈^d (and P^nom) at t_j = j Δ from j = 0 to the first sample at or after T;
    `Reference.point` holds the goal after it. T need not be a whole number of periods (a waypoint's time).
    `duration` > 0 is the episode's T the gains were tuned for (a bang-bang motion stretched to it, as every
    episode stretches it: ddarm.episodes.spec.motion_of_duration); 0: the file's own."""
    motion = motion_of_duration(file, duration or file.motion.duration)
    last = math.ceil(max(duration, motion.duration) / period - 1e-9)
    if last + 1 > MAX_REFERENCE_POINTS:
        raise MotionError(f'the motion of {last + 1} samples of {period} s is more than the '
                          f'{MAX_REFERENCE_POINTS} allowed')
    times = np.arange(last + 1) * period  # each a product, never a running sum
    q, v, a = motion.sample(times)
    return Reference(times, q, v, a, nominal_torque(model, motion, times))


class ControllerNode(ManagedNode):
    """One law behind ROS: the command for sample n from the state of sample n - d and the reference at t_n.

    sampling `state`: each command is a JointState stamped with the sample it applies to, carrying
    names and effort; a state at t = 0 starts a new episode (the delay buffer is cleared), as does
    ~/reset. sampling `timer`: sample 0 is the first tick with a state, the reference is the
    `motion` file's, and a tick whose latest state is older than one period sends nothing.

    A managed node: the parameters are declared at construction (the gains by joint at configure, as the joints
    come from the motion file or the URDF), everything else is made at configure and freed at cleanup.
    """

    def __init__(self, law: str, **kwargs) -> None:
        if law not in CONTROLLERS:
            raise GainError(f'controller must be one of {CONTROLLERS}, got {law!r}')
        super().__init__(law, **kwargs)
        self.law_name = law
        self.incompatible_qos_events = 0
        self.refused_messages = 0
        # Timer mode's faults, in ~/status and on /diagnostics.
        self.counters = {'refused_states': 0, 'out_of_order_states': 0, 'future_states': 0, 'unsafe_states': 0,
                         'stale_ticks': 0, 'future_ticks': 0, 'missed_ticks': 0, 'clock_faults': 0,
                         'non_finite_commands': 0, 'clamped_commands': 0}
        self._declare_parameters()
        self.parameter_overrides = list(kwargs.get('parameter_overrides') or ())
        self.configure_error: Exception | None = None
        self.configured = False  # the parameter callbacks check and apply changes once configure built the law
        self.active = False  # commands flow only while active
        self.configurations = 0
        self.ignored_messages = 0  # states that arrived while the node was not active
        self.joints: list[str] = []
        self.known_joints: list[str] = []  # the joints the undeclared-parameter refusal names, once known
        # Counts every change of what the commands are computed from (parameters, reference, reset), so a
        # driver can tell whether anyone touched the controller while an episode ran.
        self.configuration = 0
        self.ticks = 0
        self._forget_configuration()
        refuse_undeclared_parameters(self, law, self.known_joints, self._keyed_gains, kind='controller')
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        if self.get_parameter('autostart').value:
            self.launch(ControllerError)
        else:
            # The gains by joint are declared at configure; any other name not declared is refused now.
            unknown = [name for name in undeclared_overrides(self, self.parameter_overrides)
                       if gain_joint(name) is None]
            if unknown:
                self.destroy_node()
                raise GainError(f'unknown parameters {unknown_parameters_reason(unknown, law, ())}')

    # Lifecycle ---------------------------------------------------------------------------------

    def _configure(self) -> None:
        law = self.law_name
        if self.configurations:  # configured again after a cleanup: a change a driver must be able to see
            self.configuration += 1
        self.configurations += 1
        values = proposed_values(self, ())
        # Real time against a busy core: the process's priority and cores, refused at start if the OS will not.
        self.scheduling = NodeScheduling(values)
        self.sampling = checked_choice('sampling', values['sampling'], SAMPLINGS)
        self.command_type = checked_choice('command_type', values['command_type'], COMMAND_TYPES)
        self.motion_file = load_motion(values['motion']) if values['motion'] else None
        if self.sampling == 'timer' and self.motion_file is None:
            raise ControllerError("sampling 'timer' needs a motion file (motion): the reference comes from it")
        self.model, self.joints = self._model(values)
        self.known_joints[:] = self.joints
        self.command_encoder = JointStateEncoder(self.joints)
        self.chain = chain_from_model(self.model.model)
        self._declare_gains()
        unknown = undeclared_overrides(self, self.parameter_overrides)
        if unknown:
            raise GainError(f'unknown parameters {unknown_parameters_reason(unknown, law, self.joints)}')
        values = proposed_values(self, ())
        held = [Parameter(name, value=[float(x) for x in values[name]]) for name in positional_gains(values)]
        if held and not keyed_gains_given(values):
            self.set_parameters_atomically(held)  # given at start: read as the gains by joint (_keyed_gains)
            values = proposed_values(self, ())
        self.period = values['period']
        self.max_sample_gap = values['max_sample_gap']
        self.limits = self._robot_limits(values) if self.sampling == 'timer' else None
        self._set_time_bounds(values)
        self.reference: Reference | None = None
        self.reference_gravity: np.ndarray | None = None  # Ĝ(q^d) at each reference sample, for PD + gravity
        gains = effective_gains(law, values, self.model, None, given_gains(values, self.joints))
        self.controller = SampledController(
            make_law(law, self.chain, *(gains or (np.ones(self.model.dof),) * 2), *self._friction(values)),
            checked_delay(values['delay']))
        warm_up(self.chain)
        self.gains_ready = gains is not None
        if self.sampling == 'timer':
            self._set_reference(motion_reference(self.model, self.motion_file, self.period,
                                                 self.get_parameter('duration').value))
        self.last_sample: int | None = None
        self.waiting: deque = deque(maxlen=MAX_WAITING_STATES)
        # Timer mode: the latest state, the node's time of sample 0 (ns) and the last tick's sample.
        self.latest_state: RobotState | None = None
        self.start_time: int | None = None
        self.tick_sample: int | None = None

        timer = self.sampling == 'timer'
        try:
            self.command_publisher = self.create_publisher(
                JointState if self.command_type == 'joint_state' else Float64MultiArray, values['command_topic'],
                ROBOT_COMMAND_QOS if timer else SAMPLE_QOS, event_callbacks=PublisherEventCallbacks(
                    incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        except InvalidTopicNameException as error:
            reason = str(error).splitlines()[0]  # rcl's next lines point at the character
            raise ControllerError(f'command_topic {values["command_topic"]!r} is no topic name: {reason}') from None
        # Sampled states and stamped commands cross as CDR, read and written by ddarm.ros.cdr (rclpy's conversion
        # is slower); a robot's states, at its own rate and from any DDS, as rclpy's messages.
        self.state_subscription = self.create_subscription(
            JointState, JOINT_STATES_TOPIC, self._on_robot_state if timer else self._on_state,
            ROBOT_STATE_QOS if timer else SAMPLE_QOS, raw=not timer,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.reference_subscription = None if timer else self.create_subscription(
            JointTrajectory, REFERENCE_TOPIC, self._on_reference, REFERENCE_QOS,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS) \
            if timer else None
        # On the node's clock: the wall clock, or /clock under use_sim_time.
        self.timer = self.create_timer(self.period, self._on_tick, clock=self.get_clock()) if timer else None
        # Says, on the wall clock, why a timer-mode node has not started the motion (no /clock, no state).
        self.watchdog = self.create_timer(WATCH_EVERY, self._watch, clock=Clock(clock_type=ClockType.STEADY_TIME)) \
            if timer else None
        self.reset_service = self.create_service(Trigger, '~/reset', self._on_reset)
        self.status_service = self.create_service(Trigger, '~/status', self._on_status)
        self.configured = True
        self.get_logger().info(self._describe())
        unbounded = [] if self.limits is None else [joint for joint, bound in zip(self.joints, self.limits.velocity)
                                                    if bound == math.inf]
        if unbounded:
            self.get_logger().warning(f'the URDF gives no velocity limit > 0 for {unbounded}: their states are not '
                                      'checked for velocity, nor for moves too fast between states')

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._fresh_motion()
        self.active = True
        if not self.launching:
            self.get_logger().info('activated: the commands flow, a fresh motion from the next state')
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        self._fresh_motion()
        self.configuration += 1
        self.get_logger().info('deactivated: no command until activated again (states and ticks ignored)')
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        """Back to unconfigured: the topics, timers and services made at configure destroyed, the model freed."""
        self.active = False
        self.configured = False
        self.destroy_entities('command_publisher', 'diagnostics_publisher', 'state_subscription',
                              'reference_subscription', 'timer', 'watchdog', 'reset_service', 'status_service')
        self._forget_configuration()

    def _forget_configuration(self) -> None:
        """What configure makes, unset: the node unconfigured."""
        for name in ('command_publisher', 'diagnostics_publisher', 'state_subscription', 'reference_subscription',
                     'timer', 'watchdog', 'reset_service', 'status_service', 'model', 'chain', 'controller',
                     'command_encoder', 'motion_file', 'limits', 'reference', 'reference_gravity', 'latest_state',
                     'start_time', 'tick_sample', 'last_sample'):
            setattr(self, name, None)
        self.gains_ready = False
        self.waiting = deque(maxlen=MAX_WAITING_STATES)

    def _fresh_motion(self) -> None:
        """The next command starts a new motion: the delay buffer cleared, the states held forgotten."""
        self.controller.reset()
        self.last_sample = None
        self.waiting.clear()
        self.latest_state = None
        self.start_time = self.tick_sample = None

    def _declare_parameters(self) -> None:
        declare_from_schema(self, 'controller', GainError)

    def _declare_gains(self) -> None:
        """gains.<joint>.p and gains.<joint>.d for each controlled joint: ros2_controllers' gains by joint name."""
        for joint in self.joints:
            declare_joint_gains(self, joint)

    def _model(self, values: dict) -> tuple[Arm, list[str]]:
        """The controller's model and its joints: the motion file's (the others locked), else the URDF's."""
        urdf = values['urdf'] or None
        given = list(values['joints']) if values['joints'] else None
        if self.motion_file is None:
            model = Arm.from_urdf(urdf)
            joints = given or model.joint_names
            if joints != model.joint_names:
                raise ModelError(f'joints {joints} must be the URDF joints in URDF order {model.joint_names}')
            return model, joints
        joints = list(self.motion_file.joint_names)
        if given is not None and given != joints:
            raise ControllerError(f'joints {given} disagree with the joint_names {joints} of the motion file '
                                  f'{values["motion"]}: give one of them, or the same joints in the same order')
        return Arm.from_urdf(urdf, None, joints, getattr(self.motion_file, 'locked', ())), joints

    def _keyed_gains(self, parameters: list) -> list:
        """The node holds its gains by joint (gains.<joint>.p and .d, ros2_controllers' form): a positional kp or kv
        (deprecated) set once the joints are known is read as those, with a notice, and left empty. One that cannot
        be (not a finite number > 0 per joint), or given with gains by joint in the same change, is left as it is,
        for the check to refuse naming it."""
        names = {parameter.name for parameter in parameters}
        keyed = {gain_parameter(joint, key) for joint in self.joints for key in GAIN_KEYS}
        given = positional_gains({parameter.name: parameter.value for parameter in parameters})
        positional = [parameter for parameter in parameters if parameter.name in given]
        if not self.joints or not positional or not names.isdisjoint(keyed):
            return parameters
        converted = []
        for parameter in positional:
            try:
                values = per_joint(parameter.name, parameter.value, len(self.joints), GainError, positive=True)
            except GainError:
                return parameters
            converted += [Parameter(gain_parameter(joint, POSITIONAL_GAINS[parameter.name]), value=float(value))
                          for joint, value in zip(self.joints, values)]
            converted.append(Parameter(parameter.name, Parameter.Type.DOUBLE_ARRAY, []))
            self.get_logger().warning(positional_gains_notice(parameter.name, f'{self.law_name} parameter'))
        return [parameter for parameter in parameters if parameter not in positional] + converted

    def _robot_limits(self, values: dict) -> RobotLimits:
        """The bounds of robot mode from the URDF and the parameters; ControllerError naming the joint if the
        efforts are to be clamped and a joint has no limit to clamp them to."""
        given = values['effort_limits']
        effort = None
        if values['clamp_efforts'] and given is not None and len(given):
            if len(given) != len(self.joints):
                raise ControllerError(f'effort_limits has {len(given)} values for the {len(self.joints)} joints '
                                      f'{self.joints}: give one per joint, in that order')
            effort = np.array(given, dtype=float)
            bad = {joint: value for joint, value in zip(self.joints, given) if not 0 < value < math.inf}
            if bad:
                raise ControllerError(f'effort_limits must be finite and > 0 for each joint: got {bad} '
                                      '(clamp_efforts:=false publishes the efforts unclamped)')
        elif values['clamp_efforts']:
            effort = self.model.effort_limit
            bad = {joint: value for joint, value in zip(self.joints, effort.tolist()) if not 0 < value < math.inf}
            if bad:
                raise ControllerError(f'URDF {self.model.urdf_path} gives no effort limit > 0 to clamp the efforts '
                                      f'of {sorted(bad)} to (<limit effort>: {bad}): give effort_limits, one per '
                                      f'joint of {self.joints}, or clamp_efforts:=false')
        units = tuple('m' if prismatic else 'rad' for prismatic in self.model.prismatic)
        # A <limit velocity="0"> is how some URDFs say "not given": no bound rather than every moving state refused.
        velocity = np.where(self.model.velocity_limit > 0, values['velocity_limit_factor'] * self.model.velocity_limit,
                            np.inf)
        return RobotLimits(tuple(self.joints), self.model.lower, self.model.upper, values['position_margin'],
                           velocity, effort, units)

    def _set_time_bounds(self, values: dict) -> None:
        self.max_state_lead = round(values['max_state_lead'] * 1e9)  # ns, as the stamps
        self.max_clock_jump = round(values['max_clock_jump'] * 1e9)

    def _friction(self, values: dict) -> tuple:
        return tuple(checked_friction(name, values[name] if values[name] is not None and len(values[name]) else None,
                                      self.model.dof) for name in ('viscous_friction', 'coulomb_friction'))

    def _check_parameters(self, changes) -> SetParametersResult:
        if not self.configured:  # configure checks them all
            return SetParametersResult(successful=True)
        values = proposed_values(self, changes)
        try:
            for name in positional_gains(values):  # a positional diagonal not read as gains by joint: refused naming it
                per_joint(name, values[name], len(self.joints), GainError, positive=True)
            effective_gains(self.law_name, values, self.model, self.reference, given_gains(values, self.joints))
            checked_delay(values['delay'])
            self._friction(values)
        except GainError as error:
            return SetParametersResult(successful=False, reason=str(error))
        if self.sampling == 'timer' and values['period'] != self.period:
            return SetParametersResult(successful=False, reason=f'period is the timer\'s in timer mode: fixed at '
                                                                f'{self.period} s while the node runs')
        if self.sampling == 'timer':
            try:
                self._robot_limits(values)
            except ControllerError as error:
                return SetParametersResult(successful=False, reason=str(error))
        refused = self.scheduling.refusal(values)  # last: applied once the rest is valid, nothing changed if refused
        return SetParametersResult(successful=refused is None, reason=refused or '')

    def _apply_parameters(self, changes) -> None:
        if not self.configured:  # configure reads them
            return
        values = proposed_values(self, ())
        self.period = values['period']
        self.max_sample_gap = values['max_sample_gap']
        if self.sampling == 'timer':
            self.limits = self._robot_limits(values)
        self._set_time_bounds(values)
        self._set_gains(values)
        self.controller.law = make_law(self.law_name, self.chain, self.controller.law.kp, self.controller.law.kv,
                                       *self._friction(values))
        if values['delay'] != self.controller.delay:
            self.controller.set_delay(values['delay'])
        self.configuration += 1
        self.get_logger().info(self._describe())

    def _set_gains(self, values: dict) -> None:
        gains = effective_gains(self.law_name, values, self.model, self.reference, given_gains(values, self.joints))
        if gains is not None:
            self.controller.law.set_gains(*gains)
        self.gains_ready = gains is not None

    def _set_reference(self, reference: Reference) -> None:
        self.reference = reference
        self.reference_gravity = gravity_feedforward(self.model, reference.q)
        self._set_gains(proposed_values(self, ()))

    def _describe(self) -> str:
        law = self.controller.law
        gains = dict(zip(self.joints, zip(np.round(law.kp, 6).tolist(), np.round(law.kv, 6).tolist())))
        described = (f'{self.law_name}: (kp, kv) by joint {gains}, delay {self.controller.delay} sample(s), '
                     f'period {self.period} s, sampling {self.sampling}, commands as {self.command_type} on '
                     f"{self.command_publisher.topic_name}")
        if self.limits is None:
            return described
        clamp = ('NOT clamped (clamp_efforts is false)' if self.limits.effort is None else
                 f'clamped to {dict(zip(self.joints, self.limits.effort.tolist()))}')
        return f'{described}, efforts {clamp}'

    def _incompatible_qos(self, event) -> None:
        self.incompatible_qos_events += 1
        self.get_logger().error(f'incompatible QoS with a peer (policy {event.last_policy_kind}): '
                                'samples will not flow; use the profiles of ddarm.ros.interface')

    def _on_reference(self, msg: JointTrajectory) -> None:
        try:
            reference = read_reference(msg, self.joints, self.period)
        except MessageError as error:
            self.refused_messages += 1
            self.get_logger().error(f'refused: {error}')
            return
        self._set_reference(reference)
        self.configuration += 1
        self.get_logger().info(f'reference of {len(self.reference.times)} samples; {self._describe()}')
        while self.active and self.waiting:
            self._command(self.waiting.popleft())

    def _on_reset(self, request, response):
        """Clear the delay buffer; the reply (JSON, as ~/status gives) says what the next episode will run with.

        In timer mode the state held is forgotten too: the motion starts again from its start at the next tick
        with a fresh state, whatever stamps came before.
        """
        self._fresh_motion()
        self.configuration += 1
        return self._on_status(request, response)

    def _on_status(self, request, response):
        """What the commands are computed from, changing nothing: gains, delay, reference, configuration count."""
        response.success = self.reference is not None and self.gains_ready
        law = self.controller.law
        response.message = json.dumps({
            'ready': response.success, 'kp': law.kp.tolist(), 'kv': law.kv.tolist(), 'joints': self.joints,
            'delay': self.controller.delay, 'period': self.period, 'sampling': self.sampling,
            'reference_samples': 0 if self.reference is None else len(self.reference.times),
            'reference_final': None if self.reference is None else self.reference.q[-1].tolist(),
            'sample': self.tick_sample if self.sampling == 'timer' else self.last_sample, 'ticks': self.ticks,
            'refused_messages': self.refused_messages, **self.counters,
            # Matched on this node's side of each topic: a driver waits for them before sample 0 goes out.
            'state_publishers': self.state_subscription.get_publisher_count(),
            'command_subscribers': self.command_publisher.get_subscription_count(),
            'scheduling': self.scheduling.current().report(),
            'parameters': plain_parameters(proposed_values(self, ())), 'configuration': self.configuration})
        return response

    # sampling: state ---------------------------------------------------------------------------

    def _on_state(self, data: bytes) -> None:
        if not self.active:
            self.ignored_messages += 1
            return
        try:
            state = read_joint_state(decode_joint_state(data), self.joints, self.period)
        except MessageError as error:
            self.refused_messages += 1
            self.get_logger().error(f'refused, no command sent: {error}')
            return
        expected = 0 if self.last_sample is None else self.last_sample + 1
        if state.n > expected + self.max_sample_gap:
            # Accepting it would make every real state that follows look like one from the past.
            self.refused_messages += 1
            self.get_logger().error(f'refused a state for sample {state.n}: more than max_sample_gap = '
                                    f'{self.max_sample_gap} samples after the expected sample {expected}')
            return
        if state.n == 0:
            self.controller.reset()
            self.waiting.clear()
        elif self.last_sample is not None and state.n <= self.last_sample:
            self.refused_messages += 1
            self.get_logger().error(f'refused a state for sample {state.n}: sample {self.last_sample} came already')
            return
        elif self.last_sample is not None and state.n > self.last_sample + 1:
            self.get_logger().warning(f'samples {self.last_sample + 1}..{state.n - 1} never arrived')
        self.last_sample = state.n
        if self.reference is None or not self.gains_ready:
            self.waiting.append(state)
            return
        self._command(state)

    def _command(self, state) -> None:
        torque = self._torque(state.n, state.q, state.v)
        if torque is not None:
            self._publish(torque, state.n * self.period)

    def _torque(self, n: int, q: np.ndarray, v: np.ndarray) -> np.ndarray | None:
        """The law's torque for sample n from this sample's state (delayed by the buffer); None if not finite."""
        q_ref, v_ref, a_ref = self.reference.point(n)
        gravity_ref = self.reference_gravity[min(n, len(self.reference_gravity) - 1)]
        torque = self.controller.step(Measurement(q, v, q_ref, v_ref), ReferencePoint(q_ref, v_ref, a_ref),
                                      gravity_ref)
        if not all(map(math.isfinite, torque.tolist())):  # per sample: np.isfinite costs six times as much
            self.counters['non_finite_commands'] += 1
            self.get_logger().error(f'no command for sample {n}: the law gave {torque.tolist()}')
            return None
        return torque

    def _publish(self, torque: np.ndarray, t: float) -> None:
        if not self.active:  # never a command from an inactive node
            return
        if self.command_type == 'joint_state':
            self.command_publisher.publish(self.command_encoder.encode(t, effort=torque))
        else:
            self.command_publisher.publish(effort_array_msg(torque))

    # sampling: timer ---------------------------------------------------------------------------

    def _on_robot_state(self, msg: JointState) -> None:
        """Keep the latest state of our joints (others in the message ignored); refuse one that cannot be used:
        malformed, stamped before the state held or too far ahead of the node's clock, or beyond the robot's
        limits (`RobotLimits.refusal`). A refused state is never held: the ticks go on with the state before."""
        if not self.active:
            self.ignored_messages += 1
            return
        try:
            state = read_robot_state(msg, self.joints)
        except MessageError as error:
            self._refuse('refused_states', f'refused a state ({self.counters["refused_states"] + 1} so far): {error}')
            return
        now = self.get_clock().now().nanoseconds
        self._drop_state_ahead(now)
        # Before the node's clock has a time (use_sim_time, no /clock yet) nothing is ahead of it: the tick judges.
        if now and state.stamp - now > self.max_state_lead:
            self._refuse('future_states', f'refused a state stamped {state.stamp * 1e-9:.9f} s: more than '
                                          f'max_state_lead = {self.max_state_lead * 1e-9:g} s ahead of the node\'s '
                                          f'clock, {now * 1e-9:.9f} s ({self.counters["future_states"] + 1} so far)')
            return
        if self.latest_state is not None and state.stamp < self.latest_state.stamp:
            self._refuse('out_of_order_states', f'refused a state stamped {state.stamp * 1e-9:.9f} s: before the '
                                                f'latest one, {self.latest_state.stamp * 1e-9:.9f} s '
                                                f'({self.counters["out_of_order_states"] + 1} so far)')
            return
        unsafe = self.limits.refusal(state, self.latest_state)
        if unsafe is not None:
            self._refuse('unsafe_states', f'refused a state stamped {state.stamp * 1e-9:.9f} s, no command from it: '
                                          f'{unsafe} ({self.counters["unsafe_states"] + 1} so far)')
            return
        self.latest_state = state

    def _refuse(self, counter: str, message: str) -> None:
        self.refused_messages += 1
        self.counters[counter] += 1
        self.get_logger().error(message, throttle_duration_sec=LOG_EVERY)

    def _drop_state_ahead(self, now: int) -> None:
        """Forget the state held once it is more than max_state_lead ahead of the node's clock (which went back):
        held, it would refuse every later state as out of order until the clock caught up with its stamp."""
        held = self.latest_state
        if held is not None and now and held.stamp - now > self.max_state_lead:
            self.latest_state = None
            self.counters['future_states'] += 1
            self.get_logger().warning(f'dropped the state held, stamped {held.stamp * 1e-9:.9f} s: more than '
                                      f'max_state_lead = {self.max_state_lead * 1e-9:g} s ahead of the node\'s '
                                      f'clock, {now * 1e-9:.9f} s', throttle_duration_sec=LOG_EVERY)

    def _on_tick(self) -> None:
        """One sample: the command from the latest state and the motion at t_n, n counted from the first tick
        with a fresh state. A state older than one period (or stamped more than one ahead) sends nothing.

        Between two ticks the clock moves by one period, late ticks skipped (counted as missed); when it jumps
        further than max_clock_jump, ahead or back, the motion is re-anchored: it goes on from the next sample,
        neither skipping to its end nor waiting for the clock to come back. A smaller step back sends nothing
        until the clock passes the last sample again.
        """
        now = self.get_clock().now().nanoseconds
        self.ticks += 1
        if not self.active:  # counted, nothing sent
            return
        self._drop_state_ahead(now)
        state = self.latest_state
        if state is None:
            return
        period = round(self.period * 1e9)
        age = now - state.stamp
        fresh = -period <= age <= period
        if self.start_time is None:
            if not fresh:
                self._stale(age, 'the motion waits for a fresh one')
                return
            self.start_time, self.tick_sample = now, None
            self.controller.reset()
            self.get_logger().info(f'motion starts: sample 0 at {now * 1e-9:.9f} s on the node\'s clock')
        n = round((now - self.start_time) / period)
        if self.tick_sample is not None:
            jump = (n - self.tick_sample - 1) * period  # how far the clock moved beyond one period, ns
            if abs(jump) > self.max_clock_jump:
                self.counters['clock_faults'] += 1
                n = self.tick_sample + 1
                self.start_time = now - n * period
                self.get_logger().warning(f'the node\'s clock jumped {"back" if jump < 0 else "ahead"} by '
                                          f'{abs(jump) * 1e-9:.9f} s, more than max_clock_jump = '
                                          f'{self.max_clock_jump * 1e-9:g} s: the motion goes on from sample {n}',
                                          throttle_duration_sec=LOG_EVERY)
            elif n <= self.tick_sample:
                self.counters['clock_faults'] += 1
                self.get_logger().error(f'the clock went back to sample {n} (sample {self.tick_sample} came '
                                        'already): no command until it passes it again',
                                        throttle_duration_sec=LOG_EVERY)
                return
            elif n > self.tick_sample + 1:
                self.counters['missed_ticks'] += n - self.tick_sample - 1
        self.tick_sample = n
        if not fresh:
            self._stale(age, f'no command for sample {n}')
        else:
            torque = self._torque(n, state.q, state.v)
            if torque is not None:
                self._publish(self._clamped(n, torque), now * 1e-9)
        if n == len(self.reference.times) - 1:
            self.get_logger().info(f'motion done at sample {n}: holding the goal; {json.dumps(self.counters)}')
        if n % max(1, round(1.0 / self.period)) == 0:
            self._report(n)

    def _clamped(self, n: int, torque: np.ndarray) -> np.ndarray:
        """The law's efforts within the limits (clamp_efforts); a clamp counted and logged."""
        clamped, beyond = self.limits.clamped(torque)
        if beyond:
            self.counters['clamped_commands'] += 1
            self.get_logger().warning(f'sample {n}: clamped the efforts of {beyond} to their limits (the law gave '
                                      f'{torque.tolist()}, sent {clamped.tolist()}; '
                                      f'{self.counters["clamped_commands"]} clamped so far)',
                                      throttle_duration_sec=LOG_EVERY)
        return clamped

    def _stale(self, age: int, consequence: str) -> None:
        """A tick whose latest state is more than one period old (or ahead of the node's clock): counted, logged."""
        key = 'stale_ticks' if age > 0 else 'future_ticks'
        self.counters[key] += 1
        self.get_logger().warning(
            f'{consequence}: the latest state is {abs(age) * 1e-9:.6f} s '
            f'{"old" if age > 0 else "ahead of the node clock"}, more than one period '
            f'({self.counters[key]} {key.replace("_", " ")} so far)', throttle_duration_sec=LOG_EVERY)

    def _watch(self) -> None:
        """Until the motion starts: what it waits for, every WATCH_EVERY s of wall time."""
        if self.start_time is not None or not self.active:
            return
        if self.ticks == 0 and self.get_parameter('use_sim_time').value:
            self.get_logger().warning(f'no tick in {WATCH_EVERY:g} s: use_sim_time is true and no /clock arrives')
        elif self.latest_state is None:
            self.get_logger().warning(f'waiting for a state of {self.joints} on {self.state_subscription.topic_name} '
                                      f'({self.counters["refused_states"]} refused so far)')

    def _report(self, n: int) -> None:
        """Timer mode's counters on /diagnostics, about once a second of ticks."""
        faults = sum(self.counters.values()) + self.refused_messages
        values = {'node': self.get_fully_qualified_name(), 'sample': n, 'refused_messages': self.refused_messages,
                  **self.counters}
        status = DiagnosticStatus(level=DiagnosticStatus.WARN if faults else DiagnosticStatus.OK,
                                  name=f'ddarm/{self.law_name}', hardware_id='ddarm',
                                  message=f'{faults} fault(s) so far' if faults else 'ok',
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)


def main(args=None, law: str | None = None) -> int:
    args = sys.argv if args is None else args
    if law is None:
        if (problem := non_utf8_argument(args)) is not None:  # rclpy cannot read the law's name among them
            print(f'controller: refused to start: {problem}', flush=True)
            return REFUSED
        non_ros = rclpy.utilities.remove_ros_args(args)[1:]
        if len(non_ros) != 1 or non_ros[0] not in CONTROLLERS:
            print(f'usage: controller {{{",".join(CONTROLLERS)}}} [--ros-args ...]', file=sys.stderr)
            return 2
        law = non_ros[0]
    return run_node(lambda: ControllerNode(law), law,
                    (GainError, ModelError, MotionError, ControllerError, SchedulingError), args)


def main_pd_gravity(args=None) -> int:
    return main(args, 'pd_gravity')


def main_computed_torque(args=None) -> int:
    return main(args, 'computed_torque')


if __name__ == '__main__':
    raise SystemExit(main())
