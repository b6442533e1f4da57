"""Episodes as rosbag2 bags: the recorder's writer, and the indices scored from a bag alone.

A bag holds what the graph carried (states, commands, the reference, /clock, the plant's
diagnostics) with the QoS its publishers offered, and, on /ddarm/episode and in the metadata's
custom data, the episode's configuration (ddarm.episode), whether it finished (ddarm.status) and
who published what (ddarm.publishers). Scoring reads nothing else: no model, no node; it refuses
evidence that is missing, duplicated, or from more than one publisher.
"""

from __future__ import annotations

import json
import os
import sqlite3
import stat
import types
import unicodedata
import typing
import weakref
from collections import defaultdict
from collections.abc import Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import TypedDict

import numpy as np
import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore

from ddarm.arrays import per_joint
from ddarm.errors import DdarmError
from ddarm.samples import (MAX_JOINTS, MAX_SAMPLES, MessageError, checked_reference, finite_array, joint_order,
                           sample_at, stamp_ns)
from ddarm.episodes.indices import IndicesError
from ddarm.episodes.result import Episodes, RecordingError
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec
from ddarm.interrupts import Interrupted, critical_section
from ddarm.datafiles import (MAX_TOPIC_MESSAGES, SAFE_LOADER, DataFileError, bag_metadata_text, is_missing,
                             unreachable)
from ddarm.motion.files import shown
from ddarm.reporting.text import visible

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
EPISODE_TOPIC = '/ddarm/episode'
TOPICS = {
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/effort_command': 'sensor_msgs/msg/JointState',
    '/reference': 'trajectory_msgs/msg/JointTrajectory',
    '/clock': 'rosgraph_msgs/msg/Clock',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
    EPISODE_TOPIC: 'std_msgs/msg/String',
}
REQUIRED_TOPICS = ('/joint_states', '/effort_command', '/reference', EPISODE_TOPIC)
# The topics the indices are computed from: each must come from one publisher.
SAMPLED_TOPICS = ('/joint_states', '/effort_command', '/clock', '/reference')
# A robot's episode (`ddarm robot`, a ros2_control robot's topics): its efforts arrive unstamped on the command topic,
# and the robot's own record of the command in force at each sample stands where a plant's stamped commands do.
ROBOT_COMMANDS_TOPIC = '/effort_controller/commands'
ROBOT_COMMANDED_TOPIC = '/robot/commanded_effort'
ROBOT_TOPICS = {**{topic: TOPICS[topic] for topic in ('/joint_states', '/reference', '/clock', '/diagnostics',
                                                      EPISODE_TOPIC)},
                ROBOT_COMMANDED_TOPIC: 'sensor_msgs/msg/JointState',
                ROBOT_COMMANDS_TOPIC: 'std_msgs/msg/Float64MultiArray'}
# The stamp (integer ns) of a robot episode's sample 0: a robot's clock does not start at 0 with its episode.
SAMPLE_0_KEY = 'sample_0_stamp_ns'
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
STATUS_KEY = 'ddarm.status'
EPISODE_KEY = 'ddarm.episode'
PUBLISHERS_KEY = 'ddarm.publishers'


class BagError(DdarmError, ValueError):
    """A bag that cannot be written where asked, or cannot be scored; the text names the problem."""


class TopicQos(TypedDict):
    """The QoS one publisher offered on a topic, as the bag records it (rosbag2's offered_qos_profiles).

    reliability: 'reliable' or 'best_effort'; durability: 'volatile' or 'transient_local';
    history: 'keep_last', 'keep_all', or 'unknown'; depth: an int >= 0. DDS discovery does not
    carry a publisher's history, so the graph (rclpy's get_publishers_info_by_topic) reports
    'unknown' with depth 0, and rosbag2 records that; `ros2 bag play` uses its own history anyway.
    """

    reliability: str
    durability: str
    history: str
    depth: int


