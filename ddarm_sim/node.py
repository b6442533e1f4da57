"""The plant node: the simulated arm behind /joint_states, stepped in lockstep with its controller or in real time."""

from __future__ import annotations

import gc
import json
import threading
import time
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from ddarm.episodes.spec import ROBOT_EXCLUDED, read_motion_file
from ddarm.motion.files import motion_of_duration
from ddarm.physics.arm import Arm, ModelError
from ddarm.physics.dynamics import chain_from_model
from ddarm.physics.mujoco_plant import MujocoPlant, Robot, RobotError, at_period, load_robot
from ddarm.physics.plant import (Plant, PlantError, PlantOptions,
                                 checked_mass_scale, warm_up)
from ddarm.realtime import SchedulingError, TickThread, period_ns
from ddarm.ros.interface import (CLOCK_QOS, CLOCK_TOPIC, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC,
                                     EFFORT_COMMAND_TOPIC, JOINT_STATES_TOPIC, SAMPLE_QOS,
                                     declare_from_schema, plain_parameters, proposed_values,
                                     read_joint_state, refuse_undeclared_parameters, time_msg,
                                     undeclared_overrides)
from ddarm.ros.cdr import JointStateEncoder, decode_joint_state, encode_clock
from ddarm.ros.executable import run_node
from ddarm.ros.lifecycle import ManagedNode
from ddarm.ros.scheduling import NodeScheduling
from ddarm.ros.parameter_schema import DEFAULT_SPIN_MARGIN
from ddarm.samples import MessageError
from ddarm.arrays import per_joint
from ddarm.motion.programmed import PAPER_TRAJECTORIES, MotionError, disturbed_start

MODES = ('lockstep', 'realtime')
WATCHDOG_PERIOD = 0.05  # s
IDLE, STARTING, RUNNING, ENDED = 'idle', 'starting', 'running', 'ended'


@dataclass(frozen=True)
class PlantSettings:
    """The plant node's parameters, checked together: what the next episode runs with."""

    mode: str
    period: float
    command_timeout: float
    required_subscribers: int
    required_clock_subscribers: int
    max_samples: int
    options: PlantOptions
    mass_scale: tuple | None
    q0: np.ndarray
    v0: np.ndarray
    spin_margin: float = DEFAULT_SPIN_MARGIN
    robot: Robot | None = None  # the MuJoCo robot stepped instead of ddarm's plant, at `period`


def _optional_array(values) -> np.ndarray | None:
    return None if values is None or len(values) == 0 else np.array(values, dtype=float)


def _motion_problem(values: dict, error: Exception) -> PlantError:
    """A problem of the motion file, naming the parameter and the file."""
    return PlantError(f"parameter motion = {values['motion']!r}: {error}")


# The joints a motion file controls and the ones it locks (name, position): what the plant's arm was reduced by.
Reduction = tuple[tuple[str, ...], tuple[tuple[str, float], ...]]


def plant_arm(values: dict) -> tuple[Arm, Reduction | None]:
    """The arm the plant integrates, and the motion file's joints it was reduced by (None: every movable joint).

    With a `motion`, the URDF is reduced to the file's joints, every other movable joint locked
    where the file says (at 0 otherwise), as `ddarm.episodes.spec.plant_arm` reduces it; without
    one, the arm has every movable joint of the URDF.
    """
    urdf = values['urdf'] or None
    if not values['motion']:
        return Arm.from_urdf(urdf), None
    try:
        file = read_motion_file(values['motion'])
        reduction = file.joint_names, file.locked
        return Arm.from_urdf(urdf, None, *reduction), reduction
    except (MotionError, ModelError) as error:
        raise _motion_problem(values, error) from error


