"""Waypoint motion files from recorded rosbag2 bags: a JointTrajectory as it was sent, or /joint_states as the arm
moved.

A trajectory_msgs/JointTrajectory topic gives its first message: its joint_names and points as they are (the
points' effort, a torque and no part of q^d, is left out). A sensor_msgs/JointState topic gives one point per
message: the positions of the chosen joints and, when every message has them, their velocities, at the header
stamp's time after the first message used; the last point's velocities are written as zero, since the motion
ends at rest. The text written reads back, through ddarm.motion.files, to the same motion bit for bit: each float
is Python's repr of the double.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from ddarm.datafiles import MAX_TOPIC_MESSAGES, DataFileError, bag_metadata_text, is_missing, unreachable
from ddarm.motion.files import MAX_JOINTS, MAX_POINTS, flow_names, flow_numbers, parse_motion, shown
from ddarm.motion.programmed import MotionError

# For a bag that carries no message definitions of its own (older sqlite3 bags).
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
JOINT_STATE = 'sensor_msgs/msg/JointState'
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'
DEFAULT_TOPIC = '/joint_states'
_NANOSEC_PER_SEC = 1_000_000_000
# Fast DDS rounds a serialized JointState with empty sequences up by as much as 8 bytes, which rosbag2 records and
# rosbags' own deserialize_cdr refuses (it allows 3; see ddarm.recording.bags.deserialize): up to 8 is padding.
_CDR_PADDING = 8
# A joint name written as it is (within a flow list: no comma, bracket, colon or space).


def motion_file_from_bag(bag: Path | str, topic: str | None = None, joints: Sequence[str] | None = None,
                         start: float | None = None, end: float | None = None) -> str:
    """The text of a waypoint motion file from the bag's `topic` (mcap or sqlite3 storage).

    Args:
        bag: a rosbag2 folder.
        topic: a JointTrajectory or JointState topic; None: /joint_states if the bag has it, else its only
            JointTrajectory topic.
        joints: of a JointState topic, the joints by name, in the order the file lists them; None: those of the
            first message used, in its order.
        start, end: of a JointState topic, the window of messages used, in s after the topic's first message
            (by header stamp), each end included; None: from the first, to the last.

    Raises:
        MotionError: naming the bag (and the topic) for a folder that is no readable bag, a topic it lacks or of
            another type, no messages, joints the messages lack, stamps that do not increase, values that are
            not finite, or a motion the file cannot hold.
    """
    bag = Path(bag)
    for name, bound in (('start', start), ('end', end)):
        if bound is not None and not (math.isfinite(bound) and bound >= 0):
            raise MotionError(f'{bag}: the window {name} must be a finite number of seconds >= 0 after the topic\'s '
                              f'first message, got {bound!r}')
    if start is not None and end is not None and not start <= end:
        raise MotionError(f'{bag}: the window start {start!r} s is after its end {end!r} s')
    # A symlink loop, a folder it may not search: the OS's own reason, not that no metadata.yaml is there.
    for where, failure in ((f'{bag}', unreachable(bag)),
                           (f'{bag}: metadata.yaml', unreachable(bag / 'metadata.yaml') if bag.is_dir() else None)):
        if failure is not None and not is_missing(failure):
            raise MotionError(f'{where}: {failure.strerror or failure}')
    if not (bag / 'metadata.yaml').is_file():
        raise MotionError(f'{bag}: no metadata.yaml in it: not a rosbag2 bag, or a recording that never closed')
    try:
        bag_metadata_text(bag)  # before rosbags reads it
    except DataFileError as error:
        raise MotionError(str(error)) from None
    try:
        with AnyReader([bag], default_typestore=TYPESTORE) as reader:
            topic, msgtype, connections = _chosen_topic(bag, reader, topic)
            if msgtype == JOINT_TRAJECTORY and (joints is not None or start is not None or end is not None):
                raise MotionError(f'{bag}: {topic}: a JointTrajectory is taken whole, as it was sent: joints, '
                                  'start and end choose among /joint_states messages')
            messages = []
            for _, _, raw in reader.messages(connections=connections):
                if len(messages) == MAX_TOPIC_MESSAGES:  # counted as read: the metadata's count may lie
                    raise MotionError(f'{bag}: {topic} holds more than {MAX_TOPIC_MESSAGES} messages, the most a '
                                      'motion is taken from')
                messages.append(_deserialized(f'{bag}: {topic}', reader, bytes(raw), msgtype))
                if msgtype == JOINT_TRAJECTORY:
                    break
    except MotionError:
        raise
    except Exception as error:  # rosbags asserts and raises freely on damaged files
        raise MotionError(f'{bag}: unreadable bag ({type(error).__name__}: {error})') from error
    where = f'{bag}: {topic}'
    if not messages:
        raise MotionError(f'{where}: no messages')
    count = sum(connection.msgcount for connection in connections)
    if msgtype == JOINT_TRAJECTORY:
        text = _from_trajectory(where, bag, topic, messages[0], count)
    else:
        text = _from_joint_states(where, bag, topic, messages, joints, start, end)
    parse_motion(text, where)  # what is written must load; a refusal names the point
    return text


def _chosen_topic(bag: Path, reader: AnyReader, topic: str | None):
    by_topic = defaultdict(list)
    for connection in reader.connections:
        by_topic[connection.topic].append(connection)
    listing = ', '.join(f'{name} ({", ".join(sorted({c.msgtype for c in by_topic[name]}))})'
                        for name in sorted(by_topic)) or 'none'
    if topic is None:
        trajectories = sorted(name for name, connections in by_topic.items()
                              if any(c.msgtype == JOINT_TRAJECTORY for c in connections))
        if DEFAULT_TOPIC in by_topic:
            topic = DEFAULT_TOPIC
        elif len(trajectories) == 1:
            topic = trajectories[0]
        else:
            which = 'no JointTrajectory topic' if not trajectories else f'{len(trajectories)} JointTrajectory topics'
            raise MotionError(f'{bag}: no {DEFAULT_TOPIC} and {which}: choose a topic (the bag has {listing})')
    elif topic not in by_topic:
        raise MotionError(f'{bag}: no topic {topic} (the bag has {listing})')
    types = sorted({connection.msgtype for connection in by_topic[topic]})
    if types not in ([JOINT_STATE], [JOINT_TRAJECTORY]):
        raise MotionError(f'{bag}: {topic} carries {", ".join(types)}: a motion comes from {JOINT_TRAJECTORY} or '
                          f'{JOINT_STATE}')
    return topic, types[0], by_topic[topic]


def _deserialized(where: str, reader: AnyReader, raw: bytes, msgtype: str):
    """CDR to a message by the bag's own definitions, allowing the padding rosbag2 itself records."""
    if len(raw) < 4 or raw[:2] not in (b'\x00\x00', b'\x00\x01'):
        raise MotionError(f'{where}: a message that is not CDR')
    msgdef = reader.typestore.get_msgdef(msgtype)
    decode = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
    message, end = decode(raw[4:], 0, msgdef.cls, reader.typestore)
    if len(raw) - 4 - end > _CDR_PADDING:
        raise MotionError(f'{where}: {len(raw) - 4 - end} unexpected bytes after a {msgtype}')
    return message


