"""sensor_msgs/JointState (and rosgraph_msgs/Clock) in CDR, read and written in place: the states, commands and
clock ticks of every sample.

rclpy turns each message into Python objects field by field when it takes or publishes one; a
lockstep sample crosses two nodes, and that conversion with the reading around it was about a
third of each node's Python time. Written here, not with rosbags' CDR (about 8 µs a message against
2 here), because a node does it at every sample. Plain (XCDR1) little-endian CDR as rmw_fastrtps
writes it: each field aligned to its size from the start of the body, a float64 sequence's elements
to 8 only when it has any. Any JointState rmw_fastrtps reads, this reads the same (any frame_id, names and
lengths, trailing bytes ignored), but for text that is not UTF-8, which it refuses; bytes that break the
rules are a MessageError that says where.
"""

from __future__ import annotations

import functools
import math
import struct
from typing import NamedTuple

import numpy as np

from ddarm.samples import MAX_JOINTS, MessageError

# The encapsulation rmw_fastrtps writes on a little-endian machine, CDR_LE with no options: what the bag reader
# (ddarm.recording.bags.deserialize) takes too.
ENCAPSULATION = b'\x00\x01\x00\x00'
_BODY = len(ENCAPSULATION)
_STAMP = struct.Struct('<iI')
_COUNT = struct.Struct('<I')


class Stamp(NamedTuple):
    """header.stamp as builtin_interfaces/Time has it."""

    sec: int
    nanosec: int


class Header(NamedTuple):
    stamp: Stamp
    frame_id: str


class JointStateFields(NamedTuple):
    """A decoded JointState, with the attributes of rclpy's message that ddarm's readers use."""

    header: Header
    name: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...]
    effort: tuple[float, ...]


def stamp_of(seconds: float) -> Stamp:
    """The stamp of a time in seconds: nanoseconds rounded, carried into the seconds at 10^9."""
    whole = math.floor(seconds)
    nanoseconds = int(round((seconds - whole) * 1e9))
    if nanoseconds == 1_000_000_000:
        whole, nanoseconds = whole + 1, 0
    return Stamp(int(whole), nanoseconds)


@functools.lru_cache(maxsize=2 * MAX_JOINTS)
def _doubles(count: int) -> struct.Struct:
    return struct.Struct(f'<{count}d')


def _refuse(data: bytes, what: str, problem: str):
    raise MessageError(f'{what}: not a JointState in little-endian CDR ({len(data)} bytes): {problem}')


def _string_field(index: int) -> str:
    return 'header.frame_id' if index == 0 else f'name[{index - 1}]'


def read_stamp(data: bytes, what: str) -> Stamp:
    """The stamp of a serialized stamped message (a JointState's header.stamp, a Clock's clock).

    Read in place because it is the message's first field, right after the encapsulation: one
    microsecond where deserialising the message costs thirty, at every sample of a recorder.
    """
    if len(data) < _BODY + _STAMP.size or data[:2] != ENCAPSULATION[:2]:
        raise MessageError(f'{what}: not a stamped message in little-endian CDR ({len(data)} bytes, '
                           f'encapsulation {bytes(data[:2]).hex() or "none"})')
    sec, nanosec = _STAMP.unpack_from(data, _BODY)
    if nanosec >= 1_000_000_000:
        raise MessageError(f'{what}: stamp nanosec = {nanosec} is not below 10^9')
    return Stamp(sec, nanosec)


