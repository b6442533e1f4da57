"""A robot's episode as a robot runs it: `ddarm robot` and the controller node in robot mode, recorded and scored.

The robot (MuJoCo, `ddarm_sim.robot_node`) and the controller (sampling on a timer, the efforts as the
Float64MultiArray a ros2_control forward_command_controller takes) run as two processes in a namespace of their
own, as `ddarm.ros.session` runs the plant's; this process only listens. What the two published (the robot's
states, its record of the command in force at each sample, the efforts, /clock, /diagnostics) goes into an
episode bag of ROBOT_TOPICS once the episode is over, which is then scored from the bag alone: a stop before the
end leaves no bag rather than half of one.

lockstep: the robot integrates one period per command and publishes /clock; the controller runs on it
(use_sim_time), so the episode is the in-process one. realtime: both run free on the wall clock at 1/Δ, their
ticks unsynchronised, as on a real robot.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from ddarm.episodes.result import Episodes
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, check_episode
from ddarm.errors import DdarmError
from ddarm.recording.bags import (ROBOT_COMMANDED_TOPIC, ROBOT_COMMANDS_TOPIC, ROBOT_TOPICS, SAMPLE_0_KEY,
                                  BagError, EpisodeBagWriter, bag_result, checked_output_path, read_episode_bag,
                                  score_bag)
from ddarm.ros.cdr import read_stamp
from ddarm.samples import stamp_ns
from ddarm.ros.driver import qos_description
from ddarm.ros.executors import node_executor
from ddarm.ros.lifetime import stop_processes
from ddarm.ros.interface import CLOCK_QOS, DIAGNOSTICS_QOS, ROBOT_COMMAND_QOS, SAMPLE_QOS, reference_msg
from ddarm.ros.names import namespace_arguments
from ddarm.ros.node_parameters import gains_parameters
from ddarm.ros.session import node_environment, session_namespace

MODES = ('lockstep', 'realtime')
# What the robot and the controller count on /diagnostics that makes a measurement other than the law's clean loop.
FAULT_COUNTERS = ('refused_commands', 'timeouts', 'late_periods', 'refused_states', 'out_of_order_states',
                  'future_states', 'unsafe_states', 'stale_ticks', 'future_ticks', 'missed_ticks', 'clock_faults',
                  'non_finite_commands')
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'  # rmw's name for a publisher whose node's name has not been discovered
NAMING_TIMEOUT = 2.0  # wall s to wait for the graph to name every publisher heard
# Wall s the robot waits for a command before a lockstep period runs without one: long enough for a loaded machine.
LOCKSTEP_COMMAND_TIMEOUT = 5.0
# Realtime: s without a command after which the robot zeroes its efforts (its watchdog), as a robot's would.
REALTIME_COMMAND_TIMEOUT = 0.5
START_TIMEOUT = 120.0  # wall s for the processes to come up and the first command to arrive (a cold start compiles)


class RobotEpisodeError(DdarmError, RuntimeError):
    """A robot episode that could not be recorded: a process that ended, or an episode that never finished."""


def robot_node_parameters(spec: EpisodeSpec, plan: EpisodePlan, mode: str) -> dict:
    """The robot node's parameters for `spec`: its MJCF, joints (the MJCF's names of the plan's), rate and start."""
    joints = list(spec.mjcf_joints or plan.joint_names)
    return {'mjcf': str(Path(spec.mjcf).resolve()), 'joints': joints, 'mode': mode, 'rate': 1.0 / spec.period,
            'initial_position': plan.q0.tolist(), 'initial_velocity': plan.v0.tolist(),
            'command_topic': ROBOT_COMMANDS_TOPIC.lstrip('/'),  # relative: in the session's namespace
            'command_timeout': LOCKSTEP_COMMAND_TIMEOUT if mode == 'lockstep' else REALTIME_COMMAND_TIMEOUT,
            'required_subscribers': 2}  # the controller and the recorder hear sample 0