def _from_trajectory(where: str, bag: Path, topic: str, message, count: int) -> str:
    if not message.points:
        raise MotionError(f'{where}: its first message has no points')
    first = message.points[0].time_from_start
    if (first.sec, first.nanosec) != (0, 0):
        raise MotionError(f'{where}: points[0] is at {first.sec + first.nanosec / _NANOSEC_PER_SEC!r} s, not 0: the '
                          "message holds no q at t = 0 (the JTC starts from the arm's state then), which a motion "
                          'file needs as its start')
    lines = [f'# Motion from the bag {str(bag)!r}, topic {topic!r} ({JOINT_TRAJECTORY}): the joint_names and points '
             f'of its first message (of {count}), as they are.']
    if any(len(point.effort) for point in message.points):
        lines.append("# The points' effort is left out: a motion file holds q^d; its torque P^nom is computed.")
    if len(message.joint_names) > MAX_JOINTS:
        raise MotionError(f'{where}: its first message names {len(message.joint_names)} joints, more than the '
                          f'{MAX_JOINTS} a motion may drive')
    if len(message.points) > MAX_POINTS:
        raise MotionError(f'{where}: its first message holds {len(message.points)} points, more than the '
                          f'{MAX_POINTS} a motion may have')
    lines += [f'joint_names: {flow_names(message.joint_names)}', 'points:']
    for i, point in enumerate(message.points):
        if not len(point.positions):
            raise MotionError(f'{where}: points[{i}] has no positions (velocities or accelerations alone, which the '
                              'JTC can integrate, are no motion file)')
        lines.append(f'  - positions: {flow_numbers(_finite(where, f"points[{i}].positions", point.positions))}')
        for key in ('velocities', 'accelerations'):
            if len(values := getattr(point, key)):
                lines.append(f'    {key}: {flow_numbers(_finite(where, f"points[{i}].{key}", values))}')
        lines.append(f'    time_from_start: {{sec: {point.time_from_start.sec}, '
                     f'nanosec: {point.time_from_start.nanosec}}}')
    return '\n'.join(lines) + '\n'


