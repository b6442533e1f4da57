"""ddarm.ros.cdr against the two CDR implementations it stands in for: rclpy's (rmw_fastrtps, what crosses DDS) and
rosbags' (what the bags hold). Every case both ways: what we write, they read as written; what they write, we read."""

import random
import re
import struct

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from ddarm.ros.cdr import JointStateEncoder, decode_joint_state, encode_clock, stamp_of
from ddarm.ros.interface import read_joint_state, time_msg
from ddarm.samples import MAX_JOINTS, MessageError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
MSGTYPE = 'sensor_msgs/msg/JointState'
FIELDS = ('position', 'velocity', 'effort')


def _cases(count: int, seed: int = 7):
    """Joint names of every length (none, one character, multi-byte UTF-8), 0 to 9 joints, each array given or
    empty, stamps from 0 to beyond 2^31 ns, and the values CDR must carry bit for bit (-0.0, subnormals, NaN)."""
    rng = random.Random(seed)
    special = [0.0, -0.0, 5e-324, 1e308, -np.inf, np.nan, 1 / 3]
    for _ in range(count):
        joints = [''.join(rng.choice('ab_7é漢') for _ in range(rng.randrange(0, 13)))
                  for _ in range(rng.randrange(10))]
        arrays = [None if rng.random() < 0.35 else
                  np.array([rng.choice(special) if rng.random() < 0.2 else rng.gauss(0, 100) for _ in joints])
                  for _ in FIELDS]
        t = rng.choice([0.0, 0.01 * rng.randrange(10 ** 6), rng.random() * 3e4, 2.0 ** 31 - 0.5])
        yield joints, t, arrays


def _rosbags_bytes(joints, t, arrays) -> bytes:
    stamp = stamp_of(t)
    types = TYPESTORE.types
    message = types[MSGTYPE](
        header=types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](sec=stamp.sec,
                                                                                      nanosec=stamp.nanosec),
                                            frame_id=''),
        name=list(joints),
        **{field: np.empty(0) if values is None else values for field, values in zip(FIELDS, arrays)})
    return bytes(TYPESTORE.serialize_cdr(message, MSGTYPE))


def _same_values(first, second) -> bool:
    return np.array_equal(np.asarray(first, dtype=float).view(np.int64), np.asarray(second, dtype=float).view(np.int64))


@pytest.mark.parametrize('case', list(_cases(300)), ids=lambda case: f'{len(case[0])}-joints-t{case[1]:.3f}')
def test_what_we_write_is_rosbags_bytes_and_rclpy_reads_it_as_written(case):
    joints, t, arrays = case
    data = JointStateEncoder(joints).encode(t, *arrays)
    assert data == _rosbags_bytes(joints, t, arrays)  # rosbags zeroes its padding, as we do: the very same bytes
    msg = deserialize_message(data, JointState)
    stamp = time_msg(t)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (stamp.sec, stamp.nanosec, '')
    assert list(msg.name) == joints
    for field, values in zip(FIELDS, arrays):
        assert _same_values(getattr(msg, field), [] if values is None else values)


@pytest.mark.parametrize('seed', range(40))
def test_what_rclpy_writes_we_read_as_written(seed):
    """Any frame_id, arrays of any length (not only the names'), and rclpy's padding bytes, which it leaves
    unset, and the trailing bytes of its buffer."""
    rng = random.Random(seed)
    for joints, t, arrays in _cases(10, seed):
        msg = JointState()
        msg.header.stamp = time_msg(t)
        msg.header.frame_id = ''.join(rng.choice('base_/é') for _ in range(rng.randrange(9)))
        msg.name = joints
        for field, values in zip(FIELDS, arrays):
            setattr(msg, field, [rng.gauss(0, 1) for _ in range(rng.randrange(12))] if values is None
                    else values.tolist())
        fields = decode_joint_state(serialize_message(msg))
        assert fields.header.frame_id == msg.header.frame_id and list(fields.name) == joints
        assert (fields.header.stamp.sec, fields.header.stamp.nanosec) == (msg.header.stamp.sec,
                                                                          msg.header.stamp.nanosec)
        for field in FIELDS:
            assert _same_values(getattr(fields, field), getattr(msg, field))


def test_a_decoded_state_reads_as_rclpys_message_of_it_reads():
    joints = ['joint_1', 'joint_2', 'joint_3']
    q, v, effort = np.array([0.1, -2.5, 1e-300]), np.array([3.0, 0.0, -0.0]), np.array([1e6, -7.25, 2.0])
    data = JointStateEncoder(joints[::-1]).encode(0.37, q[::-1], v[::-1], effort[::-1])
    ours = read_joint_state(decode_joint_state(data), joints, 0.01, need_effort=True)
    theirs = read_joint_state(deserialize_message(data, JointState), joints, 0.01, need_effort=True)
    assert ours.n == theirs.n == 37
    for field in ('q', 'v', 'effort'):
        assert _same_values(getattr(ours, field), getattr(theirs, field))
    np.testing.assert_array_equal(ours.q, q)


