"""The driver: a node that checks the graph, configures the plant and a controller through their
parameter services, publishes the programmed motion, runs the episode, records it (optionally as a
bag) and scores what it heard. The node processes it drives are started by `ddarm.ros.session`."""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ddarm.control.laws import CONTROLLERS
from ddarm.errors import DdarmError
from ddarm.ros.interface import (CLOCK_QOS, CLOCK_TOPIC, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC,
                                 EFFORT_COMMAND_TOPIC, JOINT_STATES_TOPIC, REFERENCE_QOS, REFERENCE_TOPIC,
                                 SAMPLE_QOS, read_joint_state, reference_msg, sample_index)
from ddarm.ros.cdr import decode_joint_state, read_stamp
from ddarm.ros.names import fully_qualified, namespace_arguments
from ddarm.ros.node_parameters import (COMMAND_TIMEOUT, CONTROLLER_OPTIONAL, PLANT_OPTIONAL,
                                       SchedulingOptions, arm_parameters, node_parameters, same_read_only,
                                       service_parameters)
from ddarm.samples import DEFAULT_PERIOD, MessageError, stamp_ns
from ddarm.recording.bags import BagError, EpisodeBagWriter
from ddarm.episodes.result import Episodes, RecordingError
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, check_episode
from ddarm.interrupts import check_stop
from ddarm.ros.parameter_schema import PEER_TIMEOUT

# How often the graph is checked while an episode runs, and how long a node may be missing from
# it before the episode fails (discovery can lag a little; a foreign publisher fails at once).
GRAPH_CHECK_PERIOD = 0.5
# A driver trusts its look at the graph only once its DDS participant is this old: a context's participant is made
# with its first node (and destroyed with its last), and discovers the others one by one, so a fresh one can see the
# plant and one controller before the second controller on the domain. A driver whose nodes came up while its process
# searched is that old by then, and waits no more.
DISCOVERY_SETTLE = 1.0
PEER_LOSS_GRACE = 1.0
# A node process that ended is gone from the graph once discovery forgets it: at once when its participant's
# goodbye is heard, or when its lease runs out if that was lost or the process was killed (a session's nodes
# announce 5 s, ddarm.ros.session.NODE_LEASE_S; Fast DDS's default is 20 s, a hand-started node's).
DEPARTURE_TIMEOUT = 25.0
# A plant that owes the next state (its command was heard) and sends nothing for this long has
# stalled or died; DDS itself notices a killed process only after its 20 s lease.
PLANT_STALL_TIMEOUT = 5.0
# Waiting on the controller, the plant reports its own command timeout; nothing at all for this
# long means that report is lost too.
STALL_TIMEOUT = COMMAND_TIMEOUT + 5.0
# Before the plant starts an episode, the states and commands still in flight from the one before
# (a controller that was slow or stopped answers late) must have arrived: this long without any.
QUIET_PERIOD = 0.05
# While the driver waits, it checks the node processes and the graph at most this often (wall s), not at every
# message: the checks cost tens of µs, a lockstep sample a few hundred.
WATCH_PERIOD = 0.01
# Messages recorded before the driver writes them to the bag: a write of this many takes a few ms, far less than the
# samples that the topics' QoS depth keeps while the driver is busy with it.
UNWRITTEN_LIMIT = 256
# Who reads the controller's commands in an episode: the plant and this driver's recorder.
COMMAND_SUBSCRIBERS = 2
# A request that may be repeated (parameters read or set, a controller's reset or status) is sent again after this
# many wall seconds without a reply.
RESEND_AFTER = 5.0
# What the graph API says of an endpoint whose node it has not learnt yet.
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'
# The topics every ROS node publishes by default (rcl's parameter events and log).
GLOBAL_NODE_TOPICS = ('/parameter_events', '/rosout')
# The topics of every sample, heard from sample 0 on.
RECORDED_SAMPLE_TOPICS = ('/' + JOINT_STATES_TOPIC, '/' + EFFORT_COMMAND_TOPIC, CLOCK_TOPIC)
# The profile each recorded topic's publisher declares (ddarm.ros.interface).
TOPIC_QOS = {'/' + JOINT_STATES_TOPIC: SAMPLE_QOS, '/' + EFFORT_COMMAND_TOPIC: SAMPLE_QOS,
             '/' + REFERENCE_TOPIC: REFERENCE_QOS, CLOCK_TOPIC: CLOCK_QOS, DIAGNOSTICS_TOPIC: DIAGNOSTICS_QOS}
# Plant counters that make a lockstep episode, or a real-time one, a failed episode: a command the
# plant refused, one for a sample it had passed, or a second one for a sample (a foreign publisher).
FAILING_COUNTERS = {'lockstep': ('refused_commands', 'stale_commands', 'duplicate_commands'),
                    'realtime': ('refused_commands', 'duplicate_commands')}
REPORT_COUNTERS = tuple(sorted({name for names in FAILING_COUNTERS.values() for name in names}))