# These mirror ddarm.ros.interface's SAMPLE_QOS, REFERENCE_QOS, CLOCK_QOS and DIAGNOSTICS_QOS
# (restated, since that module imports rclpy). /ddarm/episode has no DDS publisher: it is
# recorded latched, so a replay hands the configuration to a late subscriber.
DEFAULT_QOS: dict[str, TopicQos] = {
    '/joint_states': {'reliability': 'reliable', 'durability': 'volatile', 'history': 'keep_last', 'depth': 1000},
    '/effort_command': {'reliability': 'reliable', 'durability': 'volatile', 'history': 'keep_last', 'depth': 1000},
    '/reference': {'reliability': 'reliable', 'durability': 'transient_local', 'history': 'keep_last', 'depth': 1},
    '/clock': {'reliability': 'reliable', 'durability': 'volatile', 'history': 'keep_last', 'depth': 1000},
    '/diagnostics': {'reliability': 'reliable', 'durability': 'volatile', 'history': 'keep_last', 'depth': 10},
    EPISODE_TOPIC: {'reliability': 'reliable', 'durability': 'transient_local', 'history': 'keep_last', 'depth': 1},
    ROBOT_COMMANDED_TOPIC: {'reliability': 'reliable', 'durability': 'volatile', 'history': 'keep_last',
                            'depth': 1000},
    ROBOT_COMMANDS_TOPIC: {'reliability': 'reliable', 'durability': 'volatile', 'history': 'keep_last', 'depth': 1},
}
_RELIABILITY = {'reliable': QosReliability.RELIABLE, 'best_effort': QosReliability.BEST_EFFORT}
_DURABILITY = {'volatile': QosDurability.VOLATILE, 'transient_local': QosDurability.TRANSIENT_LOCAL}
_HISTORY = {'keep_last': QosHistory.KEEP_LAST, 'keep_all': QosHistory.KEEP_ALL, 'unknown': QosHistory.UNKNOWN}
# RMW_DURATION_INFINITE: what the graph reports for ddarm's publishers, none of which sets a
# deadline, lifespan or liveliness lease.
_INFINITE = QosTime(9223372036, 854775807)


def _rosbags_qos(path: Path, topic: str, profile) -> Qos:
    if not isinstance(profile, Mapping) or set(profile) != TopicQos.__required_keys__:
        raise BagError(f'{path}: offered QoS for {topic} must be a mapping with exactly the keys '
                       f'{sorted(TopicQos.__required_keys__)}, got {profile!r}')
    for key, names in (('reliability', _RELIABILITY), ('durability', _DURABILITY), ('history', _HISTORY)):
        if profile[key] not in names:
            raise BagError(f'{path}: offered QoS for {topic}: {key} must be one of {sorted(names)}, '
                           f'got {profile[key]!r}')
    depth = profile['depth']
    if not isinstance(depth, int) or isinstance(depth, bool) or depth < 0:
        raise BagError(f'{path}: offered QoS for {topic}: depth must be an int >= 0, got {depth!r}')
    return Qos(_HISTORY[profile['history']], depth, _RELIABILITY[profile['reliability']],
               _DURABILITY[profile['durability']], _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE,
               False)


def _offered_profiles(path: Path, offered_qos: Mapping[str, Sequence[TopicQos]] | None,
                      topics: Mapping[str, str]) -> dict[str, list[Qos]]:
    offered_qos = {} if offered_qos is None else offered_qos
    unknown = sorted(set(offered_qos) - set(topics))
    if unknown:
        raise BagError(f'{path}: offered QoS for {unknown}, which are not topics of an episode bag {sorted(topics)}')
    profiles = {}
    for topic in topics:
        given = offered_qos.get(topic, [DEFAULT_QOS[topic]])
        if isinstance(given, Mapping):
            raise BagError(f'{path}: offered QoS for {topic} must be a list of profiles, one per publisher')
        profiles[topic] = [_rosbags_qos(path, topic, profile) for profile in given]
    return profiles


def _reason(error: Exception) -> str:
    """What the OS said, without Python's errno prefix; sqlite keeps the OS's errno to itself and says what it can."""
    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    if isinstance(error, sqlite3.Error) and getattr(error, 'sqlite_errorname', None):
        return f'{error} ({error.sqlite_errorname})'
    return str(error) or type(error).__name__