def controller_node_parameters(spec: EpisodeSpec, mode: str) -> dict:
    """The controller node's parameters for `spec` in robot mode: the law of the episode, on the robot's clock in
    lockstep. Its efforts are not clamped (the robot's own ranges bound them, as in-process), and its state checks
    (position and velocity limits) stay on, as on a robot."""
    urdf = spec.model_urdf or spec.urdf
    parameters = {'urdf': str(Path(urdf).resolve()) if urdf else '', 'motion': str(Path(spec.motion).resolve()),
                  'duration': float(spec.duration), **gains_parameters(spec), 'omega': 0.0,
                  'delay': spec.delay, 'period': spec.period, 'sampling': 'timer',
                  'command_type': 'float64_multi_array', 'command_topic': ROBOT_COMMANDS_TOPIC.lstrip('/'),
                  'clamp_efforts': False, 'use_sim_time': mode == 'lockstep'}
    parameters.update({name: list(getattr(spec, name)) for name in ('viscous_friction', 'coulomb_friction')
                       if getattr(spec, name) is not None})
    return parameters


class RobotRecorder(Node):
    """Listens to one robot episode's topics in `namespace` and keeps every message, as heard, for its bag."""

    def __init__(self, namespace: str, context) -> None:
        super().__init__('ddarm_robot_recorder', namespace=namespace, context=context)
        self.messages: list[tuple[str, int, bytes]] = []  # (the bag's topic, when heard in ns, CDR)
        self.topics: dict[str, str] = {}  # the bag's topic -> the graph's
        self.subscriptions_by_bag_topic: dict = {}
        self.sample_0_ns: int | None = None
        self.last_state_ns: int | None = None
        self.last_commanded_ns: int | None = None
        for topic, bag_topic, msg_type, qos in (
                ('joint_states', '/joint_states', JointState, SAMPLE_QOS),
                ('robot/commanded_effort', ROBOT_COMMANDED_TOPIC, JointState, SAMPLE_QOS),
                (ROBOT_COMMANDS_TOPIC.lstrip('/'), ROBOT_COMMANDS_TOPIC, Float64MultiArray, ROBOT_COMMAND_QOS),
                ('clock', '/clock', ClockMsg, CLOCK_QOS),
                ('diagnostics', '/diagnostics', DiagnosticArray, DIAGNOSTICS_QOS)):
            subscription = self.create_subscription(msg_type, topic, self._keeper(bag_topic), qos, raw=True)
            self.topics[bag_topic] = subscription.topic_name
            self.subscriptions_by_bag_topic[bag_topic] = subscription

    def publishers(self) -> dict[str, list[str | None]]:
        """The nodes the graph shows publishing each recorded topic, by fully qualified name (None: a publisher
        whose node DDS has not named yet)."""
        return {bag_topic: [None if info.node_name == UNKNOWN_NODE else
                            f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                            for info in self.get_publishers_info_by_topic(topic)]
                for bag_topic, topic in self.topics.items()}

    def _keeper(self, topic: str):
        def keep(data: bytes) -> None:
            self.messages.append((topic, time.time_ns(), data))
            if topic == '/joint_states':
                self.last_state_ns = stamp_ns(read_stamp(data, topic))
            elif topic == ROBOT_COMMANDED_TOPIC:
                stamp = stamp_ns(read_stamp(data, topic))
                if self.sample_0_ns is None:
                    self.sample_0_ns = stamp  # the robot's first period with a command in force
                self.last_commanded_ns = stamp
        return keep

    def status(self, executor, node: str, timeout: float = 5.0) -> dict:
        """What `node` (a name in the namespace) says on its ~/status: JSON; {} if it does not answer in time."""
        client = self.create_client(Trigger, f'{node}/status')
        try:
            deadline = time.monotonic() + timeout
            while not client.service_is_ready() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            if not client.service_is_ready():
                return {}
            future = client.call_async(Trigger.Request())
            while not future.done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            return json.loads(future.result().message) if future.done() else {}
        finally:
            self.destroy_client(client)

    def hears_robot(self) -> bool:
        """Whether the robot's states and commands in force reach this recorder (matched on its side)."""
        return all(self.subscriptions_by_bag_topic[topic].get_publisher_count() >= 1
                   for topic in ('/joint_states', ROBOT_COMMANDED_TOPIC))

    def heard_through(self, k_max: int, period: float) -> bool:
        """Whether the states of samples 0 … k_max + 1 and the commands of 0 … k_max have been heard."""
        if self.sample_0_ns is None or self.last_state_ns is None or self.last_commanded_ns is None:
            return False
        period_ns = round(period * 1e9)
        return (self.last_state_ns >= self.sample_0_ns + (k_max + 1) * period_ns
                and self.last_commanded_ns >= self.sample_0_ns + k_max * period_ns)