def spin_once(executor, timeout: float) -> None:
    """executor.spin_once, a stop by signal kept a stop: Interrupted raised inside rclpy's C++ (a message being
    built) comes out as a SystemError of its own, which check_stop turns back into the stop it was."""
    try:
        executor.spin_once(timeout_sec=timeout)
    except Exception:
        check_stop()
        raise


class GraphEpisodeError(DdarmError, RuntimeError):
    """An episode over ROS that did not complete; the text says which sample and why."""


@dataclass
class Recording:
    """What the driver heard during one episode: states and commands by sample, as the CDR that crossed DDS.

    They are read (`result_from_recording`) once the episode has ended; while it runs, only their
    stamps are (`ddarm.ros.cdr.read_stamp`).
    """

    k_max: int
    controller: str
    states: dict = field(default_factory=dict)
    commands: dict = field(default_factory=dict)
    diverged_at: int | None = None  # the sample of the plant's last state, which has no position, by its report
    plant_report: dict | None = None  # the plant's end-of-episode diagnostics (complete or diverged)
    error: str | None = None
    last_heard: float = field(default_factory=time.monotonic)  # wall time of the last state or command
    clock_ticks: set = field(default_factory=set)  # the samples whose /clock tick was heard
    latest_state: int | None = None  # the sample of the latest state heard (they come in order)

    @property
    def last_state(self) -> int:
        """The sample of the plant's last state: k_max + 1, or the one that says it diverged."""
        return self.k_max + 1 if self.diverged_at is None else self.diverged_at

    @property
    def ended(self) -> bool:
        """An error, or the last state, the plant's report and every scored command all heard.

        Topics are not ordered among themselves: the plant's last state can arrive before the
        command it applied, and its report before its last state.
        """
        if self.error is not None:
            return True
        # The plant ticks /clock with every state it integrated to (not with a diverged one): all in the bag. Ticks
        # are those of samples 0..k_max + 1, and none comes after a diverged state: all of them are there.
        ticked = self.last_state if self.diverged_at is None else self.last_state - 1
        return (self.plant_report is not None and self.last_state in self.states
                and len(self.commands) >= self.last_state and len(self.clock_ticks) > ticked)

    def fail(self, message: str) -> None:
        """Keep the first problem: it is the cause, later ones its consequences."""
        if self.error is None:
            self.error = message

    def owed_by_plant(self) -> bool:
        """The command for the latest state has come: the next message must be the plant's."""
        return self.latest_state is not None and self.latest_state in self.commands

    def heard(self) -> str:
        """What came, for a message that says why an episode did not end."""
        return (f'heard states up to sample {self.latest_state}, {len(self.commands)} of {self.k_max + 1} commands, '
                f"{len(self.clock_ticks)} clock ticks, {'a' if self.plant_report else 'no'} plant report")


def qos_description(profile) -> dict:
    """An rclpy QoS profile as the bag's offered_qos_profiles entry."""
    return {'reliability': profile.reliability.name.lower(), 'durability': profile.durability.name.lower(),
            'history': profile.history.name.lower(), 'depth': int(profile.depth)}


