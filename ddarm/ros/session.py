"""A graph session: the plant and a controller as node processes in a namespace of their own, a driver
in this process, and the episodes run (and recorded, and scored from their bags) through them."""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import rclpy
import yaml

from ddarm.control.laws import CONTROLLERS
from ddarm.ros.driver import GraphDriver, GraphEpisodeError
from ddarm.ros.executors import node_executor
from ddarm.ros.lifetime import child_environment, stop_processes, tell_to_stop
from ddarm.ros.names import fully_qualified, namespace_arguments
from ddarm.ros.node_parameters import (COMMAND_TIMEOUT, GRAPH_SUBSCRIBERS, SchedulingOptions, arm_parameters,
                                       episode_record, gains_parameters)
from ddarm.recording.bags import EpisodeBagWriter, checked_output_path
from ddarm.episodes.engine import warm_up
from ddarm.episodes.result import Episodes
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, check_episode


# The DDS lease that a session's node processes announce (Fast DDS: `leaseDuration`, 20 s by default), and how
# often they renew it. A node process that ended is forgotten by discovery at once when its goodbye is heard, or
# when its lease runs out if the goodbye was lost (a loaded machine) or it was killed; the next law's start waits
# for that (GraphDriver.wait_until_gone), so the lease is a few seconds, well within DEPARTURE_TIMEOUT. A live node
# loses its place only after NODE_LEASE_S without one of its renewals, sent every NODE_LEASE_RENEWAL_S.
# A controller started for an episode template (`prepare`) runs the ω rule at the paper's ω until the driver sets
# an episode's gains: it needs gains to configure, and the template has none.
TEMPLATE_OMEGA = 15.0
NODE_LEASE_S = 5
NODE_LEASE_RENEWAL_S = 1
# Where Fast DDS reads a participant's default profile from (older and newer names); a user's own file is kept.
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
NODE_PROFILE = f"""<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="ddarm_session_node" is_default_profile="true">
    <rtps>
      <builtin>
        <discovery_config>
          <leaseDuration><sec>{NODE_LEASE_S}</sec></leaseDuration>
          <leaseAnnouncement><sec>{NODE_LEASE_RENEWAL_S}</sec></leaseAnnouncement>
        </discovery_config>
      </builtin>
    </rtps>
  </participant>
</profiles>
"""


def node_environment(folder: Path) -> dict:
    """The environment of a session's node process: child_environment, and a participant profile in `folder`
    that announces a lease of NODE_LEASE_S, unless the user gave Fast DDS a profile of their own."""
    environment = child_environment()
    if not any(environment.get(variable) for variable in PROFILE_VARIABLES):
        profile = folder / 'fastdds_profile.xml'
        if not profile.is_file():
            profile.write_text(NODE_PROFILE)
        environment[PROFILE_VARIABLES[0]] = str(profile)
    return environment


def session_namespace() -> str:
    """A namespace no other graph on this machine or network uses.

    A namespace per session is how ROS runs several robots on one domain: every topic and
    service of the session is its own, and the domain (which the user chose) stays as it is.
    """
    return f'/ddarm_{os.getpid()}_{secrets.token_hex(4)}'