def decode_joint_state(data: bytes, what: str = 'joint state') -> JointStateFields:
    """A serialized JointState's fields; MessageError for anything else."""
    size = len(data)
    stamp = read_stamp(data, what)
    offset = _BODY + _STAMP.size  # 4-aligned in the body, as every field after a string or a count is made
    strings = []
    count = 0  # of names, read after header.frame_id
    while len(strings) <= count:
        offset += -(offset - _BODY) % 4
        if offset + 4 > size:
            _refuse(data, what, f'it ends before the length of {_string_field(len(strings))}')
        (length,) = _COUNT.unpack_from(data, offset)
        end = offset + 4 + length
        if end > size:
            _refuse(data, what, f'{_string_field(len(strings))} says {length} bytes, more than the bytes left hold')
        try:
            # As Fast CDR reads a string: its length counts the NUL, and the text ends at the first NUL (or at the
            # length, if a foreign writer left the NUL out).
            strings.append(data[offset + 4:end].split(b'\x00', 1)[0].decode())
        except UnicodeDecodeError as error:
            _refuse(data, what, f'{_string_field(len(strings))} is not UTF-8 ({error.reason} at byte {error.start})')
        offset = end
        if len(strings) == 1:
            offset += -(offset - _BODY) % 4
            if offset + 4 > size:
                _refuse(data, what, 'it ends before the length of name')
            (count,) = _COUNT.unpack_from(data, offset)
            if count > MAX_JOINTS:
                _refuse(data, what, f'name says {count} joints, more than the {MAX_JOINTS} allowed')
            offset += 4
    arrays = []
    for field in ('position', 'velocity', 'effort'):
        offset += -(offset - _BODY) % 4
        if offset + 4 > size:
            _refuse(data, what, f'it ends before the length of {field}')
        (count,) = _COUNT.unpack_from(data, offset)
        offset += 4
        if count == 0:
            arrays.append(())
            continue
        offset += -(offset - _BODY) % 8
        if offset + 8 * count > size:
            _refuse(data, what, f'{field} has {count} values, more than the bytes left hold')
        arrays.append(_doubles(count).unpack_from(data, offset))
        offset += 8 * count
    return JointStateFields(Header(stamp, strings[0]), tuple(strings[1:]), *arrays)


def stamp_of_ns(nanoseconds: int) -> Stamp:
    """The stamp of a time in integer nanoseconds: exact, where a wall-clock time in float seconds is not."""
    return Stamp(nanoseconds // 1_000_000_000, nanoseconds % 1_000_000_000)


def encode_clock(t: float | Stamp) -> bytes:
    """A rosgraph_msgs/Clock of time `t` (s, or a Stamp), serialized: the plant's tick at every sample."""
    stamp = t if isinstance(t, Stamp) else stamp_of(t)
    return ENCAPSULATION + _STAMP.pack(stamp.sec, stamp.nanosec)


class JointStateEncoder:
    """Serializes JointStates of fixed joint names (frame_id empty), as rmw_fastrtps would: for `publish`."""

    def __init__(self, joints) -> None:
        self.joints = len(joints)
        self._prefix = self._names_block([str(joint) for joint in joints])

    @staticmethod
    def _names_block(joints: list[str]) -> bytes:
        block = bytearray(b'\x01\x00\x00\x00\x00')  # frame_id: '' and its NUL
        def align4() -> None:
            block.extend(bytes(-(_STAMP.size + len(block)) % 4))
        align4()
        block.extend(_COUNT.pack(len(joints)))
        for joint in joints:
            encoded = joint.encode()
            align4()
            block.extend(_COUNT.pack(len(encoded) + 1) + encoded + b'\x00')
        return bytes(block)

    def encode(self, t: float | Stamp, position=None, velocity=None, effort=None) -> bytes:
        """A JointState stamped `t` (s, or a Stamp) with these arrays (None: empty), each one value per joint."""
        stamp = t if isinstance(t, Stamp) else stamp_of(t)
        parts = [ENCAPSULATION, _STAMP.pack(stamp.sec, stamp.nanosec), self._prefix]
        offset = _STAMP.size + len(self._prefix)  # from the start of the body
        for values in (position, velocity, effort):
            padding = -offset % 4
            offset += padding + 4
            doubles = None if values is None else np.ascontiguousarray(values, dtype='<f8')
            if doubles is not None and doubles.shape != (self.joints,):
                raise MessageError(f'a JointState of {self.joints} joints cannot carry {doubles.shape} values')
            if doubles is None or self.joints == 0:
                parts.append(bytes(padding) + _COUNT.pack(0))
                continue
            alignment = -offset % 8
            parts.append(bytes(padding) + _COUNT.pack(self.joints) + bytes(alignment) + doubles.tobytes())
            offset += alignment + 8 * self.joints
        return b''.join(parts)