class GraphDriver(Node):
    """Runs episodes on a running plant and controller node, one at a time, and records them.

    Before and while an episode runs it checks the graph: the plant and the controller must be
    there once each, and the only publishers of the episode's topics; two messages for one sample,
    or a plant that refused or dropped a command, fail the episode. With a bag writer, every
    message it publishes or hears during the episode goes into the bag as the CDR that crossed
    DDS, timestamped with its simulated time.
    """

    def __init__(self, name: str = 'ddarm_episode_driver', plant_node: str = 'plant', namespace: str = '',
                 **kwargs) -> None:
        rules = namespace_arguments(namespace)[2:]  # the node's own namespace is set directly
        super().__init__(name, namespace=namespace or None, cli_args=['--ros-args', *rules] if rules else None,
                         **kwargs)
        self.plant_node = plant_node
        self.joints: list[str] = []  # the episode's joints (its plan's), in the order of every per-joint array
        self.recording: Recording | None = None
        self.bag: EpisodeBagWriter | None = None
        self.period = DEFAULT_PERIOD  # until an episode sets its own
        self.reference_publisher = self.create_publisher(JointTrajectory, REFERENCE_TOPIC, REFERENCE_QOS)
        self.subscriptions_by_topic = {
            # The messages of every sample come serialized: what the bag records, read whole only after the episode.
            # A listener that deserialises them as they come takes CPU time from the loop it listens to (a third
            # of the round trips of two processes, measured with one beside them).
            '/' + JOINT_STATES_TOPIC: self.create_subscription(JointState, JOINT_STATES_TOPIC, self._on_state,
                                                               SAMPLE_QOS, raw=True),
            '/' + EFFORT_COMMAND_TOPIC: self.create_subscription(JointState, EFFORT_COMMAND_TOPIC,
                                                                 self._on_command, SAMPLE_QOS, raw=True),
            DIAGNOSTICS_TOPIC: self.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics,
                                                        DIAGNOSTICS_QOS),
            CLOCK_TOPIC: self.create_subscription(Clock, CLOCK_TOPIC, self._on_clock, CLOCK_QOS, raw=True),
        }
        self.parameter_clients = {plant_node: AsyncParameterClient(self, plant_node)}
        self.reset_clients = {plant_node: self.create_client(Trigger, f'{plant_node}/reset')}
        self.status_clients = {}
        for law in CONTROLLERS:
            self.parameter_clients[law] = AsyncParameterClient(self, law)
            self.reset_clients[law] = self.create_client(Trigger, f'{law}/reset')
            self.status_clients[law] = self.create_client(Trigger, f'{law}/status')
        self._next_graph_check = 0.0
        self._discovered_by = time.monotonic() + DISCOVERY_SETTLE  # its participant is made with it
        self._peer_missing_since: float | None = None
        self.last_traffic = 0.0  # wall time of the last state or command heard, in an episode or not
        self._unwritten: list[tuple[str, int, bytes]] = []  # (topic, stamp ns, CDR) recorded, not yet in the bag

    def node_name(self, name: str) -> str:
        """The fully qualified name of a node `name` in this driver's namespace."""
        return fully_qualified(name, self.get_namespace())

    # The graph -------------------------------------------------------------------------------

    def topic_owners(self, law: str) -> dict[str, tuple[str, str]]:
        """Bag topic -> (resolved topic, the one node that may publish it) for an episode of `law`."""
        owners = {'/' + JOINT_STATES_TOPIC: self.plant_node, '/' + EFFORT_COMMAND_TOPIC: law,
                  CLOCK_TOPIC: self.plant_node, DIAGNOSTICS_TOPIC: self.plant_node}
        topics = {topic: (self.subscriptions_by_topic[topic].topic_name, self.node_name(owner))
                  for topic, owner in owners.items()}
        topics['/' + REFERENCE_TOPIC] = (self.reference_publisher.topic_name, self.get_fully_qualified_name())
        return topics

    def publishers(self, law: str) -> dict[str, list[str]]:
        """Bag topic -> the fully qualified names of the nodes publishing it now."""
        return {topic: [fully_qualified(info.node_name, info.node_namespace)
                        for info in self.get_publishers_info_by_topic(resolved)]
                for topic, (resolved, _) in self.topic_owners(law).items()}

    def graph_nodes(self) -> Counter:
        """The fully qualified name of every node on the graph, with how many nodes bear it: nodes as their endpoints
        show them, one per name and DDS participant (the first 12 bytes of an endpoint's GID, its GUID prefix).

        Not the graph's list of node names: discovery can keep a node's name after its process ended, without any
        endpoint, for good (its word of the node, heard after its participant's goodbye, adds it back; seen on a
        busy machine), and a name that owns no endpoint can do nothing on the graph. The topics read are this
        driver's namespace's and the two every ROS node has endpoints on unless told otherwise (a few ms in all).
        """
        prefix = self.get_namespace().rstrip('/') + '/'
        topics = [topic for topic, _ in self.get_topic_names_and_types()
                  if topic.startswith(prefix) or topic in GLOBAL_NODE_TOPICS]
        nodes = set()
        for topic in topics:
            for info in (*self.get_publishers_info_by_topic(topic), *self.get_subscriptions_info_by_topic(topic)):
                if UNKNOWN_NODE not in info.node_name:
                    nodes.add((fully_qualified(info.node_name, info.node_namespace), bytes(info.endpoint_gid[:12])))
        return Counter(name for name, _ in nodes)

    def graph_problems(self, law: str) -> tuple[list[str], list[str]]:
        """(foreign, missing): what is on the graph that must not be, and who is not there yet."""
        names = self.graph_nodes()
        foreign, missing = [], []
        for node, role in ((self.node_name(self.plant_node), 'plant'), (self.node_name(law), 'controller')):
            if names[node] == 0:
                missing.append(f'no {role} node {node} on the graph')
            elif names[node] > 1:
                foreign.append(f'{names[node]} nodes are named {node}: a second {role} on this domain')
        me = self.get_fully_qualified_name()
        if names[me] > 1:
            foreign.append(f'{names[me]} nodes are named {me}: a second driver on this domain')
        for other in CONTROLLERS:
            if other != law and names[self.node_name(other)]:
                foreign.append(f'{self.node_name(other)} is running too: two laws would answer the same states')
        heard = self.publishers(law)
        for topic, (resolved, owner) in self.topic_owners(law).items():
            if topic == DIAGNOSTICS_TOPIC:
                continue  # many nodes publish diagnostics; only the plant's own status is read
            # Discovery can name an endpoint's node a moment after the endpoint: alone, it is ours not yet known.
            others = [node for node in heard[topic] if node != owner and UNKNOWN_NODE not in node]
            if others or len(heard[topic]) > 1:
                foreign.append(f'{resolved} is published by {sorted(heard[topic])}; only {owner} may publish it '
                               f'(foreign: {sorted(set(others))})')
            elif heard[topic] != [owner]:
                missing.append(f'nobody known publishes {resolved} (expected {owner}; heard {heard[topic]})')
        return foreign, missing

    def wait_for_peers(self, executor, law: str, timeout: float = PEER_TIMEOUT, alive=lambda: None) -> None:
        """Until the plant and the `law` controller are on the graph, alone; names what is wrong if they never are."""
        deadline = time.monotonic() + timeout
        while True:
            check_stop()
            foreign, missing = self.graph_problems(law)
            if not foreign and not missing:
                # Settling is caution: never a refusal of a ready graph.
                if time.monotonic() >= min(self._discovered_by, deadline):
                    return
            elif time.monotonic() > deadline:
                raise GraphEpisodeError('the graph is not ready for an episode: ' + '; '.join(foreign + missing))
            if not self.context.ok():
                raise ExternalShutdownException('shut down while waiting for the plant and controller')
            alive()
            spin_once(executor, 0.05)

    def wait_until_gone(self, nodes: list[str], timeout: float = DEPARTURE_TIMEOUT) -> None:
        """Until no node of `nodes` (names in this driver's namespace, their processes ended) is on the graph.

        A participant that leaves says so, and discovery forgets it at once; one whose word was lost (a
        loaded machine) or that was killed is forgotten when its lease runs out.
        """
        deadline = time.monotonic() + timeout
        while True:
            check_stop()
            present = self.graph_nodes()
            lingering = [self.node_name(node) for node in nodes if self.node_name(node) in present]
            if not lingering:
                return
            if time.monotonic() > deadline:
                raise GraphEpisodeError(f'{", ".join(lingering)} still on the graph {timeout:.0f} s after its process '
                                        'ended: another node of that name on this domain?')
            time.sleep(0.05)

    def _watch_graph(self, law: str) -> None:
        """While an episode runs: a foreign publisher or duplicate node fails it at once, a lost peer after a grace."""
        now = time.monotonic()
        if now < self._next_graph_check:
            return
        self._next_graph_check = now + GRAPH_CHECK_PERIOD
        foreign, missing = self.graph_problems(law)
        if foreign:
            raise GraphEpisodeError('foreign nodes on the episode\'s graph: ' + '; '.join(foreign))
        if not missing:
            self._peer_missing_since = None
        elif self._peer_missing_since is None:
            self._peer_missing_since = now
        elif now - self._peer_missing_since > PEER_LOSS_GRACE:
            raise GraphEpisodeError('a node left the graph during the episode (did it die?): ' + '; '.join(missing))

    def open_bag(self, path: Path | str, episode: dict, storage: str = 'mcap', law: str | None = None
                 ) -> EpisodeBagWriter:
        """A bag for the next episode, with the QoS each topic's publishers offer (call once the graph is checked).

        DDS discovery does not carry history and depth, so the graph cannot tell them: the profiles
        are the ones ddarm's nodes declare, one per publisher the graph shows (the check allows one).
        """
        law = law or episode['spec']['controller']
        heard = self.bag_publishers(law)
        offered = {topic: [qos_description(TOPIC_QOS[topic])] * len(heard[topic]) for topic in heard}
        return EpisodeBagWriter(path, episode, storage, offered_qos=offered)

    def bag_publishers(self, law: str) -> dict[str, list[str]]:
        """The publishers of what the bag records: of /diagnostics only the plant's status is recorded."""
        heard = self.publishers(law)
        plant = self.node_name(self.plant_node)
        heard[DIAGNOSTICS_TOPIC] = [node for node in heard[DIAGNOSTICS_TOPIC] if node == plant]
        return heard

    # What the graph says --------------------------------------------------------------------

    def _record(self, topic: str, stamp, data: bytes) -> None:
        # Kept, and written to the bag in batches (`_write_bag`): a bag write costs as much as the rest of a
        # message's handling, and batched it stays off the path of most samples.
        if self.bag is not None and self.recording is not None:
            self._unwritten.append((topic, stamp_ns(stamp), data))
            if len(self._unwritten) >= UNWRITTEN_LIMIT:
                self._write_bag()

    def _write_bag(self) -> None:
        """Write the messages recorded and not yet written, in the order heard."""
        unwritten, self._unwritten = self._unwritten, []
        if self.bag is not None:
            for topic, stamp, data in unwritten:
                self.bag.write(topic, stamp, data)

    def _on_clock(self, data: bytes) -> None:
        if self.recording is None:
            return
        heard = self._sample_of(data, f'clock message on {CLOCK_TOPIC}')
        if heard is not None and heard[1] <= self.recording.k_max + 1:
            self._record(CLOCK_TOPIC, heard[0], data)
            self.recording.clock_ticks.add(heard[1])

    def _sample_of(self, data: bytes, what: str) -> tuple[object, int] | None:
        """(stamp, sample n) of a serialized state or command; None, the episode failed, if it has none."""
        try:
            stamp = read_stamp(data, what)
            return stamp, sample_index(stamp, self.period)
        except MessageError as error:
            self.recording.fail(f'unusable {what}: {error}')
            return None

    def _on_state(self, data: bytes) -> None:
        self.last_traffic = time.monotonic()
        if self.recording is None:
            return
        topic = self.subscriptions_by_topic['/' + JOINT_STATES_TOPIC].topic_name
        heard = self._sample_of(data, f'joint state on {topic}')
        if heard is None:
            return
        stamp, n = heard
        if n > self.recording.k_max + 1:
            # Not a sample of this episode (the controllers refuse such stamps too): kept out of the bag.
            self.get_logger().warning(f'ignored a joint state for sample {n}, beyond the episode\'s last '
                                      f'sample {self.recording.k_max + 1}')
            return
        self._record('/' + JOINT_STATES_TOPIC, stamp, data)
        if n in self.recording.states:
            self.recording.fail(f'two joint states for sample {n}: a second publisher on {topic}?')
            return
        expected = 0 if self.recording.latest_state is None else self.recording.latest_state + 1
        if n != expected:  # one publisher, reliable: the plant's states come in order, one per sample
            self.recording.fail(f'a joint state for sample {n} where sample {expected} was due: '
                                f'a second publisher on {topic}?')
            return
        self.recording.last_heard = time.monotonic()
        self.recording.states[n] = data
        self.recording.latest_state = n

    def _on_command(self, data: bytes) -> None:
        self.last_traffic = time.monotonic()
        if self.recording is None:
            return
        topic = self.subscriptions_by_topic['/' + EFFORT_COMMAND_TOPIC].topic_name
        heard = self._sample_of(data, f'command on {topic}')
        if heard is None:
            return
        stamp, n = heard
        if n > self.recording.k_max:
            return  # the answer to the final state, or beyond it: never applied, not part of the episode
        self._record('/' + EFFORT_COMMAND_TOPIC, stamp, data)
        if n in self.recording.commands:
            self.recording.fail(f'two commands for sample {n}: a second publisher on {topic}?')
            return
        self.recording.last_heard = time.monotonic()
        self.recording.commands[n] = data

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if self.recording is None:
            return
        plant = self.node_name(self.plant_node)
        ours = [status for status in msg.status if status.name == 'ddarm/plant'
                and {pair.key: pair.value for pair in status.values}.get('node', plant) == plant]
        if not ours:
            return  # another node's diagnostics: not part of this episode
        self._record(DIAGNOSTICS_TOPIC, msg.header.stamp, serialize_message(msg))
        for status in ours:
            values = {pair.key: pair.value for pair in status.values}
            if values.get('event') == 'timeout':
                self.recording.fail(f'{plant}: {status.message}; {self._controller_note()}')
            elif values.get('event') == 'no_start':
                self.recording.fail(f'{plant}: {status.message}')
            elif values.get('event') in ('complete', 'diverged'):
                # Judged as it comes, not only at the end, where the plant's own report may have replaced it: a
                # report that does not parse, or a second one (the plant sends one per episode), is a foreign one.
                if self.recording.plant_report is not None:
                    self.recording.fail(f'two end-of-episode reports from {plant} on {DIAGNOSTICS_TOPIC}: a foreign '
                                        'publisher?')
                try:
                    plant_counters(values, REPORT_COUNTERS, plant)
                    if values['event'] == 'diverged':  # its last state is stamped a period after its last sample
                        self.recording.diverged_at = _reported_sample(values, self.recording.k_max, plant) + 1
                except GraphEpisodeError as error:
                    self.recording.fail(str(error))
                self.recording.plant_report = values

    def _controller_note(self) -> str:
        """Who kept the plant waiting: the controller, and whether it is still on the graph."""
        controller = self.node_name(self.recording.controller)
        last = max(self.recording.commands) if self.recording.commands else None
        present = controller in self.graph_nodes()
        return (f"the controller {controller} sent {'no command' if last is None else f'nothing after sample {last}'}"
                f" ({'still on the graph: stuck or refusing states?' if present else 'gone from the graph'})")

    def _stalled(self, mode: str) -> str | None:
        """Why an episode under way stopped moving, naming the node that owes a message; None while it moves."""
        waited = time.monotonic() - self.recording.last_heard

        def silent_plant(question: str) -> str:
            return (f'the plant {self.node_name(self.plant_node)} published nothing for {waited:.1f} s '
                    f'({self.recording.heard()}): {question}')

        if (mode == 'realtime' or self.recording.owed_by_plant()) and waited > max(PLANT_STALL_TIMEOUT,
                                                                                     5 * self.period):
            return silent_plant('did it die, or not hear the command?')
        if waited > STALL_TIMEOUT:
            # Before its first state the plant may wait for its subscribers, but it would have reported a start it
            # could not make by now: the state owed is its own, not a command (a plant killed just after starting).
            if self.recording.latest_state is None:
                return silent_plant('did it die before its first state?')
            return f'nothing heard for {waited:.1f} s ({self.recording.heard()}); {self._controller_note()}'
        return None

    # Driving --------------------------------------------------------------------------------

    def _spin_until(self, executor, done, deadline: float, what: str, alive) -> None:
        next_watch = 0.0
        while True:
            check_stop()
            if not self.context.ok():  # rclpy's signal handler shut the context down
                raise ExternalShutdownException(f'shut down while waiting for {what}')
            if done():
                return
            now = time.monotonic()
            if now > deadline:
                heard = f' ({self.recording.heard()})' if self.recording is not None else ''
                raise GraphEpisodeError(f'timed out waiting for {what}{heard}')
            if now >= next_watch:
                alive()
                next_watch = now + WATCH_PERIOD
            spin_once(executor, 0.05)

    def _answer(self, executor, send, deadline: float, what: str, alive, again: bool = True):
        """The reply to the request `send()` sends; with `again` (a request that may be repeated), sent again after
        each RESEND_AFTER s without a reply, and the last one's reply taken: a server drops its reply when the
        client's reader has not matched its writer yet, which a busy machine makes likely."""
        while True:
            future = send()
            resend_at = time.monotonic() + RESEND_AFTER if again else math.inf
            self._spin_until(executor, lambda: future.done() or time.monotonic() >= resend_at, deadline, what, alive)
            if future.done():
                return future.result()

    def _trigger(self, executor, client, deadline: float, alive, again: bool = True):
        """Call a std_srvs/Trigger service (a node's reset or status) and wait for its reply; `again`: as _answer."""
        self._spin_until(executor, client.service_is_ready, deadline, f'service {client.srv_name}', alive)
        return self._answer(executor, lambda: client.call_async(Trigger.Request()), deadline,
                            f'a reply from {client.srv_name}', alive, again)

    def _read_only(self, executor, node: str, names, deadline: float, alive) -> dict:
        """The node's read-only parameters `names` ('' for one it does not declare)."""
        client = self.parameter_clients[node]
        self._spin_until(executor, client.services_are_ready, deadline, f'the parameters of {self.node_name(node)}',
                         alive)
        values = {}
        for name in names:  # one at a time: a node answers a request naming an undeclared one with nothing
            answer = self._answer(executor, lambda: client.get_parameters([name]), deadline,
                                  f'parameter {name} of {self.node_name(node)}', alive).values
            values[name] = parameter_value_to_python(answer[0]) if answer else ''
        return values

    def _check_arm(self, executor, node: str, wanted: dict, deadline: float, alive) -> None:
        """The node was started with the episode's URDF and motion file (`arm_parameters`)."""
        started = self._read_only(executor, node, tuple(wanted), deadline, alive)
        differ = [f'{name} is {started[name]!r}, the episode\'s {wanted[name]!r}' for name in wanted
                  if not same_read_only(name, started[name], wanted[name])]
        if differ:
            raise GraphEpisodeError(f'{self.node_name(node)} runs another arm than the episode ({"; ".join(differ)}): '
                                    f'start it with the episode\'s read-only parameters {", ".join(wanted)}')

    def _configure(self, executor, node: str, parameters: list[Parameter], deadline: float, alive) -> None:
        client = self.parameter_clients[node]
        self._spin_until(executor, client.services_are_ready, deadline, f'the parameters of {self.node_name(node)}',
                         alive)
        # At once: a controller's gains by joint are taken all together or not at all (given_gains).
        answer = self._answer(executor, lambda: client.set_parameters_atomically(parameters), deadline,
                              f'{self.node_name(node)} to take its parameters', alive)
        if not answer.result.successful:
            raise GraphEpisodeError(f"{self.node_name(node)} refused the episode's parameters: {answer.result.reason}")

    def run_episode(self, executor, spec: EpisodeSpec, plan: EpisodePlan | None = None,
                    bag: EpisodeBagWriter | None = None, mode: str = 'lockstep', timeout: float = 120.0,
                    alive=lambda: None, peer_timeout: float = PEER_TIMEOUT,
                    scheduling: SchedulingOptions | None = None) -> Episodes:
        """Check the graph, configure, start, record and score one episode; `alive` raises if a node process died.

        `scheduling`: the real-time priority, cores and spin margin the nodes are set to (None: as they are); a
        node whose OS refuses them refuses the parameter, and the episode does not start.
        """
        plan = plan if plan is not None else check_episode(spec)
        if not plan.joint_names:
            raise GraphEpisodeError('the episode\'s plan names no joints (a plan read back from a recording?): '
                                    'plan it with ddarm.episodes.spec.check_episode')
        self.wait_for_peers(executor, spec.controller, peer_timeout, alive)
        deadline = time.monotonic() + timeout

        def watching() -> None:
            alive()
            self._watch_graph(spec.controller)
            if self.recording is not None and self.recording.error is None:
                stalled = self._stalled(mode)
                if stalled:
                    self.recording.fail(stalled)

        # The nodes run the arm of their read-only parameters, given when they started: never another one silently.
        arms = arm_parameters(spec)
        self._check_arm(executor, self.plant_node, arms['plant'], deadline, watching)
        self._check_arm(executor, spec.controller, arms[spec.controller], deadline, watching)
        parameters = node_parameters(spec, plan, mode, scheduling)
        plant_parameters = service_parameters(parameters['plant']['ros__parameters'], PLANT_OPTIONAL, 'plant')
        controller_parameters = service_parameters(parameters[spec.controller]['ros__parameters'],
                                                    CONTROLLER_OPTIONAL, 'controller')
        self._configure(executor, self.plant_node, plant_parameters, deadline, watching)
        self._configure(executor, spec.controller, controller_parameters, deadline, watching)
        self.period, self.bag, self.joints = spec.period, bag, list(plan.joint_names)
        self._peer_missing_since = None
        try:
            reference = reference_msg(self.joints, plan.times, plan.q_ref, plan.v_ref, plan.a_ref, plan.nominal)
            self.reference_publisher.publish(reference)
            expected = {'ready': True, 'kp': list(spec.kp), 'kv': list(spec.kv), 'delay': spec.delay,
                        'reference_samples': plan.k_max + 1, 'reference_final': plan.q_ref[-1].tolist()}
            # Until the controller holds this episode's reference and gains, and its own side of the state and
            # command topics has matched the plant and this recorder: a command its writer sends before matching
            # the plant's reader is lost, and the lockstep plant would wait for it forever.
            while True:
                state = json.loads(self._trigger(executor, self.reset_clients[spec.controller], deadline,
                                                 watching).message)
                configured = all(state[key] == value for key, value in expected.items())
                matched = state['state_publishers'] >= 1 and state['command_subscribers'] >= COMMAND_SUBSCRIBERS
                if configured and matched:
                    break
                if time.monotonic() > deadline:
                    controller = self.node_name(spec.controller)
                    raise GraphEpisodeError(
                        f'{controller} does not hold the episode\'s reference and gains' if not configured else
                        f'{controller} matched {state["state_publishers"]} joint_states publisher(s) (1 needed) and '
                        f'{state["command_subscribers"]} command subscriber(s) ({COMMAND_SUBSCRIBERS} needed: the plant '
                        'and the recorder) before the timeout')
                spin_once(executor, 0.01)
            configuration = state['configuration']
            self._check_started_with(spec.controller, controller_parameters, state['parameters'])
            self._spin_until(executor, lambda: time.monotonic() - self.last_traffic >= QUIET_PERIOD, deadline,
                             'the messages of the last episode to drain', watching)
            # Each side of a topic matches the other on its own, and a volatile reader drops what a writer sent
            # before the reader knew it: the plant waits for its side (required_subscribers and
            # required_clock_subscribers), the driver for its own before sample 0 can go out.
            recorded = [self.subscriptions_by_topic[topic] for topic in RECORDED_SAMPLE_TOPICS]
            self._spin_until(executor, lambda: all(reader.get_publisher_count() >= 1 for reader in recorded), deadline,
                             'the recorder to match the publishers of ' + ', '.join(RECORDED_SAMPLE_TOPICS), watching)
            self.recording = Recording(plan.k_max, spec.controller)
            self._record('/' + REFERENCE_TOPIC, reference.header.stamp, serialize_message(reference))
            # Never sent twice: the plant's reset starts the episode.
            reply = self._trigger(executor, self.reset_clients[self.plant_node], deadline, watching, again=False)
            if not reply.success:
                raise GraphEpisodeError(f'the plant refused to start: {reply.message}')
            self._check_started_with(self.plant_node, plant_parameters, json.loads(reply.message)['parameters'])
            self.recording.last_heard = time.monotonic()
            self._spin_until(executor, lambda: self.recording.ended, deadline, 'the episode to end', watching)
            if self.recording.error:
                raise GraphEpisodeError(self.recording.error)
            counted = plant_counters(self.recording.plant_report, FAILING_COUNTERS[mode],
                                     self.node_name(self.plant_node))
            if any(counted.values()):
                raise GraphEpisodeError(f'{self.node_name(self.plant_node)} counted {counted} during the episode: '
                                        'commands it refused, missed or got twice (a foreign publisher?)')
            self._watch_graph_now(spec.controller)
            after = json.loads(self._trigger(executor, self.status_clients[spec.controller], deadline,
                                             watching).message)
            if after.get('configuration') != configuration:
                raise GraphEpisodeError(f'{self.node_name(spec.controller)} was reconfigured, reset or sent another '
                                        'reference during the episode (by another node?): its commands may not be '
                                        "this episode's")
            self._write_bag()
            if bag is not None:
                bag.set_publishers(self.bag_publishers(spec.controller))
            return result_from_recording(spec, plan, self.recording, self.joints, {
                'states': self.subscriptions_by_topic['/' + JOINT_STATES_TOPIC].topic_name,
                'commands': self.subscriptions_by_topic['/' + EFFORT_COMMAND_TOPIC].topic_name})
        except BaseException as error:
            # A failed episode's bag (closed incomplete by its owner) still holds all that was heard.
            try:
                self._write_bag()
            except BagError as failure:
                error.add_note(str(failure))
            raise
        finally:
            self.recording, self.bag, self._unwritten = None, None, []

    def _check_started_with(self, node: str, sent: list[Parameter], reported: dict) -> None:
        """The node runs the episode with the parameters this driver set, not ones another node set in between."""
        changed = [f'{parameter.name} is {reported.get(parameter.name)!r}, not {parameter.value!r}'
                   for parameter in sent if not _same_value(reported.get(parameter.name), parameter.value)]
        if changed:
            raise GraphEpisodeError(f'{self.node_name(node)} started the episode with parameters that another node '
                                    f'set after this driver: {"; ".join(changed)}')

    def _watch_graph_now(self, law: str) -> None:
        self._next_graph_check = 0.0
        self._watch_graph(law)


