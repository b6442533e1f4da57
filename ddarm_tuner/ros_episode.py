"""One episode run through the ROS 2 graph: plant and controller nodes, driven and recorded by a driver node."""

from __future__ import annotations

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
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ddarm_sim.ros_interface import (CLOCK_QOS, CLOCK_TOPIC, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC,
                                     EFFORT_COMMAND_TOPIC, JOINT_STATES_TOPIC, REFERENCE_QOS, REFERENCE_TOPIC,
                                     SAMPLE_QOS, MessageError, read_joint_state, reference_msg)
from ddarm_tuner.bags import EpisodeBagWriter
from ddarm_tuner.episodes import EpisodePlan, EpisodeResult, EpisodeSpec, load_arm, plan_episode, score

# Lockstep waits this long (wall clock) for a command before the plant ends the episode.
COMMAND_TIMEOUT = 10.0


class GraphEpisodeError(RuntimeError):
    """An episode over ROS that did not complete; the text says which sample and why."""


def node_parameters(spec: EpisodeSpec, plan: EpisodePlan, mode: str = 'lockstep',
                    required_subscribers: int = 2) -> dict:
    """The parameter YAML (node: ros__parameters:) that makes the plant and controller run `spec`."""
    plant = {
        'mode': mode, 'period': spec.period, 'substeps': spec.substeps, 'command_timeout': COMMAND_TIMEOUT,
        'required_subscribers': required_subscribers, 'max_samples': plan.k_max + 1, 'autostart': False,
        'trajectory': spec.trajectory, 'duration': spec.duration, 'tau': spec.tau,
    }
    optional = {'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
                'viscous_friction': spec.viscous_friction, 'coulomb_friction': spec.coulomb_friction,
                'external_torque': spec.external_torque, 'mass_scale': spec.mass_scale}
    plant.update({name: [float(x) for x in value] for name, value in optional.items() if value is not None})
    controller = {'kp': list(spec.kp), 'kv': list(spec.kv), 'compute_delay_steps': spec.delay,
                  'period': spec.period}
    # The in-process runner gives computed torque the plant's friction as its model F̂; so does this.
    controller.update({name: list(getattr(spec, name)) for name in ('viscous_friction', 'coulomb_friction')
                       if getattr(spec, name) is not None})
    if spec.urdf:
        plant['urdf'] = controller['urdf'] = spec.urdf
    return {'plant': {'ros__parameters': plant}, spec.controller: {'ros__parameters': controller}}


@dataclass
class Recording:
    """What the driver heard: states (with applied effort) and commands, by sample index."""

    states: dict = field(default_factory=dict)
    commands: dict = field(default_factory=dict)
    diverged_at: int | None = None
    last_state_heard: bool = False
    plant_report: dict | None = None  # the plant's end-of-episode diagnostics (complete or diverged)
    error: str | None = None
    diagnostics: list = field(default_factory=list)

    @property
    def ended(self) -> bool:
        return self.error is not None or (self.last_state_heard and self.plant_report is not None)