class GraphSession:
    """The plant and a controller as separate processes over DDS, with a driver in this process.

    The session's nodes live in a namespace of their own (`session_namespace`), so two sessions,
    or a session and a user's graph, on one domain never hear each other. The node processes live
    as long as the session, so episodes cost no start-up, and no longer: they end when it closes
    and, should this process be killed, with it (`ddarm.ros.lifetime`). Switching controller
    stops the other law's process, because two laws would answer the same states. A node is
    built from its arm when it starts (the read-only `urdf` and `motion`): an episode of another
    arm restarts it with that arm's. `scheduling`: the real-time priority, cores and spin margin every episode
    sets on the nodes (None: whatever they have; they start with SCHED_OTHER on this process's cores).
    """

    def __init__(self, folder: Path | str | None = None, timeout: float = 120.0,
                 scheduling: SchedulingOptions | None = None) -> None:
        self._temporary = tempfile.TemporaryDirectory(prefix='ddarm-graph-') if folder is None else None
        self.folder = Path(folder if folder is not None else self._temporary.name)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.timeout = timeout
        self.scheduling = scheduling
        self.namespace = session_namespace()
        self.processes: dict[str, subprocess.Popen] = {}
        self._closed = False
        self._keep: Path | None = None
        self._stopping: list[subprocess.Popen] = []  # told to stop (stop_nodes), not yet waited for
        self.arms: dict[str, dict] = {}  # per node process: the read-only parameters it was started with
        self.context = rclpy.Context()
        # A context of our own (rclpy installs no signal handler for it), given no arguments: ddarm's command line
        # holds none for ROS, and rclpy.init would read sys.argv, whose non-UTF-8 bytes it cannot encode.
        rclpy.init(args=[], context=self.context)
        self.driver = GraphDriver(namespace=self.namespace, context=self.context)
        self.executor = node_executor(self.context)
        self.executor.add_node(self.driver)
        try:
            # The nodes run the compiled loop: built (or loaded from numba's cache) here first, so that
            # on a fresh checkout the node processes load it instead of compiling it past their peer timeout.
            warm_up()
        except BaseException:
            self.close()
            raise

    def _start(self, name: str, module: list[str], parameters: dict, arm: dict) -> None:
        path = self.folder / f'{name}.parameters.yaml'
        given = {**parameters, **{key: value for key, value in arm.items() if value}}  # '': the node's default
        path.write_text(yaml.safe_dump({fully_qualified(name, self.namespace): {'ros__parameters': given}}))
        with open(self.folder / f'{name}.log', 'a') as log:  # appended: a node restarted for another arm
            # A session of its own: a Ctrl-C in the terminal reaches this process, which stops its nodes in order.
            self.processes[name] = subprocess.Popen(
                [sys.executable, '-m', *module, '--ros-args', *namespace_arguments(self.namespace),
                 '--params-file', str(path)],
                stdout=log, stderr=subprocess.STDOUT, env=node_environment(self.folder), start_new_session=True)
        self.arms[name] = dict(arm)

    def use_nodes(self, spec: EpisodeSpec) -> None:
        """The plant and the `spec` law's controller running with the arm of `spec`: started (or restarted,
        for another URDF or motion file) unless they run with it already; the other law's process stopped."""
        law = spec.controller
        stopped = [other for other in CONTROLLERS if other != law and other in self.processes]
        arms = arm_parameters(spec)
        stopped += [name for name in ('plant', law) if name in self.processes and self.arms[name] != arms[name]]
        self._stop(*stopped)
        # Before another starts: a stopped node still on the graph would fail the next episode's check of it.
        self.driver.wait_until_gone(stopped)
        if 'plant' not in self.processes:
            self._start('plant', ['ddarm_sim.node'], {'autostart': False, 'required_subscribers': GRAPH_SUBSCRIBERS,
                                                       'command_timeout': COMMAND_TIMEOUT}, arms['plant'])
        if law not in self.processes:
            gains = {'omega': TEMPLATE_OMEGA} if spec.is_template else gains_parameters(spec)
            self._start(law, ['ddarm_control.node', law], gains, arms[law])

    def prepare(self, spec: EpisodeSpec) -> None:
        """The nodes of `spec` started (`use_nodes`) without waiting for them: they come up while this process works."""
        self.use_nodes(spec)

    def check_alive(self) -> None:
        for name, process in self.processes.items():
            if process.poll() is not None:
                tail = (self.folder / f'{name}.log').read_text()[-2000:]
                raise GraphEpisodeError(f'the {name} node ({fully_qualified(name, self.namespace)}) exited with '
                                        f'code {process.returncode}:\n{tail}')

    def ready(self, spec: EpisodeSpec) -> None:
        """The plant and the `spec` law's controller running with its arm, and both on the graph, alone."""
        self.use_nodes(spec)
        self.driver.wait_for_peers(self.executor, spec.controller, alive=self.check_alive)

    def open_bag(self, path: Path | str, spec: EpisodeSpec, plan: EpisodePlan, transport: str, storage: str,
                 command: str | None) -> EpisodeBagWriter:
        """A bag for the next episode of `spec`, once its nodes are up (the bag records what they offer)."""
        self.ready(spec)
        return self.driver.open_bag(path, episode_record(spec, plan, transport, command, self.scheduling), storage)

    def run(self, spec: EpisodeSpec, plan: EpisodePlan | None = None, bag: EpisodeBagWriter | None = None,
            realtime: bool = False) -> Episodes:
        self.use_nodes(spec)
        return self.driver.run_episode(self.executor, spec, plan, bag, 'realtime' if realtime else 'lockstep',
                                       self.timeout, alive=self.check_alive, scheduling=self.scheduling)

    def record_and_score(self, spec: EpisodeSpec, bag: Path, command: str | None = None, storage: str = 'mcap'
                         ) -> tuple[Episodes, dict]:
        """`record_and_score` on this session: run `spec` in lockstep, record it at `bag`, score the bag."""
        return record_and_score(self, spec, bag, storage=storage, command=command)

    def _released(self, names) -> list[subprocess.Popen]:
        """The processes of the nodes `names`, no longer the session's."""
        for name in names:
            self.arms.pop(name, None)
        return [self.processes.pop(name) for name in names]

    def _stop(self, *names: str, signalled=()) -> None:
        stop_processes(self._released(names), timeout=5, signalled=signalled)

    def stop_nodes(self) -> None:
        """Tell every node to stop, without waiting: they leave the graph while this process goes on; close waits."""
        released = self._released(list(self.processes))
        tell_to_stop(released)
        self._stopping += released

    def keep_files_in(self, folder: Path | str) -> None:
        """Where closing copies the session's folder (the nodes' logs, parameter files and DDS profile, complete once
        they stopped), whether the session ends well or not: for a session that started before its run's folder."""
        self._keep = Path(folder)

    def close(self) -> None:
        """Stop the nodes (all at once), leave the graph, keep the session's files (keep_files_in). A second close
        does nothing."""
        if self._closed:
            return
        self._closed = True
        self._stop(*list(self.processes), signalled=self._stopping)
        self.executor.shutdown()
        self.driver.destroy_node()
        rclpy.try_shutdown(context=self.context)
        if self._keep is not None:
            shutil.copytree(self.folder, self._keep, dirs_exist_ok=True)
        if self._temporary is not None:
            self._temporary.cleanup()

    def __enter__(self) -> GraphSession:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if error is None:
            self.close()
            return
        try:  # a failure to stop cleanly must not hide why the session ended
            self.close()
        except Exception as cleanup:
            error.add_note(f'while closing the graph session: {type(cleanup).__name__}: {cleanup}')