def output_name_problem(name: str) -> str | None:
    """What keeps `name` from naming a file or folder ddarm makes, or None: it is empty, or it holds a control
    character (Unicode category Cc: a newline, a tab, ESC, DEL), which would break or rewrite every line, listing
    and report that names it. The one rule for every output's own name (the --run name, the last part of --out,
    --bag, a new --runs folder): checked_output_path applies it to each part of a path that ddarm creates."""
    if not name:
        return 'the name is empty'
    controls = sorted({character for character in name if unicodedata.category(character) == 'Cc'})
    if controls:
        codes = ', '.join(f'U+{ord(character):04X}' for character in controls)
        plural = 's' if len(controls) > 1 else ''
        return f'the name {visible(name, pictures=False)} holds the control character{plural} {codes}; give a name ' \
               'without control characters'
    return None


def folder_problem(folder: Path | str) -> str | None:
    """Why nothing new can be made in `folder`, or None when it is a folder: 'F is a file, not a folder' (F the
    folder or a file on the way to it), 'the folder F does not exist' (ENOENT alone), or what the OS says of it
    (a symlink loop, a folder it may not search): the one wording of every output location's folder."""
    folder = Path(folder)
    failure = unreachable(folder)
    if isinstance(failure, NotADirectoryError):  # a file on the way: name it, not the folder behind it
        folder = next(parent for parent in folder.parents if unreachable(parent) is None)
    elif is_missing(failure):
        return f'the folder {folder} does not exist'
    elif failure is not None:
        return f'the folder {folder} cannot be reached: {failure.strerror or failure}'
    mode = os.stat(folder).st_mode
    if stat.S_ISDIR(mode):
        return None
    return f'{folder} is a file, not a folder' if stat.S_ISREG(mode) else f'{folder} is not a folder'


def checked_output_path(path: Path | str) -> Path:
    """Refuse an output path that is empty, climbs with '..', goes through a symlink, already exists, goes through
    a file, or whose parts that ddarm creates (those not there yet) are no names (output_name_problem) (docs/faults.md
    19). Its folder may be new (made with it); checked_output_location also wants the folder there."""
    if str(path) == '':  # Path('') is '.', the current folder
        raise BagError('the output path is empty')
    path = Path(path)
    if '..' in path.parts:
        raise BagError(f'{path}: ".." is not allowed in an output path')
    for parent in [path, *path.parents]:
        if parent.is_symlink():
            raise BagError(f'{path}: {parent} is a symlink; refusing to write through it')
    if path.exists():
        raise BagError(f'{path} exists already, not overwriting')
    ancestor = next(parent for parent in path.parents if parent.exists())
    if not ancestor.is_dir():
        raise BagError(f'{path}: {ancestor} is a file, not a folder')
    for created in path.relative_to(ancestor).parts:
        if (problem := output_name_problem(created)) is not None:
            raise BagError(f'{visible(path, pictures=False)}: {problem}')
    return path


def checked_output_location(path: Path | str) -> Path:
    """checked_output_path, and the folder it goes in is there (folder_problem): what a new output the user names
    (a file or a folder) is checked with before any work, so that a mistyped path grows no tree."""
    path = checked_output_path(path)
    if (problem := folder_problem(path.absolute().parent)) is not None:
        raise BagError(f'{path}: {problem}')
    return path


def child_path(folder: Path | str, name: str) -> Path:
    """folder/name for a name that is one plain path component, so it cannot leave the folder."""
    if not name or name in ('.', '..') or '/' in name or '\\' in name:
        raise BagError(f'{name!r} must be a plain file name inside {folder}')
    return checked_output_path(Path(folder) / name)


def _close_abandoned(writer: Writer) -> None:
    # A stop raised in a finaliser would be lost with the close; it waits, and is raised at the next check.
    with suppress(OSError, sqlite3.Error, WriterError, Interrupted), critical_section():
        writer.set_custom_data(STATUS_KEY, 'incomplete')
        writer.close()