def test_the_encoder_refuses_arrays_that_are_not_one_value_per_joint():
    encoder = JointStateEncoder(['a', 'b'])
    for values in (np.ones(3), np.ones((2, 1)), [1.0]):
        with pytest.raises(MessageError, match='2 joints'):
            encoder.encode(0.0, values)


def _valid() -> bytes:
    return JointStateEncoder(['joint_1', 'joint_2']).encode(1.5, [1.0, 2.0], [3.0, 4.0])


@pytest.mark.parametrize('length', range(len(_valid())))
def test_every_truncation_of_a_state_is_refused_never_misread(length):
    with pytest.raises(MessageError, match=r'joint state( on /js)?: '):
        decode_joint_state(_valid()[:length], 'joint state on /js')


def _patched(offset: int, value: bytes) -> bytes:
    data = bytearray(_valid())
    data[offset:offset + len(value)] = value
    return bytes(data)


@pytest.mark.parametrize('data, problem', [
    (b'\x00\x00\x00\x00' + _valid()[4:],  # big-endian
     'not a stamped message in little-endian CDR (96 bytes, encapsulation 0000)'),
    (b'\x00\x07\x00\x00' + _valid()[4:], 'encapsulation 0007'),  # XCDR2
    (_patched(8, struct.pack('<I', 10 ** 9)), 'stamp nanosec = 1000000000 is not below 10^9'),
    (_patched(12, struct.pack('<I', 10 ** 6)), 'header.frame_id says 1000000 bytes, more than the bytes left hold'),
    (_patched(20, struct.pack('<I', MAX_JOINTS + 1)), f'more than the {MAX_JOINTS} allowed'),
    (_patched(24, struct.pack('<I', 73)), 'name[0] says 73 bytes, more than the bytes left hold'),
    (_patched(28, b'\xff'), 'name[0] is not UTF-8'),
    (_patched(48, struct.pack('<I', 2 ** 31)), 'position has 2147483648 values, more than the bytes left hold'),
])
def test_bytes_that_break_the_rules_are_refused_naming_the_field(data, problem):
    with pytest.raises(MessageError, match=re.escape(problem)):
        decode_joint_state(data, 'command on /effort_command')


def test_the_offsets_the_refusals_patch_are_those_fields():
    data = _valid()
    assert struct.unpack_from('<iI', data, 4) == (1, 500_000_000)
    assert struct.unpack_from('<III', data, 12) == (1, 0, 2)  # frame_id '' (length 1, then its NUL), 2 names
    assert struct.unpack_from('<I', data, 24) == (8,) and data[28:36] == b'joint_1\x00'
    assert struct.unpack_from('<I', data, 48) == (2,) and struct.unpack_from('<2d', data, 52) == (1.0, 2.0)


@pytest.mark.parametrize('seconds', [0.0, 0.01, 0.7, 1.23, 59.99, 3600.5, 0.9999999999, 2.0 ** 31 - 1.0])
def test_the_stamp_of_a_time_is_the_nearest_nanosecond(seconds):
    stamp = stamp_of(seconds)
    assert 0 <= stamp.nanosec < 10 ** 9
    assert abs(stamp.sec + stamp.nanosec * 1e-9 - seconds) <= 5e-10 + abs(seconds) * 2 ** -52


@pytest.mark.parametrize('seconds', [0.0, 0.01, 1.23, 3600.5, 2.0 ** 31 - 1.0])
def test_a_clock_tick_is_rclpys_and_rosbags_clock(seconds):
    data = encode_clock(seconds)
    stamp = time_msg(seconds)
    assert deserialize_message(data, Clock).clock == stamp
    types = TYPESTORE.types
    assert data == bytes(TYPESTORE.serialize_cdr(types['rosgraph_msgs/msg/Clock'](
        clock=types['builtin_interfaces/msg/Time'](sec=stamp.sec, nanosec=stamp.nanosec)), 'rosgraph_msgs/msg/Clock'))


def test_strings_read_as_fast_cdr_reads_them():
    """What a foreign writer may send and rmw_fastrtps reads: an empty string of length 0, one without its NUL,
    one with a NUL inside (the text ends there)."""
    def state(name: bytes, length: int) -> bytes:
        body = struct.pack('<iI', 0, 0) + struct.pack('<I', 1) + b'\x00' + bytes(3) + struct.pack('<I', 1)
        body += struct.pack('<I', length) + name
        body += bytes(-len(body) % 4) + struct.pack('<III', 0, 0, 0)
        return b'\x00\x01\x00\x00' + body
    for name, length, expected in ((b'', 0, ''), (b'jk', 2, 'jk'), (b'j\x00x\x00', 4, 'j')):
        data = state(name, length)
        assert list(decode_joint_state(data).name) == list(deserialize_message(data, JointState).name) == [expected]