def start_state(values: dict, arm: Arm, reduced_by: Reduction | None) -> tuple[np.ndarray, np.ndarray]:
    """q(0), q̇(0): initial_position/initial_velocity (trajectory 0), else (3.1) against the motion file's
    q^d (`motion`) or the paper trajectory's (`trajectory`), a bang-bang motion stretched to `duration`."""
    dof = arm.dof
    trajectory = values['trajectory']
    if trajectory == 0:
        return tuple(np.zeros(dof) if _optional_array(values[name]) is None
                     else per_joint(name, values[name], dof, PlantError)
                     for name in ('initial_position', 'initial_velocity'))
    if not values['motion'] and trajectory not in PAPER_TRAJECTORIES:
        raise PlantError(f'trajectory must be 0 (initial_position) or one of {list(PAPER_TRAJECTORIES)}')
    try:
        file = read_motion_file(values['motion'] or None, trajectory)
        if reduced_by is not None:
            joints, locked = file.joint_names, file.locked
            if (joints, locked) != reduced_by:
                # The arm is built at start: a file edited since then describes another arm.
                raise PlantError(f'the file now controls joints {list(joints)} and locks {dict(locked)}; the plant '
                                 f'started with joints {list(reduced_by[0])}, locked {dict(reduced_by[1])}: '
                                 'restart the plant to run it')
        motion = motion_of_duration(file, values['duration'] or file.motion.duration)
        if motion.dof != dof:
            raise PlantError(f'trajectory {trajectory} has {motion.dof} joints, the URDF {dof}')
        return disturbed_start(motion, values['tau'])
    except (MotionError, PlantError) as error:
        if values['motion']:
            raise _motion_problem(values, error) from error
        if isinstance(error, PlantError):
            raise
        raise PlantError(str(error)) from error


def plant_robot(values: dict, arm: Arm) -> Robot | None:
    """The MuJoCo robot of `mjcf` ('' : none) for the arm's joints (named in it by `mjcf_joints`, if given)."""
    if not values['mjcf']:
        if values['mjcf_joints']:
            raise PlantError('mjcf_joints names the joints of an MJCF robot: set mjcf')
        return None
    names = list(values['mjcf_joints'] or [])
    if names and len(names) != arm.dof:
        raise PlantError(f'mjcf_joints names {len(names)} joints; the arm has {arm.dof}: {arm.joint_names}')
    return load_robot(values['mjcf'], tuple(arm.joint_names), tuple(bool(x) for x in arm.prismatic),
                      values['period'], dict(zip(arm.joint_names, names)) if names else None)


def plant_settings(values: dict, arm: Arm, reduced_by: Reduction | None = None,
                   robot: Robot | None = None) -> PlantSettings:
    """Build and check the settings from parameter values; PlantError names the first problem. `robot`: the
    node's MuJoCo robot (plant_robot), which the options of ddarm's own plant do not apply to."""
    dof = arm.dof
    if robot is not None:
        given = [name for name in ROBOT_EXCLUDED if _optional_array(values[name]) is not None]
        if given:
            raise PlantError(f'{", ".join(given)} change ddarm\'s own plant; this plant steps the MJCF robot '
                             f"{values['mjcf']}: its friction, torques and masses are the MJCF's")
        robot = at_period(robot, values['period'])
    if values['mode'] not in MODES:
        raise PlantError(f"mode must be one of {MODES}, got {values['mode']!r}")
    if values['spin_margin'] >= values['period']:
        raise PlantError(f"spin_margin = {values['spin_margin']} s must be less than the period, {values['period']} s")
    options = PlantOptions(
        period=values['period'], substeps=values['substeps'],
        torque_limit=_optional_array(values['torque_limit']),
        viscous_friction=_optional_array(values['viscous_friction']),
        coulomb_friction=_optional_array(values['coulomb_friction']),
        external_torque=_optional_array(values['external_torque'])).checked(dof)
    mass_scale = _optional_array(values['mass_scale'])
    if mass_scale is not None:
        checked_mass_scale(mass_scale, dof)
    q0, v0 = start_state(values, arm, reduced_by)
    return PlantSettings(values['mode'], values['period'], values['command_timeout'],
                         values['required_subscribers'], values['required_clock_subscribers'],
                         values['max_samples'], options,
                         None if mass_scale is None else tuple(mass_scale), q0, v0, values['spin_margin'], robot)