class EpisodeBagWriter:
    """Writes one episode's bag; `close(complete)` records whether the episode finished.

    Use as a context manager: an exception while recording still closes the bag, marked
    incomplete, so a scorer never takes it for a good run.

    `topics` maps each topic the bag records to its type: TOPICS (a plant's episode) or ROBOT_TOPICS (a robot's).
    `offered_qos` maps a topic of those to the profiles its publishers offered, one TopicQos per
    publisher heard (rosbag2's convention); a topic it leaves out gets DEFAULT_QOS, what ddarm's
    own publisher offers. The connections are made when the bag opens, so the QoS must be known
    by then. Any failure to write (a full disk, a file-size limit, a storage error) is a BagError
    naming the bag and the reason; the storage is then abandoned without metadata.yaml, so the
    bag can never be taken for a complete one, and every later write or close(complete=True)
    raises the same error.
    """

    def __init__(self, path: Path | str, episode: dict, storage: str = 'mcap',
                 offered_qos: Mapping[str, Sequence[TopicQos]] | None = None,
                 topics: Mapping[str, str] = TOPICS) -> None:
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
        self.path = checked_output_path(path)
        self.topics = dict(topics)
        profiles = _offered_profiles(self.path, offered_qos, self.topics)
        self.status: str | None = None  # 'complete' or 'incomplete' once closed
        self.failure: str | None = None
        self.writer: Writer | None = None
        text = json.dumps(episode, sort_keys=True)
        try:
            self._open(storage, profiles, text)
        except BaseException:
            abandoned = getattr(self, '_abandoned', None)
            if abandoned is not None and self.failure is None:
                abandoned()  # closed now, marked incomplete, not when the exception is collected
            raise

    def _open(self, storage: str, profiles: dict, text: str) -> None:
        # A stop during the opening waits for its end; the caller then closes the bag incomplete.
        with critical_section(), self._writing():
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=STORAGES[storage])
            self.writer.open()
            # A writer dropped unclosed (a signal between its opening and the `with` that closes it, an
            # exception in here) is still closed, marked incomplete, when it is collected or at exit.
            self._abandoned = weakref.finalize(self, _close_abandoned, self.writer)
            self.connections = {topic: self.writer.add_connection(topic, msgtype, typestore=TYPESTORE,
                                                                  offered_qos_profiles=profiles[topic])
                                for topic, msgtype in self.topics.items()}
            self.writer.set_custom_data(EPISODE_KEY, text)
        self.write_message(EPISODE_TOPIC, 0, TYPESTORE.types['std_msgs/msg/String'](data=text))

    @contextmanager
    def _writing(self):
        try:
            yield
        except (OSError, sqlite3.Error, WriterError) as error:
            self.failure = f'{self.path}: cannot write the bag: {_reason(error)}'
            if self.writer is not None:
                if hasattr(self, '_abandoned'):
                    self._abandoned.detach()
                # The storage is failing already: closing it may fail again, and the first error is the one to report.
                with suppress(OSError, sqlite3.Error):
                    self.writer.abort()
            raise BagError(self.failure) from error

    def _check_open(self, what: str) -> None:
        if self.failure is not None:
            raise BagError(self.failure)
        if self.status is not None:
            raise BagError(f'{self.path}: the bag is closed (marked {self.status}); cannot record {what}')

    def write(self, topic: str, timestamp_ns: int, cdr: bytes) -> None:
        """One message as serialized CDR (what rclpy's serialize_message gives)."""
        self._check_open(topic)
        if topic not in self.connections:
            raise BagError(f'{self.path}: {topic} is not a topic of an episode bag {sorted(self.topics)}')
        with self._writing():
            self.writer.write(self.connections[topic], int(timestamp_ns), cdr)

    def write_message(self, topic: str, timestamp_ns: int, message) -> None:
        self.write(topic, timestamp_ns, TYPESTORE.serialize_cdr(message, self.topics[topic]))

    def set_publishers(self, publishers: Mapping[str, Sequence[str]]) -> None:
        """The fully qualified names of the nodes heard publishing each topic, one per publisher.

        Stored as JSON ({topic: [node, ...]}) under custom_data's ddarm.publishers; a scorer
        refuses a bag whose sampled topics had more than one publisher. A later call replaces it.
        """
        self._check_open(PUBLISHERS_KEY)
        unknown = sorted(set(publishers) - set(self.topics))
        if unknown:
            raise BagError(f'{self.path}: publishers for {unknown}, which are not topics of an episode bag')
        for topic, nodes in publishers.items():
            if isinstance(nodes, str) or not all(isinstance(node, str) and node.startswith('/') for node in nodes):
                raise BagError(f'{self.path}: the publishers of {topic} must be a list of fully qualified '
                               f'node names, got {nodes!r}')
        text = json.dumps({topic: list(nodes) for topic, nodes in publishers.items()}, sort_keys=True)
        with self._writing():
            self.writer.set_custom_data(PUBLISHERS_KEY, text)

    def close(self, complete: bool) -> None:
        """Close the bag marked complete or incomplete; closing again is a no-op.

        BagError if the bag cannot be closed, or if complete=True is asked of a bag that failed
        or was already closed incomplete: it is not a complete recording.
        """
        if self.failure is not None:
            if complete:
                raise BagError(self.failure)
            return
        if self.status is not None:
            if complete and self.status != 'complete':
                raise BagError(f'{self.path}: already closed and marked {self.status}; it cannot become complete')
            return
        status = 'complete' if complete else 'incomplete'
        with critical_section(), self._writing():
            self._abandoned.detach()
            self.writer.set_custom_data(STATUS_KEY, status)
            self.writer.close()
            self.status = status

    def __enter__(self) -> EpisodeBagWriter:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if error is None:
            self.close(complete=False)
            return
        # The exception that ended the recording stays the one raised; a bag that could not even
        # be closed is added to it.
        try:
            self.close(complete=False)
        except BagError as failure:
            error.add_note(str(failure))