def counted_faults(counters: dict[str, dict]) -> list[str]:
    """The faults the nodes counted, in words: a measurement with any of them is not the law's clean loop."""
    faults = []
    for name, values in sorted(counters.items()):
        counted = {key: values[key] for key in FAULT_COUNTERS if isinstance(values.get(key), int) and values[key] > 0}
        if counted:
            faults.append(f'the {name} node counted {", ".join(f"{key} {count}" for key, count in counted.items())}')
    return faults


def _tail(path: Path, lines: int = 5) -> str:
    try:
        return ' | '.join(path.read_text(errors='replace').strip().splitlines()[-lines:])
    except OSError:
        return ''


def _check(processes: dict, folder: Path, deadline: float, late: str) -> None:
    """RobotEpisodeError if a node process ended, or (saying `late`) if the deadline passed; the logs' last lines."""
    for name, process in processes.items():
        if process.poll() is not None:
            raise RobotEpisodeError(f'the {name} node ended (exit code {process.returncode}) before the episode did: '
                                    f'{_tail(folder / f"{name}.log")}')
    if time.monotonic() > deadline:
        raise RobotEpisodeError(f'{late}; robot: {_tail(folder / "robot.log")}')


def record_robot_episode(spec: EpisodeSpec, bag: Path | str, mode: str = 'lockstep', storage: str = 'mcap',
                         command: str | None = None, timeout: float = START_TIMEOUT
                         ) -> tuple[Episodes, dict, dict[str, dict]]:
    """Run `spec` (which names its `mjcf` robot) with `ddarm robot` and the controller node in robot mode, record
    it at `bag` and score the bag: (the episode read back from the bag, the score `ddarm score` gives, what each node
    said on its ~/status at the end, by node name: `counted_faults` says its faults).

    RobotEpisodeError when a process ends before the episode does or the episode does not finish within
    `timeout` wall s plus its own duration; the bag is written only for a finished episode.
    """
    if mode not in MODES:
        raise RobotEpisodeError(f'mode must be one of {list(MODES)}, got {mode!r}')
    if spec.mjcf is None or spec.motion is None:
        raise RobotEpisodeError('a robot episode needs the robot (mjcf) and a motion file (the controller node '
                                'reads its reference from it in robot mode)')
    plan = check_episode(spec)
    bag = checked_output_path(bag)
    namespace = session_namespace()
    parameters = {'robot': robot_node_parameters(spec, plan, mode),
                  spec.controller: controller_node_parameters(spec, mode)}
    with tempfile.TemporaryDirectory(prefix='ddarm-robot-') as folder:
        folder = Path(folder)
        processes = {}
        context = rclpy.Context()
        rclpy.init(args=[], context=context)
        recorder = RobotRecorder(namespace, context)
        executor = node_executor(context)
        executor.add_node(recorder)
        try:
            deadline = time.monotonic() + timeout
            for name, arguments in (('robot', ['robot']), (spec.controller, ['controller', spec.controller])):
                # The controller starts the motion: only once the robot's record of it is sure to be heard.
                while name != 'robot' and not recorder.hears_robot():
                    _check(processes, folder, deadline, 'the robot never appeared on the graph')
                    executor.spin_once(timeout_sec=0.05)
                path = folder / f'{name}.parameters.yaml'
                path.write_text(yaml.safe_dump({f'{namespace}/{name}': {'ros__parameters': parameters[name]}}))
                with open(folder / f'{name}.log', 'w') as log:
                    processes[name] = subprocess.Popen(
                        [sys.executable, '-m', 'ddarm.cli.main', *arguments, '--ros-args',
                         *namespace_arguments(namespace), '--params-file', str(path)],
                        stdout=log, stderr=subprocess.STDOUT, env=node_environment(folder), start_new_session=True)
            deadline = time.monotonic() + timeout + plan.k_max * spec.period * (1 if mode == 'realtime' else 0.1)
            while not recorder.heard_through(plan.k_max, spec.period):
                if time.monotonic() > deadline and all(process.poll() is None for process in processes.values()):
                    # Stalled, the nodes alive: what they counted (a controller refusing unsafe states, say) says why.
                    faults = counted_faults({name: recorder.status(executor, name)
                                             for name in ('robot', spec.controller)})
                    raise RobotEpisodeError('the robot episode did not finish in time: ' + (
                        'no command reached the robot' if recorder.sample_0_ns is None else
                        f'heard states to {recorder.last_state_ns} ns from sample 0 at {recorder.sample_0_ns} ns')
                        + ''.join(f'; {fault}' for fault in faults) + f'; robot: {_tail(folder / "robot.log")}')
                _check(processes, folder, deadline, 'the robot episode did not finish in time')
                executor.spin_once(timeout_sec=0.05)
            counters = {name: recorder.status(executor, name) for name in ('robot', spec.controller)}
            naming = time.monotonic() + NAMING_TIMEOUT
            while None in sum((publishers := recorder.publishers()).values(), []) and time.monotonic() < naming:
                executor.spin_once(timeout_sec=0.05)
        finally:
            stop_processes(processes.values())
            executor.shutdown()
            recorder.destroy_node()
            rclpy.try_shutdown(context=context)
        episode = {'spec': spec.to_dict(), 'joints': list(plan.joint_names), 'prismatic': list(plan.prismatic),
                   'k_max': plan.k_max, 'torque_limit': None, 'transport': f'ros-robot-{mode}', 'command': command,
                   SAMPLE_0_KEY: recorder.sample_0_ns, 'node_parameters': parameters,
                   'controller_log': _tail(folder / f'{spec.controller}.log', 3)}
    _write_robot_bag(bag, episode, plan, recorder.messages, publishers, storage)
    try:
        return bag_result(read_episode_bag(bag)), score_bag(bag), counters
    except BagError as error:  # a sample missing: what the nodes counted says why
        faults = counted_faults(counters)
        if not faults:
            raise
        raise RobotEpisodeError(f'{error} ({"; ".join(faults)})') from error