class PlantNode(ManagedNode):
    """Publishes the arm's state at every sample and integrates each period under the commanded effort.

    lockstep: the state of t_n is published, and [t_n, t_{n+1}) is integrated only once the
    command stamped t_n arrives; a command missing for `command_timeout` wall seconds ends the
    episode with an error. realtime: a thread of its own ticks at t0 + kΔ on the wall clock (waking
    `spin_margin` before each deadline and spinning to it) and integrates under the latest command;
    the executor's callbacks and the ticks share the plant's state under `lock`. `realtime_priority`
    and `cpu_affinity` schedule the whole process (ddarm.ros.scheduling). The arm is built once, at
    configure: the `urdf` reduced to the joints of the `motion` file (or with every movable joint), and
    /joint_states names its joints.

    A managed (lifecycle) node. `managed` false (the default): configured and activated at construction (a
    configure refused is raised), an episode started at once with `autostart`, else on ~/reset. `managed` true:
    unconfigured, only the parameters and the lifecycle services; configure builds the arm and makes the topics,
    the watchdog and ~/reset, activate starts an episode (as ~/reset does), deactivate ends the episode in
    progress (no more states, commands ignored, ~/reset refused), cleanup frees what configure made.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('plant', **kwargs)
        self.incompatible_qos_events = 0
        # The real-time ticks run on a thread of their own: every callback that touches the episode holds the lock.
        self.lock = threading.Lock()
        self.ticks = TickThread('plant-ticks', self._realtime_tick, self._ticks_failed)
        self.active = False  # ~/reset starts episodes only while active
        self._forget_configuration()
        self.phase = IDLE
        self.plant: Plant | None = None
        self.latest_command: np.ndarray | None = None
        self.latest_command_sample = -1
        self.deadline = 0.0
        self.counters = {'refused_commands': 0, 'stale_commands': 0, 'duplicate_commands': 0, 'deadline_misses': 0}
        self.tick_times: list[float] = []
        self.lateness: list[int] = []  # ns: how late each real-time tick started after its deadline
        self.began = 0.0
        self._declare_parameters()
        refuse_undeclared_parameters(self, 'plant')
        self.add_on_set_parameters_callback(self._check_parameters)
        overrides = kwargs.get('parameter_overrides') or ()
        if self.get_parameter('managed').value:
            # Unconfigured: the parameters and the lifecycle services; the lifecycle services do the rest.
            try:
                self._refuse_unknown(overrides)
            except PlantError:
                self.destroy_node()
                raise
            return
        # Unmanaged (the default): configured and activated at launch, refused (raised) if configure fails.
        self.launch(PlantError, lambda: self._refuse_unknown(overrides))
        if self.get_parameter('autostart').value:
            try:
                self.start_episode()
            except Exception:
                self.destroy_node()
                raise

    # Lifecycle ---------------------------------------------------------------------------------

    def _refuse_unknown(self, overrides) -> None:
        unknown = undeclared_overrides(self, overrides)
        if unknown:
            raise PlantError(f'unknown parameters {unknown} (not plant parameters: a typo?)')

    def _configure(self) -> None:
        values = self._parameter_values()
        self.scheduling = NodeScheduling(values)
        self.arm, self.reduced_by = plant_arm(values)
        self.joints = self.arm.joint_names  # the reduced model's: what /joint_states names
        self.state_encoder = JointStateEncoder(self.joints)
        self.chain = chain_from_model(self.arm.model)
        self.robot = plant_robot(values, self.arm)
        self.settings = plant_settings(values, self.arm, self.reduced_by, self.robot)
        warm_up(self.chain)

        self.state_publisher = self.create_publisher(
            JointState, JOINT_STATES_TOPIC, SAMPLE_QOS,
            event_callbacks=PublisherEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.clock_publisher = self.create_publisher(ClockMsg, CLOCK_TOPIC, CLOCK_QOS)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS)
        # States and commands cross as CDR, read and written by ddarm.ros.cdr: rclpy's conversion is slower.
        self.command_subscription = self.create_subscription(
            JointState, EFFORT_COMMAND_TOPIC, self._locked(self._on_command), SAMPLE_QOS, raw=True,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.reset_service = self.create_service(Trigger, '~/reset', self._on_reset)
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        # Checks start-up and command timeouts; each wake costs a lockstep sample's worth of executor time.
        self.watchdog = self.create_timer(WATCHDOG_PERIOD, self._locked(self._watch), clock=wall)
        with self.lock:
            self.phase = IDLE
            self.plant = None
        self.configured = True
        # Said at configure also because rclpy's logger finds its caller through inspect, whose first call in a
        # process maps every loaded module to its file: 130 ms with numba, NumPy and rclpy loaded, measured. Its
        # first warning of a stale command, under the lock, missed 7 to 12 real-time deadlines at once.
        scheduling = self.scheduling.current()
        self.get_logger().info(f'plant: joints {self.joints}, {self.settings.mode} mode, period '
                               f'{self.settings.period} s; {scheduling.policy} priority {scheduling.priority} on '
                               f'cores {list(scheduling.affinity)}')

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.launching:  # the unmanaged start: active, the episode started by autostart (or ~/reset)
            self.active = True
            return TransitionCallbackReturn.SUCCESS
        try:
            message = self.start_episode()
        except (PlantError, ModelError, RobotError, ValueError) as error:
            self.get_logger().error(f'activate refused: {error}')
            return TransitionCallbackReturn.FAILURE
        self.active = True
        self.get_logger().info(f'activated: {json.loads(message)["message"]}')
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_ticks()
        with self.lock:
            self.active = False
            ended = self.phase in (STARTING, RUNNING)
            self.phase = IDLE
            sample = self.plant.sample if self.plant is not None else 0
        self.get_logger().info(f'deactivated{f" at sample {sample}, the episode ended" if ended else ""}: no more '
                               'states, commands ignored, ~/reset refused until activated again')
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        """Back to unconfigured: the ticks stopped, the topics, timer and service made at configure destroyed."""
        self._stop_ticks()  # no tick may publish on a destroyed publisher
        with self.lock:
            self.active = False
            self.phase = IDLE
            self.plant = None
            self.destroy_entities('state_publisher', 'clock_publisher', 'diagnostics_publisher',
                                  'command_subscription', 'reset_service', 'watchdog')
            self._forget_configuration()

    def _forget_configuration(self) -> None:
        """What configure makes, unset: the node unconfigured."""
        self.configured = False  # parameter changes are checked against the arm once configure built it
        self.scheduling: NodeScheduling | None = None
        self.arm: Arm | None = None
        self.reduced_by: Reduction | None = None
        self.joints: list[str] = []
        self.state_encoder: JointStateEncoder | None = None
        self.chain = None
        self.robot: Robot | None = None
        self.settings: PlantSettings | None = None
        self.state_publisher = self.clock_publisher = self.diagnostics_publisher = None
        self.command_subscription = self.reset_service = self.watchdog = None

    def _declare_parameters(self) -> None:
        declare_from_schema(self, 'plant', PlantError)

    def _parameter_values(self, changes=()) -> dict:
        return proposed_values(self, changes)

    def _check_parameters(self, changes) -> SetParametersResult:
        if not self.configured:  # checked, with the arm, at configure
            return SetParametersResult(successful=True)
        values = self._parameter_values(changes)
        try:
            plant_settings(values, self.arm, self.reduced_by, self.robot)
        except (PlantError, ModelError, RobotError, ValueError) as error:
            return SetParametersResult(successful=False, reason=str(error))
        # Last, once the rest is valid: the OS's answer is known only by asking, and a refusal changes nothing.
        refused = self.scheduling.refusal(values)
        return SetParametersResult(successful=refused is None, reason=refused or '')

    def _locked(self, callback):
        def locked(*args):
            with self.lock:
                return callback(*args)
        return locked

    def _incompatible_qos(self, event) -> None:
        self.incompatible_qos_events += 1
        self.get_logger().error(f'incompatible QoS with a peer (policy {event.last_policy_kind}): '
                                'samples will not flow; use the profiles of ddarm.ros.interface')

    # Episodes --------------------------------------------------------------------------------

    def start_episode(self) -> str:
        """Back to t = 0 at the configured start state; sample 0 goes out once subscribers match.

        Returns JSON: a `message` for people and the `parameters` the episode runs with, so that
        whoever reset the plant can tell whether another node changed them first.
        """
        self._stop_ticks()
        with self.lock:
            return self._start_episode()

    def _start_episode(self) -> str:
        values = self._parameter_values()
        self.settings = plant_settings(values, self.arm, self.reduced_by, self.robot)
        if self.settings.robot is not None:
            self.plant = MujocoPlant(self.settings.robot, self.settings.q0, self.settings.v0,
                                     self.settings.options.torque_limit)
        else:
            self.plant = Plant(self.chain, self.settings.options, self.settings.q0, self.settings.v0,
                               self.settings.mass_scale)
        self.latest_command, self.latest_command_sample = None, -1
        self.counters = dict.fromkeys(self.counters, 0)
        self.tick_times, self.lateness = [], []
        self.phase = STARTING
        self.deadline = time.monotonic() + self.settings.command_timeout
        message = (f'episode starts in {self.settings.mode} mode once {self.settings.required_subscribers} '
                   f'subscriber(s) listen on {self.state_publisher.topic_name} and '
                   f'{self.settings.required_clock_subscribers} on {self.clock_publisher.topic_name}')
        return json.dumps({'message': message, 'parameters': plain_parameters(values)})

    def _on_reset(self, request, response):
        if not self.active:
            response.success, response.message = False, 'reset refused: the plant is inactive: activate it first'
            self.get_logger().error(response.message)
            return response
        try:
            response.message = self.start_episode()
            response.success = True
        except (PlantError, ModelError, RobotError) as error:
            response.success, response.message = False, f'reset refused: {error}'
            self.get_logger().error(response.message)
        return response

    def _watch(self) -> None:
        now = time.monotonic()
        if self.phase == STARTING:
            listeners = self.state_publisher.get_subscription_count()
            # Each topic matches on its own: a recorder whose /clock reader the plant has not matched yet would miss
            # the first ticks (volatile: never sent again), and a command publisher not matched yet sample 0's command.
            clock_listeners = self.clock_publisher.get_subscription_count()
            commanders = self.command_subscription.get_publisher_count()
            if (listeners >= self.settings.required_subscribers and commanders >= 1
                    and clock_listeners >= self.settings.required_clock_subscribers):
                self._begin()
            elif now > self.deadline:
                self._end(DiagnosticStatus.ERROR, 'no_start',
                          f'no start: {listeners} of {self.settings.required_subscribers} joint_states subscribers, '
                          f'{clock_listeners} of {self.settings.required_clock_subscribers} /clock subscribers '
                          f'and {commanders} effort_command publishers within {self.settings.command_timeout} s')
        elif self.phase == RUNNING and self.settings.mode == 'lockstep' and now > self.deadline:
            self._end(DiagnosticStatus.ERROR, 'timeout', f'no command for sample {self.plant.sample} '
                      f'(t = {self.plant.time:.6f} s) within {self.settings.command_timeout} s')

    def _begin(self) -> None:
        self.phase = RUNNING
        start = time.monotonic_ns()  # t0: tick k is due at t0 + kΔ, wall clock (CLOCK_MONOTONIC)
        self.began = start * 1e-9
        self._publish_state(effort=None)
        self.deadline = time.monotonic() + self.settings.command_timeout
        self._report(DiagnosticStatus.OK, 'started', 'episode started')
        if self.settings.mode == 'realtime':
            # A full collection of the ~170,000 objects numba, NumPy and rclpy leave took 110 ms here (eleven
            # periods); frozen, a collection walks only what the episode allocates. No mlockall: the tick touches
            # its pages every period, and with no swap here there was no paging to measure.
            gc.freeze()
            self.ticks.start(start, period_ns(self.settings.period), period_ns(self.settings.spin_margin))

    def _ticks_failed(self, error: Exception) -> None:
        if self.context.ok():  # the driver names the stall
            self.get_logger().error(f'the real-time ticks stopped: {type(error).__name__}: {error}')

    def _stop_ticks(self) -> None:
        """End the real-time ticks and wait for the thread (at most one tick's work): reset, destroy."""
        self.ticks.stop()

    def destroy_node(self) -> None:
        self._stop_ticks()  # no tick may publish on a destroyed publisher
        super().destroy_node()

    def _end(self, level: bytes, event: str, message: str) -> None:
        self.phase = ENDED
        self.ticks.end()  # the tick thread ends after this tick (this may be it): joined at the next reset
        # One call site per severity: rclpy refuses a call site that logs at another severity than before.
        if level == DiagnosticStatus.OK:
            self.get_logger().info(message)
        else:
            self.get_logger().error(message)
        self._report(level, event, message)

    def _report(self, level: bytes, event: str, message: str) -> None:
        """A DiagnosticArray on /diagnostics; `event` (started, complete, diverged, timeout, no_start) is for programs.

        `node` is this plant's fully qualified name: /diagnostics is shared by every node of the graph.
        """
        values = {'event': event, 'sample': self.plant.sample if self.plant else 0, 'mode': self.settings.mode,
                  'node': self.get_fully_qualified_name(),
                  'wall_time_s': time.monotonic() - self.began if self.phase != STARTING else 0.0, **self.counters}
        if len(self.tick_times) > 1:
            jitter = np.abs(np.diff(self.tick_times) - self.settings.period) * 1e3
            late = np.array(self.lateness) * 1e-6
            values.update({'period_jitter_p50_ms': float(np.percentile(jitter, 50)),
                           'period_jitter_p99_ms': float(np.percentile(jitter, 99)),
                           'period_jitter_max_ms': float(jitter.max()),
                           'tick_lateness_p99_ms': float(np.percentile(late, 99)),
                           'tick_lateness_max_ms': float(late.max())})
        if self.settings.mode == 'realtime':
            # A jitter figure means nothing without the conditions it was measured in: the ticking thread's.
            values.update({**self.scheduling.current().report(), 'spin_margin_s': self.settings.spin_margin})
        status = DiagnosticStatus(level=level, name='ddarm/plant', message=message, hardware_id='ddarm',
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = time_msg(self.plant.time if self.plant else 0.0)
        self.diagnostics_publisher.publish(array)

    # Samples ---------------------------------------------------------------------------------

    def _publish_state(self, effort: np.ndarray | None) -> None:
        t = self.plant.time
        # The state first: in lockstep the controller waits for it, and the clock goes out while it computes (the
        # driver ends an episode only once it has every clock tick too, whatever order they arrive in).
        self.state_publisher.publish(self.state_encoder.encode(t, self.plant.q, self.plant.v, effort))
        self.clock_publisher.publish(encode_clock(t))

    def _on_command(self, data: bytes) -> None:
        try:
            command = read_joint_state(decode_joint_state(data, 'effort command'), self.joints,
                                       self.settings.period, 'effort command', need_state=False, need_effort=True)
        except MessageError as error:
            self.counters['refused_commands'] += 1
            self.get_logger().error(f'refused: {error}')
            return
        if self.phase != RUNNING:
            return
        expected = self.plant.sample
        if command.n < expected or (self.settings.mode == 'realtime' and command.n < self.latest_command_sample):
            self.counters['stale_commands'] += 1
            self.get_logger().warning(f'ignored a stale command for sample {command.n} (now at {expected})')
            return
        if command.n > expected:
            self.counters['refused_commands'] += 1
            self.get_logger().error(f'refused a command for sample {command.n} from the future '
                                    f'(expected sample {expected})')
            return
        if command.n == self.latest_command_sample:
            # Real time only (lockstep has stepped past it): another controller answers the same states.
            self.counters['duplicate_commands'] += 1
            self.get_logger().warning(f'ignored a second command for sample {command.n}: the first one stands')
            return
        self.latest_command, self.latest_command_sample = command.effort, command.n
        if self.settings.mode == 'lockstep':
            self._step(command.effort)

    def _step(self, command: np.ndarray) -> None:
        """Apply a command over [t_n, t_{n+1}) and publish sample n + 1 with the applied effort."""
        applied = self.plant.saturate(command)
        if not self.plant.advance(applied):
            n = self.plant.sample
            self.state_publisher.publish(self.state_encoder.encode((n + 1) * self.settings.period, effort=applied))
            self._end(DiagnosticStatus.ERROR, 'diverged', f'diverged: the state left its bounds during sample {n}; '
                      'the plant is frozen')
            return
        self._publish_state(applied)
        self.deadline = time.monotonic() + self.settings.command_timeout
        if self.settings.max_samples and self.plant.sample >= self.settings.max_samples:
            self._end(DiagnosticStatus.OK, 'complete', f'episode complete: {self.plant.sample} periods')

    def _realtime_tick(self, index: int, deadline: int) -> bool:
        """One tick of the real-time thread, due at `deadline` (ns); False once the episode is over."""
        with self.lock:
            if self.phase != RUNNING:
                return False
            self._tick(deadline)
            return self.phase == RUNNING

    def _tick(self, deadline: int) -> None:
        """Real time: hold the latest command (zero until the first) and count what came late.

        A deadline miss is a tick that starts more than 1.5 periods after the one before; a stale
        command is a tick whose latest command is not for the current sample (held all the same).
        """
        started = time.monotonic_ns()
        now = started * 1e-9
        self.lateness.append(started - deadline)
        if self.tick_times and now - self.tick_times[-1] > 1.5 * self.settings.period:
            self.counters['deadline_misses'] += 1
        self.tick_times.append(now)
        if self.latest_command_sample != self.plant.sample:
            self.counters['stale_commands'] += 1
        held = self.latest_command if self.latest_command is not None else np.zeros(self.arm.dof)
        self._step(held)


def main(args=None) -> int:
    return run_node(PlantNode, 'plant', (PlantError, ModelError, RobotError, SchedulingError), args)


if __name__ == '__main__':
    raise SystemExit(main())