@dataclass
class BagEpisode:
    """What a bag says about its episode."""

    episode: dict
    status: str
    joints: list
    reference_times: np.ndarray
    q_ref: np.ndarray
    v_ref: np.ndarray
    a_ref: np.ndarray
    nominal: np.ndarray
    states: dict  # sample -> (q or None, v or None, effort or None)
    commands: dict  # sample -> effort
    path: Path | None = None  # where it was read from


def deserialize(raw: bytes | memoryview, msgtype: str):
    """CDR to a message, accepting up to 8 bytes of trailing padding after it.

    Fast DDS rounds the serialized size of a JointState with empty float64 sequences up by as
    much as 8 bytes (of unspecified content); rosbags' deserialize_cdr allows only 3, so it
    would refuse what rosbag2 itself records. The decoded fields are unaffected.
    """
    raw = bytes(raw)
    if len(raw) < 4 or raw[:2] != b'\x00\x01':
        raise BagError(f'{msgtype}: not little-endian CDR')
    msgdef = TYPESTORE.get_msgdef(msgtype)
    message, end = msgdef.deserialize_cdr_le(raw[4:], 0, msgdef.cls, TYPESTORE)
    trailing = raw[4 + end:]
    if len(trailing) > 8:
        raise BagError(f'{msgtype}: {len(trailing)} unexpected bytes after the message')
    return message


def _in_order(names, joints: list, topic: str) -> np.ndarray | slice:
    try:
        return joint_order(names, joints, topic)
    except MessageError as error:
        raise BagError(f'{error} (a bag from another robot?)') from error


def read_episode_bag(path: Path | str, require_complete: bool = True) -> BagEpisode:
    """Read and check an episode bag; BagError names whatever makes it unusable."""
    path = Path(path)
    failure = unreachable(path)  # a symlink loop, a folder it may not search: the OS's reason, not 'no such bag'
    if is_missing(failure):
        raise BagError(f'{path}: no such bag')
    if failure is not None:
        raise BagError(f'{path}: {failure.strerror or failure}')
    failure = unreachable(path / 'metadata.yaml') if path.is_dir() else None
    if failure is not None and not is_missing(failure):
        raise BagError(f'{path}: metadata.yaml: {failure.strerror or failure}')
    if not (path / 'metadata.yaml').is_file():
        raise BagError(f'{path}: no metadata.yaml: not a bag, or a recording that never closed (incomplete)')
    try:
        return _read(path, require_complete)
    except BagError as error:
        if str(error).startswith(f'{path}: '):
            raise
        raise BagError(f'{path}: {error}') from error  # a message's problem, named with its bag
    except Exception as error:  # rosbags asserts and raises freely on damaged files
        raise BagError(f'{path}: unreadable bag ({type(error).__name__}: {error})') from error


def checked_metadata(path: Path | str) -> str:
    """ddarm.datafiles.bag_metadata_text, BagError naming the bag: checked before rosbags or anything else reads it."""
    try:
        return bag_metadata_text(path)
    except DataFileError as error:
        raise BagError(str(error)) from error