def _from_joint_states(where: str, bag: Path, topic: str, messages: list, joints: Sequence[str] | None,
                       start: float | None, end: float | None) -> str:
    stamps = [message.header.stamp.sec * _NANOSEC_PER_SEC + message.header.stamp.nanosec for message in messages]
    for i in range(1, len(stamps)):
        if stamps[i] <= stamps[i - 1]:
            raise MotionError(f'{where}: message {i} is stamped {_seconds(stamps[i])!r} s, not after message '
                              f'{i - 1} ({_seconds(stamps[i - 1])!r} s): the header stamps must increase (the '
                              'times of a point are its stamp, never the time the bag received it)')
    after_first = [(stamp - stamps[0]) / _NANOSEC_PER_SEC for stamp in stamps]
    used = [i for i, t in enumerate(after_first)
            if (start is None or start <= t) and (end is None or t <= end)]
    if len(used) > MAX_POINTS:
        raise MotionError(f'{where}: {len(used)} of its messages within the window, more than the {MAX_POINTS} points '
                          'a motion may have: choose a shorter window (start, end)')
    if len(used) < 2:
        window = f'[{0.0 if start is None else start!r}, {after_first[-1] if end is None else end!r}] s'
        raise MotionError(f'{where}: {len(used)} of its {len(messages)} messages (t = 0.0 to {after_first[-1]!r} s) '
                          f'within the window {window}: a motion needs two')
    chosen = list(messages[used[0]].name) if joints is None else list(joints)
    if not chosen:
        raise MotionError(f'{where}: no joints to take (message {used[0]} names none)')
    if len(chosen) > MAX_JOINTS:
        raise MotionError(f'{where}: {len(chosen)} joints to take, more than the {MAX_JOINTS} a motion may drive')
    repeated = sorted(name for name, count in Counter(chosen).items() if count > 1)
    if repeated and joints is not None:  # a message's own repeated names are refused below, naming it
        raise MotionError(f'{where}: the joints {repeated} are asked for more than once')
    positions, velocities = [], []
    for i in used:
        message = messages[i]
        names = list(message.name)
        if len(names) > MAX_JOINTS:
            raise MotionError(f'{where}: message {i} names {len(names)} joints, more than the {MAX_JOINTS} an arm may '
                              'have')
        index = {name: k for k, name in enumerate(names)}
        if len(index) != len(names):
            raise MotionError(f'{where}: message {i} names a joint more than once: {shown(names)}')
        if len(message.position) != len(names):
            raise MotionError(f'{where}: message {i} has {len(message.position)} positions for {len(names)} joints')
        if len(message.velocity) not in (0, len(names)):
            raise MotionError(f'{where}: message {i} has {len(message.velocity)} velocities for {len(names)} joints')
        missing = [name for name in chosen if name not in index]
        if missing:
            raise MotionError(f'{where}: message {i} has no joint {shown(missing)[1:-1]} (it has {shown(names)})')
        order = [index[name] for name in chosen]
        positions.append(_finite(where, f'message {i} position', np.asarray(message.position)[order], chosen))
        velocities.append(_finite(where, f'message {i} velocity', np.asarray(message.velocity)[order], chosen)
                          if len(message.velocity) else None)
    with_velocities = all(velocity is not None for velocity in velocities)
    lines = [f'# Motion from the bag {str(bag)!r}, topic {topic!r} ({JOINT_STATE}): messages {used[0]} to {used[-1]} '
             f'of {len(messages)} (t = {after_first[used[0]]!r} to {after_first[used[-1]]!r} s after the first, by '
             f'header stamp), one point each; time_from_start counts from message {used[0]}.']
    if with_velocities:
        lines.append(f'# The last point\'s velocities are written as zero (recorded: {flow_numbers(velocities[-1])}): the '
                     'motion ends at rest, held at its last positions.')
        velocities[-1] = np.zeros(len(chosen))
    else:
        lines.append('# Positions only (not every message has velocities): the JTC joins such points linearly.')
    lines += [f'joint_names: {flow_names(chosen)}', 'points:']
    for n, i in enumerate(used):
        lines.append(f'  - positions: {flow_numbers(positions[n])}')
        if with_velocities:
            lines.append(f'    velocities: {flow_numbers(velocities[n])}')
        lines.append(f'    time_from_start: {(stamps[i] - stamps[used[0]]) / _NANOSEC_PER_SEC!r}')
    return '\n'.join(lines) + '\n'


def _seconds(nanoseconds: int) -> float:
    return nanoseconds / _NANOSEC_PER_SEC


def _finite(where: str, field: str, values, names: Sequence[str] | None = None) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        at = bad[0]
        joint = f'{field} of joint {names[at]!r}' if names is not None else f'{field}[{at}]'
        raise MotionError(f'{where}: {joint} is {float(values[at])!r}: a motion needs finite values')
    return values