def _same_value(reported, sent) -> bool:
    """A parameter as a node reports it (JSON) against the value set; an unset array reads as None or []."""
    if isinstance(sent, (list, tuple)):
        return list(reported or []) == list(sent)
    return reported == sent


def _reported_sample(report: dict, k_max: int, plant: str) -> int:
    """The sample a plant's divergence report names: a whole number in [0, k_max]."""
    text = str(report.get('sample', ''))
    if not (text.isascii() and text.isdigit()) or int(text) > k_max:
        raise GraphEpisodeError(f'the divergence report of {plant} names sample {text!r}, not one of the episode\'s '
                                f'samples 0 … {k_max}: a foreign publisher on /diagnostics?')
    return int(text)


def plant_counters(report: dict, names, plant: str) -> dict[str, int]:
    """The plant's counters from its report; a report that does not parse is not the plant's word."""
    try:
        return {name: int(report.get(name, 0)) for name in names}
    except (TypeError, ValueError) as error:
        raise GraphEpisodeError(f'the end-of-episode report of {plant} does not parse ({error}): '
                                'a foreign publisher on /diagnostics?') from error


def result_from_recording(spec: EpisodeSpec, plan: EpisodePlan, recording: Recording, joints: list[str],
                          topics: dict[str, str]) -> Episodes:
    """Read the recorded states and commands (`topics`: their resolved names, for the words) and score them by
    the one rule for recordings (`Episodes.from_recorded`)."""
    def read(n: int, data: bytes, what: str, topic: str, **needs):
        try:
            return read_joint_state(decode_joint_state(data, f'sample {n}'), joints, spec.period, what,
                                    need_state=False, **needs)
        except MessageError as error:
            raise GraphEpisodeError(f'unusable {what} on {topic}: {error}') from error

    states = {}
    for n, data in recording.states.items():
        sample = read(n, data, 'joint state', topics['states'])
        states[n] = (sample.q, sample.v, sample.effort)
    commands = {n: read(n, data, 'command', topics['commands'], need_effort=True).effort
                for n, data in recording.commands.items()}
    # The episode ended where the plant's report said; its states must say the same.
    without_position = sorted(n for n, (q, _, _) in states.items() if n > 0 and q is None)
    if without_position != ([] if recording.diverged_at is None else [recording.diverged_at]):
        raise GraphEpisodeError(f'the plant reported {recording.plant_report.get("event")!r} at sample '
                                f'{recording.plant_report.get("sample")}, but its states without a position are '
                                f'{without_position}: a foreign publisher?')
    try:
        return Episodes.from_recorded(spec, plan, states, commands, plant_report=recording.plant_report)
    except RecordingError as error:
        raise GraphEpisodeError(str(error)) from error