def _custom_data(path: Path | str) -> dict:
    # From rosbag2's own metadata file, before any storage is opened: a recording marked
    # incomplete says so even when its storage file is damaged.
    metadata = yaml.load(checked_metadata(path), Loader=SAFE_LOADER)
    information = metadata.get('rosbag2_bagfile_information') if isinstance(metadata, dict) else None
    custom = information.get('custom_data') if isinstance(information, dict) else None
    if not isinstance(custom or {}, dict):
        raise BagError(f'{path}: metadata.yaml: custom_data is not a mapping')
    return custom or {}


def bag_status(path: Path | str) -> str:
    """'complete', 'incomplete', or 'unknown' (not written by ddarm), from the bag's metadata."""
    return _custom_data(path).get(STATUS_KEY, 'unknown')


def _repeated(keys) -> list:
    seen, repeated = set(), set()
    for key in keys:
        (repeated if key in seen else seen).add(key)
    return sorted(repeated)


def _by_sample(path: Path, topic: str, messages: list, period: float, sample_0_ns: int = 0) -> dict:
    """Sample index -> the one message stamped at it, counted from the stamp of sample 0 (a robot's states before
    it, while it waited for its controller, are not the episode's); two for one sample are refused, not overwritten."""
    messages = [message for message in messages if stamp_ns(message.header.stamp) >= sample_0_ns]
    try:
        samples = [sample_at((stamp_ns(message.header.stamp) - sample_0_ns) * 1e-9, period) for message in messages]
    except MessageError as error:
        raise BagError(f'{topic}: {error}' + (f' (counted from sample 0 at {sample_0_ns} ns)' if sample_0_ns else '')
                       ) from error
    repeated = _repeated(samples)
    if repeated:
        raise BagError(f'{path}: {topic} holds more than one message for samples {repeated[:10]}: '
                       'a second publisher, or messages recorded twice')
    # One reliable publisher's messages arrive in the order it sent them, so they are recorded in that order.
    for i in range(1, len(samples)):
        if samples[i] < samples[i - 1]:
            raise BagError(f'{path}: {topic} message {i} is stamped for sample {samples[i]}, after message {i - 1} '
                           f'for sample {samples[i - 1]}: the header stamps must increase in the order recorded')
    return dict(zip(samples, messages))


def _publishers(path: Path, text) -> dict:
    try:
        publishers = json.loads(text)
    except (TypeError, ValueError):
        publishers = None
    if not (isinstance(publishers, dict) and all(
            isinstance(nodes, list) and all(isinstance(node, str) for node in nodes) for nodes in publishers.values())):
        raise BagError(f'{path}: custom_data {PUBLISHERS_KEY} is not a JSON object of node-name lists: {shown(text)}')
    return publishers


def _check_one_source(path: Path, custom: dict, connections: dict) -> None:
    """Refuse evidence from more than one publisher on a topic the indices depend on (docs/faults.md 25)."""
    for topic in (*SAMPLED_TOPICS, ROBOT_COMMANDED_TOPIC):
        if topic in connections and len(profiles := connections[topic].ext.offered_qos_profiles) > 1:
            raise BagError(f'{path}: {topic} was recorded from {len(profiles)} publishers (its '
                           'offered_qos_profiles): the evidence may mix two sources')
    if PUBLISHERS_KEY in custom:
        publishers = _publishers(path, custom[PUBLISHERS_KEY])
        for topic in (*SAMPLED_TOPICS, ROBOT_COMMANDED_TOPIC):
            if len(nodes := publishers.get(topic, [])) > 1:
                raise BagError(f'{path}: {topic} had {len(nodes)} publishers ({", ".join(nodes)}): '
                               'the evidence may mix two sources')


def _check_message_count(path: Path, topic: str, count: int) -> None:
    if count > MAX_TOPIC_MESSAGES:
        raise BagError(f'{path}: {topic} holds more than {MAX_TOPIC_MESSAGES} messages, one per sample of the longest '
                       f'episode ({MAX_SAMPLES} periods)')


