"""Episodes run through the ROS 2 graph: a driver node configures the plant and a controller through
their parameter services, publishes the programmed motion, runs the episode, records it (optionally
as a bag) and scores what it heard."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ddarm_control.laws import CONTROLLERS
from ddarm_sim.ros_interface import (CLOCK_QOS, CLOCK_TOPIC, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC,
                                     EFFORT_COMMAND_TOPIC, JOINT_STATES_TOPIC, REFERENCE_QOS, REFERENCE_TOPIC,
                                     SAMPLE_QOS, read_joint_state, reference_msg)
from ddarm_sim.samples import MessageError
from ddarm_tuner.bags import EpisodeBagWriter
from ddarm_tuner.episodes import EpisodePlan, EpisodeResult, EpisodeSpec, load_arm, plan_episode, score

# Lockstep waits this long (wall clock) for a command before the plant ends the episode.
COMMAND_TIMEOUT = 10.0
# The plant starts an episode once this many nodes listen to it: the controller and the driver.
GRAPH_SUBSCRIBERS = 2


class GraphEpisodeError(RuntimeError):
    """An episode over ROS that did not complete; the text says which sample and why."""


def node_parameters(spec: EpisodeSpec, plan: EpisodePlan, mode: str = 'lockstep') -> dict:
    """The parameters (as a node: ros__parameters: mapping) that make the plant and controller run `spec`.

    Per-joint options left out mean "none"; set through the parameter services, they are empty arrays.
    """
    plant = {
        'mode': mode, 'period': spec.period, 'substeps': spec.substeps, 'command_timeout': COMMAND_TIMEOUT,
        'required_subscribers': GRAPH_SUBSCRIBERS, 'max_samples': plan.k_max + 1, 'autostart': False,
        'trajectory': spec.trajectory, 'duration': spec.duration, 'tau': spec.tau,
    }
    optional = {'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
                'viscous_friction': spec.viscous_friction, 'coulomb_friction': spec.coulomb_friction,
                'external_torque': spec.external_torque, 'mass_scale': spec.mass_scale}
    plant.update({name: [float(x) for x in value] for name, value in optional.items() if value is not None})
    controller = {'kp': list(spec.kp), 'kv': list(spec.kv), 'omega': 0.0, 'compute_delay_steps': spec.delay,
                  'period': spec.period}
    # The in-process runner gives computed torque the plant's friction as its model F̂; so does this.
    controller.update({name: list(getattr(spec, name)) for name in ('viscous_friction', 'coulomb_friction')
                       if getattr(spec, name) is not None})
    if spec.urdf:
        plant['urdf'] = controller['urdf'] = spec.urdf
    return {'plant': {'ros__parameters': plant}, spec.controller: {'ros__parameters': controller}}


def _service_parameters(values: dict, clear: tuple[str, ...]) -> list[Parameter]:
    """Parameters to set at run time: read-only ones left out, unset per-joint options cleared."""
    parameters = [Parameter(name, value=value) for name, value in values.items() if name != 'urdf']
    parameters += [Parameter(name, Parameter.Type.DOUBLE_ARRAY, []) for name in clear if name not in values]
    return parameters


PLANT_OPTIONAL = ('torque_limit', 'viscous_friction', 'coulomb_friction', 'external_torque', 'mass_scale')
CONTROLLER_OPTIONAL = ('viscous_friction', 'coulomb_friction')


@dataclass
class Recording:
    """What the driver heard during one episode: states (with applied effort) and commands, by sample."""

    k_max: int
    states: dict = field(default_factory=dict)
    commands: dict = field(default_factory=dict)
    diverged_at: int | None = None
    last_state_heard: bool = False
    plant_report: dict | None = None  # the plant's end-of-episode diagnostics (complete or diverged)
    error: str | None = None

    @property
    def ended(self) -> bool:
        """An error, or the last state, the plant's report and every scored command all heard.

        Topics are not ordered among themselves: the plant's last state can arrive before the
        command it applied.
        """
        if self.error is not None:
            return True
        last = self.k_max if self.diverged_at is None else self.diverged_at - 1
        return self.last_state_heard and self.plant_report is not None and len(self.commands) >= last + 1


def _stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class GraphDriver(Node):
    """Runs episodes on a running plant and controller node, one at a time, and records them.

    With a bag writer, every message it publishes or hears during the episode goes into the bag
    as the CDR that crossed DDS, timestamped with its simulated time.
    """

    def __init__(self, name: str = 'ddarm_episode_driver', plant_node: str = 'plant', **kwargs) -> None:
        super().__init__(name, **kwargs)
        self.plant_node = plant_node
        self.joints = load_arm(None).joint_names
        self.recording: Recording | None = None
        self.bag: EpisodeBagWriter | None = None
        self.period = 0.01
        self.reference_publisher = self.create_publisher(JointTrajectory, REFERENCE_TOPIC, REFERENCE_QOS)
        self.create_subscription(JointState, JOINT_STATES_TOPIC, self._on_state, SAMPLE_QOS)
        self.create_subscription(JointState, EFFORT_COMMAND_TOPIC, self._on_command, SAMPLE_QOS)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, DIAGNOSTICS_QOS)
        self.create_subscription(Clock, CLOCK_TOPIC, self._on_clock, CLOCK_QOS)
        self.parameter_clients = {plant_node: AsyncParameterClient(self, plant_node)}
        self.reset_clients = {plant_node: self.create_client(Trigger, f'/{plant_node}/reset')}
        for law in CONTROLLERS:
            self.parameter_clients[law] = AsyncParameterClient(self, law)
            self.reset_clients[law] = self.create_client(Trigger, f'/{law}/reset')

    # What the graph says --------------------------------------------------------------------

    def _record(self, topic: str, stamp, msg) -> None:
        if self.bag is not None and self.recording is not None:
            self.bag.write(topic, _stamp_ns(stamp), serialize_message(msg))

    def _on_clock(self, msg: Clock) -> None:
        self._record(CLOCK_TOPIC, msg.clock, msg)

    def _on_state(self, msg: JointState) -> None:
        if self.recording is None:
            return
        try:
            sample = read_joint_state(msg, self.joints, self.period, need_state=False)
        except MessageError as error:
            self.get_logger().error(f'unusable joint state: {error}')
            return
        self._record('/' + JOINT_STATES_TOPIC, msg.header.stamp, msg)
        if sample.q is None:  # the plant diverged during the period before this stamp
            self.recording.diverged_at = sample.n
            self.recording.last_state_heard = True
        self.recording.states[sample.n] = sample
        if sample.n >= self.recording.k_max + 1:
            self.recording.last_state_heard = True

    def _on_command(self, msg: JointState) -> None:
        if self.recording is None:
            return
        try:
            sample = read_joint_state(msg, self.joints, self.period, 'command', need_state=False,
                                      need_effort=True)
        except MessageError as error:
            self.get_logger().error(f'unusable command: {error}')
            return
        if sample.n > self.recording.k_max:
            return  # the answer to the final state: never applied, not part of the episode
        self._record('/' + EFFORT_COMMAND_TOPIC, msg.header.stamp, msg)
        self.recording.commands[sample.n] = sample.effort

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if self.recording is None:
            return
        self._record(DIAGNOSTICS_TOPIC, msg.header.stamp, msg)
        for status in msg.status:
            if status.name != 'ddarm/plant':
                continue
            values = {pair.key: pair.value for pair in status.values}
            if values.get('event') in ('timeout', 'no_start'):
                self.recording.error = status.message
            elif values.get('event') in ('complete', 'diverged'):
                self.recording.plant_report = values

    # Driving --------------------------------------------------------------------------------

    def _spin_until(self, executor, done, deadline: float, what: str, alive) -> None:
        while True:
            if not self.context.ok():  # SIGINT/SIGTERM: rclpy's handler shut the context down
                raise ExternalShutdownException(f'shut down while waiting for {what}')
            if done():
                return
            if time.monotonic() > deadline:
                raise GraphEpisodeError(f'timed out waiting for {what}')
            alive()
            executor.spin_once(timeout_sec=0.05)

    def _reset(self, executor, node: str, deadline: float, alive):
        client = self.reset_clients[node]
        self._spin_until(executor, client.service_is_ready, deadline, f'service {client.srv_name}', alive)
        future = client.call_async(Trigger.Request())
        self._spin_until(executor, future.done, deadline, f'a reply from {client.srv_name}', alive)
        return future.result()

    def _configure(self, executor, node: str, parameters: list[Parameter], deadline: float, alive) -> None:
        client = self.parameter_clients[node]
        self._spin_until(executor, client.services_are_ready, deadline, f'the parameters of /{node}', alive)
        future = client.set_parameters(parameters)
        self._spin_until(executor, future.done, deadline, f'/{node} to take its parameters', alive)
        refused = [f'{parameter.name}: {result.reason}'
                   for parameter, result in zip(parameters, future.result().results) if not result.successful]
        if refused:
            raise GraphEpisodeError(f'/{node} refused parameters: {refused}')

    def run_episode(self, executor, spec: EpisodeSpec, plan: EpisodePlan | None = None,
                    bag: EpisodeBagWriter | None = None, mode: str = 'lockstep', timeout: float = 120.0,
                    alive=lambda: None) -> EpisodeResult:
        """Configure, start, record and score one episode; `alive` raises if a node process has died."""
        plan = plan if plan is not None else plan_episode(spec)
        deadline = time.monotonic() + timeout
        parameters = node_parameters(spec, plan, mode)
        self._configure(executor, self.plant_node,
                        _service_parameters(parameters['plant']['ros__parameters'], PLANT_OPTIONAL), deadline,
                        alive)
        self._configure(executor, spec.controller,
                        _service_parameters(parameters[spec.controller]['ros__parameters'],
                                            CONTROLLER_OPTIONAL), deadline, alive)
        self.period, self.bag = spec.period, bag
        self.recording = Recording(plan.k_max)
        try:
            reference = reference_msg(self.joints, plan.times, plan.q_ref, plan.v_ref, plan.a_ref, plan.nominal)
            self.reference_publisher.publish(reference)
            self._record('/' + REFERENCE_TOPIC, reference.header.stamp, reference)
            expected = {'ready': True, 'kp': list(spec.kp), 'kv': list(spec.kv), 'delay': spec.delay,
                        'reference_samples': plan.k_max + 1, 'reference_final': plan.q_ref[-1].tolist()}
            while True:  # until the controller holds this episode's reference and gains
                state = json.loads(self._reset(executor, spec.controller, deadline, alive).message)
                if all(state[key] == value for key, value in expected.items()):
                    break
                executor.spin_once(timeout_sec=0.01)
            reply = self._reset(executor, self.plant_node, deadline, alive)
            if not reply.success:
                raise GraphEpisodeError(f'the plant refused to start: {reply.message}')
            self._spin_until(executor, lambda: self.recording.ended, deadline, 'the episode to end', alive)
            if self.recording.error:
                raise GraphEpisodeError(self.recording.error)
            return result_from_recording(spec, plan, self.recording)
        finally:
            self.recording, self.bag = None, None


def result_from_recording(spec: EpisodeSpec, plan: EpisodePlan, recording: Recording) -> EpisodeResult:
    """Arrange the recorded samples as the in-process runner does, and score them."""
    last = plan.k_max if recording.diverged_at is None else recording.diverged_at - 1
    missing = [n for n in range(last + 2) if n not in recording.states]
    missing += [n for n in range(last + 1) if n not in recording.commands]
    if missing:
        raise GraphEpisodeError(f'samples {sorted(set(missing))} are missing from the recording')
    states = [recording.states[n] for n in range(last + 1)]
    result = EpisodeResult(
        spec, plan, q=np.array([s.q for s in states]), v=np.array([s.v for s in states]),
        command=np.array([recording.commands[n] for n in range(last + 1)]),
        torque=np.array([recording.states[n + 1].effort for n in range(last + 1)]),
        diverged_at=recording.diverged_at, plant_report=recording.plant_report)
    result.indices = score(plan, result.errors, result.torque)
    return result


def episode_record(spec: EpisodeSpec, plan: EpisodePlan, transport: str, command: str | None) -> dict:
    """The configuration a bag carries, so that the bag alone says what was run."""
    return {'spec': spec.to_dict(), 'joints': load_arm(spec.urdf).joint_names, 'k_max': plan.k_max,
            'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
            'transport': transport, 'command': command,
            'node_parameters': node_parameters(spec, plan, transport.removeprefix('ros-'))}


class GraphSession:
    """The plant and a controller as separate processes over DDS, with a driver in this process.

    The node processes live as long as the session, so episodes cost no start-up; switching
    controller stops the other law's process, because two laws would answer the same states.
    """

    def __init__(self, folder: Path | str | None = None, timeout: float = 120.0) -> None:
        self._temporary = tempfile.TemporaryDirectory(prefix='ddarm-graph-') if folder is None else None
        self.folder = Path(folder if folder is not None else self._temporary.name)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.timeout = timeout
        self.processes: dict[str, subprocess.Popen] = {}
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.driver = GraphDriver(context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.driver)
        self._start('plant', ['ddarm_sim.node'], {'autostart': False, 'required_subscribers': GRAPH_SUBSCRIBERS,
                                                   'command_timeout': COMMAND_TIMEOUT})

    def _start(self, name: str, module: list[str], parameters: dict) -> None:
        path = self.folder / f'{name}.parameters.yaml'
        path.write_text(yaml.safe_dump({name: {'ros__parameters': parameters}}))
        log = open(self.folder / f'{name}.log', 'w')
        self.processes[name] = subprocess.Popen(
            [sys.executable, '-m', *module, '--ros-args', '--params-file', str(path)],
            stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy())
        log.close()

    def _use_controller(self, law: str, spec: EpisodeSpec) -> None:
        for other in CONTROLLERS:
            if other != law and other in self.processes:
                self._stop(other)
        if law not in self.processes:
            self._start(law, ['ddarm_control.node', law], {'kp': list(spec.kp), 'kv': list(spec.kv)})

    def check_alive(self) -> None:
        for name, process in self.processes.items():
            if process.poll() is not None:
                tail = (self.folder / f'{name}.log').read_text()[-2000:]
                raise GraphEpisodeError(f'the {name} node exited with code {process.returncode}:\n{tail}')

    def run(self, spec: EpisodeSpec, plan: EpisodePlan | None = None, bag: EpisodeBagWriter | None = None,
            realtime: bool = False) -> EpisodeResult:
        self._use_controller(spec.controller, spec)
        return self.driver.run_episode(self.executor, spec, plan, bag, 'realtime' if realtime else 'lockstep',
                                       self.timeout, alive=self.check_alive)

    def _stop(self, name: str) -> None:
        process = self.processes.pop(name)
        if process.poll() is None:
            process.send_signal(subprocess.signal.SIGINT)
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def close(self) -> None:
        for name in list(self.processes):
            self._stop(name)
        self.executor.shutdown()
        self.driver.destroy_node()
        rclpy.try_shutdown(context=self.context)
        if self._temporary is not None:
            self._temporary.cleanup()

    def __enter__(self) -> GraphSession:
        return self

    def __exit__(self, *exception) -> None:
        self.close()


def record_and_score(session: GraphSession, spec: EpisodeSpec, bag: Path, storage: str = 'mcap',
                     command: str | None = None) -> tuple[EpisodeResult, dict]:
    """Run `spec` through the graph in lockstep, record it at `bag`, and score it from the bag alone.

    Returns what the driver heard and the bag's score (the JSON of `ddarm score`); the bag is
    closed and marked complete or incomplete whatever happens.
    """
    from ddarm_tuner.bags import score_bag

    plan = plan_episode(spec)
    writer = EpisodeBagWriter(bag, episode_record(spec, plan, 'ros-lockstep', command), storage)
    with writer:
        result = session.run(spec, plan, writer)
        writer.close(complete=True)
    return result, score_bag(bag)


def run_graph_episode(spec: EpisodeSpec, realtime: bool = False, timeout: float = 120.0,
                      bag: Path | str | None = None, storage: str = 'mcap', command: str | None = None,
                      ) -> EpisodeResult:
    """Run `spec` through plant and controller processes over DDS and score what the driver recorded.

    With `bag`, the episode is also recorded there; the bag is closed (and marked complete or
    incomplete) whatever happens, so a killed or failed run never passes for a good one.
    """
    plan = plan_episode(spec)
    transport = 'ros-realtime' if realtime else 'ros-lockstep'
    writer = None if bag is None else EpisodeBagWriter(bag, episode_record(spec, plan, transport, command),
                                                       storage)
    complete = False
    try:
        with GraphSession(timeout=timeout) as session:
            result = session.run(spec, plan, writer, realtime)
        complete = True
    finally:
        if writer is not None:
            writer.close(complete)
    return result
