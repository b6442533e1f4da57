"""Episodes as rosbag2 bags: the recorder's writer, and the indices scored from a bag alone.

A bag holds what the graph carried (states, commands, the reference, /clock, the plant's
diagnostics) and, on /ddarm/episode and in the metadata's custom data, the episode's
configuration. Scoring reads nothing else: no model, no node.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ddarm_sim.samples import MessageError, joint_order, sample_at
from ddarm_tuner.episodes import EpisodePlan, EpisodeResult, EpisodeSpec, score

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
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
STATUS_KEY = 'ddarm.status'


class BagError(ValueError):
    """A bag that cannot be written where asked, or cannot be scored; the text names the problem."""


def checked_output_path(path: Path | str) -> Path:
    """Refuse a bag path that climbs with '..', goes through a symlink, or already exists (FAULTS.md 19)."""
    path = Path(path)
    if '..' in path.parts:
        raise BagError(f'{path}: ".." is not allowed in an output path')
    for parent in [path, *path.parents]:
        if parent.is_symlink():
            raise BagError(f'{path}: {parent} is a symlink; refusing to write through it')
    if path.exists():
        raise BagError(f'{path} exists already, not overwriting')
    return path


def child_path(folder: Path | str, name: str) -> Path:
    """folder/name for a name that is one plain path component, so it cannot leave the folder."""
    if not name or name in ('.', '..') or '/' in name or '\\' in name:
        raise BagError(f'{name!r} must be a plain file name inside {folder}')
    return checked_output_path(Path(folder) / name)


class EpisodeBagWriter:
    """Writes one episode's bag; `close(complete)` records whether the episode finished.

    Use as a context manager: an exception while recording still closes the bag, marked
    incomplete, so a scorer never takes it for a good run.
    """

    def __init__(self, path: Path | str, episode: dict, storage: str = 'mcap') -> None:
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
        self.path = checked_output_path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=STORAGES[storage])
        self.writer.open()
        self.connections = {topic: self.writer.add_connection(topic, msgtype, typestore=TYPESTORE)
                            for topic, msgtype in TOPICS.items()}
        text = json.dumps(episode, sort_keys=True)
        self.writer.set_custom_data('ddarm.episode', text)
        self.write_message(EPISODE_TOPIC, 0, TYPESTORE.types['std_msgs/msg/String'](data=text))
        self.closed = False

    def write(self, topic: str, timestamp_ns: int, cdr: bytes) -> None:
        """One message as serialized CDR (what rclpy's serialize_message gives)."""
        self.writer.write(self.connections[topic], int(timestamp_ns), cdr)

    def write_message(self, topic: str, timestamp_ns: int, message) -> None:
        self.write(topic, timestamp_ns, TYPESTORE.serialize_cdr(message, TOPICS[topic]))

    def close(self, complete: bool) -> None:
        if self.closed:
            return
        self.writer.set_custom_data(STATUS_KEY, 'complete' if complete else 'incomplete')
        self.writer.close()
        self.closed = True

    def __enter__(self) -> EpisodeBagWriter:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        self.close(complete=False)


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


def _sample(stamp, period: float, topic: str) -> int:
    try:
        return sample_at(stamp.sec + stamp.nanosec * 1e-9, period)
    except MessageError as error:
        raise BagError(f'{topic}: {error}') from error


def _in_order(names, joints: list, topic: str) -> np.ndarray:
    try:
        return joint_order(names, joints, topic)
    except MessageError as error:
        raise BagError(f'{error} (a bag from another robot?)') from error


def read_episode_bag(path: Path | str, require_complete: bool = True) -> BagEpisode:
    """Read and check an episode bag; BagError names whatever makes it unusable."""
    path = Path(path)
    if not path.exists():
        raise BagError(f'{path}: no such bag')
    if not (path / 'metadata.yaml').is_file():
        raise BagError(f'{path}: no metadata.yaml: not a bag, or a recording that never closed (incomplete)')
    try:
        return _read(path, require_complete)
    except BagError:
        raise
    except Exception as error:  # rosbags asserts and raises freely on damaged files
        raise BagError(f'{path}: unreadable bag ({type(error).__name__}: {error})') from error


def bag_status(path: Path | str) -> str:
    """'complete', 'incomplete', or 'unknown' (not written by ddarm), from the bag's metadata."""
    # rosbags' Reader does not expose custom_data: read it from rosbag2's own metadata file.
    metadata = yaml.safe_load((Path(path) / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    return (metadata.get('custom_data') or {}).get(STATUS_KEY, 'unknown')


def _read(path: Path, require_complete: bool) -> BagEpisode:
    status = bag_status(path)
    if require_complete and status != 'complete':
        raise BagError(f'{path}: the recording is marked {status}: the episode did not finish')
    with Reader(path) as reader:
        topics = {connection.topic: connection for connection in reader.connections}
        missing = [topic for topic in REQUIRED_TOPICS if topic not in topics]
        if missing:
            raise BagError(f'{path}: missing topics {missing}: not a complete ddarm episode bag')
        messages: dict = {topic: [] for topic in REQUIRED_TOPICS}
        wanted = [topics[topic] for topic in REQUIRED_TOPICS]
        for connection, _, raw in reader.messages(connections=wanted):
            messages[connection.topic].append(deserialize(raw, connection.msgtype))
    if not messages[EPISODE_TOPIC]:
        raise BagError(f'{path}: {EPISODE_TOPIC} holds no configuration')
    episode = json.loads(messages[EPISODE_TOPIC][0].data)
    period = float(episode['spec']['period'])
    joints = list(episode['joints'])
    if len(messages['/reference']) != 1:
        raise BagError(f"{path}: expected one /reference message, found {len(messages['/reference'])}")
    reference = messages['/reference'][0]
    order = _in_order(reference.joint_names, joints, '/reference')
    fields = {name: np.array([np.asarray(getattr(point, name))[order] for point in reference.points])
              for name in ('positions', 'velocities', 'accelerations', 'effort')}
    times = np.array([point.time_from_start.sec + point.time_from_start.nanosec * 1e-9
                      for point in reference.points])
    states = {}
    for message in messages['/joint_states']:
        order = _in_order(message.name, joints, '/joint_states')
        n = _sample(message.header.stamp, period, '/joint_states')
        states[n] = tuple(None if len(values) == 0 else np.asarray(values)[order]
                          for values in (message.position, message.velocity, message.effort))
    commands = {}
    for message in messages['/effort_command']:
        order = _in_order(message.name, joints, '/effort_command')
        commands[_sample(message.header.stamp, period, '/effort_command')] = np.asarray(message.effort)[order]
    return BagEpisode(episode, status, joints, times, fields['positions'], fields['velocities'],
                      fields['accelerations'], fields['effort'], states, commands)


def score_bag(path: Path | str) -> dict:
    """The indices of a recorded episode, from its bag alone: the same JSON as `ddarm episode --json`."""
    bag = read_episode_bag(path)
    k_max = len(bag.reference_times) - 1
    diverged_at = next((n for n in sorted(bag.states) if bag.states[n][0] is None and n > 0), None)
    last = k_max if diverged_at is None else diverged_at - 1
    missing = [n for n in range(last + 1) if n not in bag.states or bag.states[n][0] is None]
    missing += [n + 1 for n in range(last + 1) if n + 1 not in bag.states or bag.states[n + 1][2] is None]
    missing += [n for n in range(last + 1) if n not in bag.commands]
    if missing:
        raise BagError(f'{path}: samples {sorted(set(missing))[:10]} are missing: the episode is incomplete')
    spec = EpisodeSpec(**bag.episode['spec'])
    limit = bag.episode.get('torque_limit')
    plan = EpisodePlan(bag.reference_times, bag.q_ref, bag.v_ref, bag.a_ref, bag.nominal,
                       None if limit is None else np.array(limit), bag.states[0][0], bag.states[0][1])
    result = EpisodeResult(
        spec, plan, q=np.array([bag.states[n][0] for n in range(last + 1)]),
        v=np.array([bag.states[n][1] for n in range(last + 1)]),
        command=np.array([bag.commands[n] for n in range(last + 1)]),
        torque=np.array([bag.states[n + 1][2] for n in range(last + 1)]), diverged_at=diverged_at)
    result.indices = score(plan, result.errors, result.torque)
    return {**result.summary(), 'bag': str(path)}