def _read(path: Path, require_complete: bool) -> BagEpisode:
    custom = _custom_data(path)
    status = custom.get(STATUS_KEY, 'unknown')
    if require_complete and status != 'complete':
        raise BagError(f'{path}: the recording is marked {status}: the episode did not finish')
    with Reader(path) as reader:
        by_topic = defaultdict(list)
        for connection in reader.connections:
            by_topic[connection.topic].append(connection)
        # A robot's bag holds the robot's record of its commands where a plant's holds the stamped commands.
        robot_bag = '/effort_command' not in by_topic and ROBOT_COMMANDED_TOPIC in by_topic
        commands_topic = ROBOT_COMMANDED_TOPIC if robot_bag else '/effort_command'
        required = tuple(commands_topic if topic == '/effort_command' else topic for topic in REQUIRED_TOPICS)
        missing = [topic for topic in required if topic not in by_topic]
        if missing:
            raise BagError(f'{path}: missing topics {missing}: not a complete ddarm episode bag')
        read = [topic for topic in (*required, '/clock') if topic in by_topic]
        for topic in read:
            if len(by_topic[topic]) > 1:
                types = [connection.msgtype for connection in by_topic[topic]]
                raise BagError(f'{path}: {topic} is recorded on {len(types)} connections ({types}): '
                               'the evidence may mix two sources')
        connections = {topic: by_topic[topic][0] for topic in read}
        _check_one_source(path, custom, connections)
        for topic, connection in connections.items():
            _check_message_count(path, topic, connection.msgcount)
        messages: dict = {topic: [] for topic in read}
        for connection, _, raw in reader.messages(connections=list(connections.values())):
            received = messages[connection.topic]
            _check_message_count(path, connection.topic, len(received) + 1)
            received.append(deserialize(raw, connection.msgtype))
    if len(messages[EPISODE_TOPIC]) != 1:
        raise BagError(f'{path}: {EPISODE_TOPIC} holds {len(messages[EPISODE_TOPIC])} configurations, not one: '
                       'which one the episode ran is unknown' if messages[EPISODE_TOPIC]
                       else f'{path}: {EPISODE_TOPIC} holds no configuration')
    episode, period, joints = _episode_configuration(path, messages[EPISODE_TOPIC][0].data)
    sample_0_ns = episode.get(SAMPLE_0_KEY, 0)
    if isinstance(sample_0_ns, bool) or not isinstance(sample_0_ns, int) or sample_0_ns < 0:
        raise BagError(f'{path}: {EPISODE_TOPIC} holds {SAMPLE_0_KEY} {shown(sample_0_ns)}, not a whole number of ns '
                       '>= 0: not the configuration ddarm records')
    if len(joints) > MAX_JOINTS:
        raise BagError(f'{path}: {EPISODE_TOPIC} names {len(joints)} joints, more than the {MAX_JOINTS} an arm may '
                       'have')
    if len(messages['/reference']) != 1:
        raise BagError(f"{path}: expected one /reference message, found {len(messages['/reference'])}")
    reference = messages['/reference'][0]
    _in_order(reference.joint_names, joints, '/reference')
    try:  # the checks the controllers apply to the reference they receive
        times, q_ref, v_ref, a_ref, nominal = checked_reference(
            reference.joint_names, ((point.time_from_start.sec + point.time_from_start.nanosec * 1e-9,
                                     point.positions, point.velocities, point.accelerations, point.effort)
                                    for point in reference.points), joints, period)
    except MessageError as error:
        raise BagError(f'{path}: /reference: {error}') from error
    stamps = [stamp_ns(message.clock) for message in messages.get('/clock', [])]
    repeated = _repeated(stamps)
    if repeated:
        raise BagError(f'{path}: /clock holds more than one message at t = {[t * 1e-9 for t in repeated[:10]]} s: '
                       'a second clock, or messages recorded twice')
    states = {}
    for n, message in _by_sample(path, '/joint_states', messages['/joint_states'], period, sample_0_ns).items():
        order = _in_order(message.name, joints, '/joint_states')
        states[n] = tuple(None if len(values) == 0 else _values(path, values, f'/joint_states sample {n}', field,
                                                               joints)[order]
                          for field, values in (('position', message.position), ('velocity', message.velocity),
                                                ('effort', message.effort)))
    commands = {}
    for n, message in _by_sample(path, commands_topic, messages[commands_topic], period, sample_0_ns).items():
        order = _in_order(message.name, joints, commands_topic)
        commands[n] = _values(path, message.effort, f'{commands_topic} sample {n}', 'effort', joints)[order]
    return BagEpisode(episode, status, joints, times, q_ref, v_ref, a_ref, nominal, states, commands, path)


def _refuse_constant(constant: str):
    raise ValueError(f'{constant} is no JSON number')