def realtime_warnings(plant_report: dict | None) -> list[str]:
    """What made a real-time episode differ from its lockstep twin: ticks that held an older command, late ticks.

    Such an episode's numbers are true of what ran on the wall clock, not of the sampled loop
    the indices describe; the command says so beside them.
    """
    if not plant_report:
        return []
    warnings = []
    stale, misses = int(plant_report.get('stale_commands', 0)), int(plant_report.get('deadline_misses', 0))
    if stale:
        warnings.append(f'{stale} tick(s) applied an older command (the current one was late): the loop was not '
                        'the sampled loop with a one-period compute delay')
    if misses:
        warnings.append(f"{misses} deadline miss(es) (a tick over 1.5 periods after the one before; period jitter "
                        f"max {float(plant_report.get('period_jitter_max_ms', 'nan')):.3g} ms; the plant ran "
                        f"{scheduling_text(plant_report)})")
    return warnings


def scheduling_text(plant_report: dict) -> str:
    """The plant's scheduling as its report gives it: '{policy} priority P on cores [..]'."""
    policy = plant_report.get('sched_policy', 'an unreported scheduling')
    priority = plant_report.get('sched_priority')
    cores = plant_report.get('cpu_affinity')
    return policy + (f' priority {priority}' if priority not in (None, '0') else '') + (
        f' on cores {cores}' if cores is not None else '')