def _write_robot_bag(bag: Path, episode: dict, plan: EpisodePlan, messages: list, publishers: dict,
                     storage: str) -> None:
    """The episode's bag: its configuration, the reference the controller ran, and every message as heard."""
    # One profile per publisher heard (the ones ddarm's nodes declare: discovery does not carry history and depth),
    # so that a scorer sees a second source; the names the graph gave, those it did not counted all the same.
    offered = {topic: [qos_description(qos)] * len(publishers[topic]) for topic, qos in (
        ('/joint_states', SAMPLE_QOS), (ROBOT_COMMANDED_TOPIC, SAMPLE_QOS), (ROBOT_COMMANDS_TOPIC, ROBOT_COMMAND_QOS),
        ('/clock', CLOCK_QOS), ('/diagnostics', DIAGNOSTICS_QOS)) if publishers[topic]}
    reference = reference_msg(list(plan.joint_names), plan.times, plan.q_ref, plan.v_ref, plan.a_ref, plan.nominal)
    with EpisodeBagWriter(bag, episode, storage, offered_qos=offered, topics=ROBOT_TOPICS) as writer:
        first = messages[0][1] if messages else time.time_ns()
        writer.write('/reference', first, serialize_message(reference))
        for topic, heard_ns, data in messages:
            writer.write(topic, heard_ns, data)
        writer.set_publishers({topic: [name for name in names if name is not None]
                               for topic, names in publishers.items()})
        writer.close(complete=True)