def record_and_score(session: GraphSession, spec: EpisodeSpec, bag: Path, storage: str = 'mcap',
                     command: str | None = None) -> tuple[Episodes, dict]:
    """Run `spec` through the graph in lockstep, record it at `bag`, and score it from the bag alone.

    Returns what the driver heard and the bag's score (the JSON of `ddarm score`); the bag is
    closed and marked complete or incomplete whatever happens.
    """
    from ddarm.recording.bags import score_bag

    plan = check_episode(spec)
    with session.open_bag(bag, spec, plan, 'ros-lockstep', storage, command) as writer:
        result = session.run(spec, plan, writer)
        writer.close(complete=True)
    return result, score_bag(bag)


def run_graph_episode(spec: EpisodeSpec, realtime: bool = False, timeout: float = 120.0,
                      bag: Path | str | None = None, storage: str = 'mcap', command: str | None = None,
                      scheduling: SchedulingOptions | None = None) -> Episodes:
    """Run `spec` through plant and controller processes over DDS and score what the driver recorded.

    With `bag`, the episode is also recorded there; the bag is closed (and marked complete or
    incomplete) whatever happens, so a killed or failed run never passes for a good one.
    `scheduling`: the nodes' real-time priority, cores and spin margin (GraphSession).
    """
    plan = check_episode(spec)
    if bag is not None:
        checked_output_path(bag)  # refused before any node starts
    transport = 'ros-realtime' if realtime else 'ros-lockstep'
    with GraphSession(timeout=timeout, scheduling=scheduling) as session:
        if bag is None:
            return session.run(spec, plan, realtime=realtime)
        with session.open_bag(bag, spec, plan, transport, storage, command) as writer:
            result = session.run(spec, plan, writer, realtime)
            writer.close(complete=True)
        return result