def _episode_configuration(path: Path, text: str) -> tuple[dict, float, list[str]]:
    """The configuration on /ddarm/episode, its period and joints; BagError naming the field that is missing or
    not what ddarm writes there."""
    def refused(problem: str) -> BagError:
        return BagError(f'{path}: {EPISODE_TOPIC} {problem}: not the configuration ddarm records')

    try:
        episode = json.loads(text, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as error:
        raise refused(f'is not JSON ({type(error).__name__}: {error})') from error
    spec = episode.get('spec') if isinstance(episode, dict) else None
    if not isinstance(spec, dict):
        raise refused('holds no spec (a JSON object under "spec")')
    period = spec.get('period')
    if isinstance(period, bool) or not isinstance(period, (int, float)) or not period > 0:
        raise refused(f'holds the spec period {period!r}, not a positive number of s')
    joints = episode.get('joints')
    if not (isinstance(joints, list) and joints and all(isinstance(name, str) for name in joints)):
        raise refused('holds no joints (a list of joint names under "joints")')
    prismatic = episode.get('prismatic', [False] * len(joints))
    if not (isinstance(prismatic, list) and len(prismatic) == len(joints)
            and all(isinstance(flag, bool) for flag in prismatic)):
        raise refused(f'holds prismatic {shown(prismatic)}, not one true or false per joint '
                      f'({len(joints)})')
    return episode, float(period), joints


def _fits(value, hint) -> bool:
    """Whether a JSON value has the type an EpisodeSpec field is annotated with: a float field takes an int, a
    bool is never a number, a tuple is a JSON list."""
    origin, arguments = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, argument) for argument in arguments)
    if origin is tuple:
        return isinstance(value, list) and all(_fits(item, arguments[0]) for item in value)
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _checked_spec(path: Path, spec: dict) -> dict:
    """The recorded spec, each field of the type EpisodeSpec declares (EpisodeSpec itself converts, so that a
    bool or a numeric string would pass for a number); BagError naming the field otherwise."""
    hints = typing.get_type_hints(EpisodeSpec)
    for name, value in spec.items():
        if name in hints and not _fits(value, hints[name]):
            raise BagError(f'{path}: {EPISODE_TOPIC} holds the spec {name} {shown(value)}, not a {hints[name]}: not '
                           'the configuration ddarm records')
    return spec


def _values(path: Path, values, what: str, field: str, joints: list) -> np.ndarray:
    """A recorded field as the nodes check it on arrival: one finite number per joint."""
    try:
        return finite_array(values, what, field, len(joints))
    except MessageError as error:
        raise BagError(f'{path}: {error}') from error


def bag_result(bag: BagEpisode) -> Episodes:
    """The recorded episode as an Episodes (B = 1), scored by the one rule for recordings.

    BagError (naming the bag) for a configuration on /ddarm/episode that does not make a spec,
    a torque limit that is not one positive number per joint, samples missing, or a reference
    the indices cannot be weighed by.
    """
    path = bag.path
    try:
        spec = EpisodeSpec(**_checked_spec(path, bag.episode['spec']))
    except (TypeError, ValueError) as error:  # EpisodeError is a ValueError
        raise BagError(f'{path}: {EPISODE_TOPIC} holds a spec that cannot be run: {error}') from error
    limit = bag.episode.get('torque_limit')
    if limit is not None:
        limit = per_joint(f'{path}: {EPISODE_TOPIC} torque_limit', limit, len(bag.joints), BagError, positive=True)
    plan = EpisodePlan(bag.reference_times, bag.q_ref, bag.v_ref, bag.a_ref, bag.nominal, limit,
                       *(bag.states[0][:2] if 0 in bag.states else (None, None)), joint_names=tuple(bag.joints),
                       prismatic=tuple(bag.episode.get('prismatic', [False] * len(bag.joints))))
    try:
        return Episodes.from_recorded(spec, plan, bag.states, bag.commands)
    except (RecordingError, IndicesError) as error:
        raise BagError(f'{path}: {error}') from error


def score_bag(path: Path | str) -> dict:
    """The indices of a recorded episode, from its bag alone: the same JSON as `ddarm episode --json`.

    BagError, naming the bag, for anything that keeps it from being scored.
    """
    return {**bag_result(read_episode_bag(path)).summary(), 'bag': str(path)}