def _stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class EpisodeDriver(Node):
    """Publishes the programmed motion, resets controller then plant, and records the episode's samples.

    With a bag writer, every message it publishes or hears goes into the bag as the CDR that
    crossed DDS, timestamped with its simulated time.
    """

    def __init__(self, spec: EpisodeSpec, plan: EpisodePlan, plant_node: str = 'plant',
                 bag: EpisodeBagWriter | None = None, **kwargs) -> None:
        super().__init__('ddarm_episode_driver', **kwargs)
        self.spec, self.plan, self.bag = spec, plan, bag
        self.joints = load_arm(spec.urdf).joint_names
        self.recording = Recording()
        self.reference_publisher = self.create_publisher(JointTrajectory, REFERENCE_TOPIC, REFERENCE_QOS)
        self.create_subscription(JointState, JOINT_STATES_TOPIC, self._on_state, SAMPLE_QOS)
        self.create_subscription(JointState, EFFORT_COMMAND_TOPIC, self._on_command, SAMPLE_QOS)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, DIAGNOSTICS_QOS)
        if bag is not None:
            self.create_subscription(Clock, CLOCK_TOPIC, self._on_clock, CLOCK_QOS)
        self.plant_reset = self.create_client(Trigger, f'/{plant_node}/reset')
        self.controller_reset = self.create_client(Trigger, f'/{spec.controller}/reset')

    def _record(self, topic: str, stamp, msg) -> None:
        if self.bag is not None:
            self.bag.write(topic, _stamp_ns(stamp), serialize_message(msg))

    def _on_clock(self, msg: Clock) -> None:
        self._record(CLOCK_TOPIC, msg.clock, msg)

    def _on_state(self, msg: JointState) -> None:
        self._record('/' + JOINT_STATES_TOPIC, msg.header.stamp, msg)
        try:
            sample = read_joint_state(msg, self.joints, self.spec.period, need_state=False)
        except MessageError as error:
            self.get_logger().error(f'unusable joint state: {error}')
            return
        if sample.q is None:  # the plant diverged during the period before this stamp
            self.recording.diverged_at = sample.n
            self.recording.last_state_heard = True
        self.recording.states[sample.n] = sample
        if sample.n >= self.plan.k_max + 1:
            self.recording.last_state_heard = True

    def _on_command(self, msg: JointState) -> None:
        self._record('/' + EFFORT_COMMAND_TOPIC, msg.header.stamp, msg)
        try:
            sample = read_joint_state(msg, self.joints, self.spec.period, 'command', need_state=False,
                                      need_effort=True)
        except MessageError as error:
            self.get_logger().error(f'unusable command: {error}')
            return
        self.recording.commands[sample.n] = sample.effort

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self._record(DIAGNOSTICS_TOPIC, msg.header.stamp, msg)
        for status in msg.status:
            if status.name != 'ddarm/plant':
                continue
            values = {pair.key: pair.value for pair in status.values}
            self.recording.diagnostics.append({'message': status.message, **values})
            if values.get('event') in ('timeout', 'no_start'):
                self.recording.error = status.message
            elif values.get('event') in ('complete', 'diverged'):
                self.recording.plant_report = values

    def _spin_until(self, executor, done, deadline: float, what: str, alive=lambda: None) -> None:
        while not done():
            if time.monotonic() > deadline:
                raise GraphEpisodeError(f'timed out waiting for {what}')
            alive()
            executor.spin_once(timeout_sec=0.05)

    def _call(self, executor, client, deadline: float, alive):
        self._spin_until(executor, client.service_is_ready, deadline, f'service {client.srv_name}', alive)
        future = client.call_async(Trigger.Request())
        self._spin_until(executor, future.done, deadline, f'a reply from {client.srv_name}', alive)
        return future.result()

    def run(self, executor, timeout: float, alive=lambda: None) -> Recording:
        """Drive one episode; `alive` raises if a node process has died."""
        deadline = time.monotonic() + timeout
        plan = self.plan
        reference = reference_msg(self.joints, plan.times, plan.q_ref, plan.v_ref, plan.a_ref, plan.nominal)
        self.reference_publisher.publish(reference)
        self._record('/' + REFERENCE_TOPIC, reference.header.stamp, reference)
        reply = self._call(executor, self.controller_reset, deadline, alive)
        while not reply.success:  # the latched reference is still on its way
            executor.spin_once(timeout_sec=0.01)
            reply = self._call(executor, self.controller_reset, deadline, alive)
        reply = self._call(executor, self.plant_reset, deadline, alive)
        if not reply.success:
            raise GraphEpisodeError(f'the plant refused to start: {reply.message}')
        self._spin_until(executor, lambda: self.recording.ended, deadline, 'the episode to end', alive)
        if self.recording.error:
            raise GraphEpisodeError(self.recording.error)
        return self.recording


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


class NodeProcesses:
    """The plant and controller as separate processes, stopped (SIGINT, then SIGKILL) on exit."""

    def __init__(self, spec: EpisodeSpec, plan: EpisodePlan, folder: Path, mode: str) -> None:
        parameters = folder / 'parameters.yaml'
        parameters.write_text(yaml.safe_dump(node_parameters(spec, plan, mode)))
        self.logs = {name: folder / f'{name}.log' for name in ('plant', spec.controller)}
        commands = {
            'plant': [sys.executable, '-m', 'ddarm_sim.node'],
            spec.controller: [sys.executable, '-m', 'ddarm_control.node', spec.controller],
        }
        self.processes = {}
        for name, command in commands.items():
            with open(self.logs[name], 'w') as log:
                self.processes[name] = subprocess.Popen(
                    [*command, '--ros-args', '--params-file', str(parameters)],
                    stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy())

    def check_alive(self) -> None:
        for name, process in self.processes.items():
            if process.poll() is not None:
                tail = self.logs[name].read_text()[-2000:]
                raise GraphEpisodeError(f'the {name} node exited with code {process.returncode}:\n{tail}')

    def stop(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                process.send_signal(subprocess.signal.SIGINT)
        for process in self.processes.values():
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def episode_record(spec: EpisodeSpec, plan: EpisodePlan, transport: str, command: str | None) -> dict:
    """The configuration a bag carries, so that the bag alone says what was run."""
    return {'spec': spec.to_dict(), 'joints': load_arm(spec.urdf).joint_names, 'k_max': plan.k_max,
            'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
            'transport': transport, 'command': command,
            'node_parameters': node_parameters(spec, plan, transport.removeprefix('ros-'))}


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
    context = rclpy.Context()
    rclpy.init(context=context)
    complete = False
    try:
        with tempfile.TemporaryDirectory(prefix='ddarm-episode-') as folder:
            nodes = NodeProcesses(spec, plan, Path(folder), transport.removeprefix('ros-'))
            driver = EpisodeDriver(spec, plan, bag=writer, context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(driver)
            try:
                recording = driver.run(executor, timeout, alive=nodes.check_alive)
            finally:
                executor.shutdown()
                driver.destroy_node()
                nodes.stop()
        result = result_from_recording(spec, plan, recording)
        complete = True
    finally:
        rclpy.try_shutdown(context=context)
        if writer is not None:
            writer.close(complete)
    return result
