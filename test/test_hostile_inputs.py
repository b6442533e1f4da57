"""Hostile data files, bags and cluster addresses (issue 23): every input has a stated bound, refused at once
beyond it with a one-line error naming the file and the field, and no refusal writes out a whole value."""

import errno
import importlib.util
import os
import re
import socket
import struct
import sys
import tempfile
import threading
import tracemalloc

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.writer import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

from ddarm import datafiles
from ddarm.cli.main import main
from ddarm.motion import files, from_bag
from ddarm.motion.files import MAX_FILE_BYTES, MAX_JOINTS, MAX_NODES, MAX_POINTS, load_motion
from ddarm.motion.programmed import MotionError
from ddarm.motion.waypoints import WaypointMotion
from ddarm.paper.settings import SettingsError, load_settings
from ddarm.recording import bags
from ddarm.recording.bags import BagError, score_bag
from ddarm.tuning import campaign
from ddarm.tuning.campaign import MAX_JOBS, CampaignError, load_campaign

if sys.version_info >= (3, 14):
    from compression import zstd
else:
    from backports import zstd

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
JOINT_STATE = 'sensor_msgs/msg/JointState'
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'
Header = TYPESTORE.types['std_msgs/msg/Header']
Time = TYPESTORE.types['builtin_interfaces/msg/Time']
Duration = TYPESTORE.types['builtin_interfaces/msg/Duration']
JointState = TYPESTORE.types[JOINT_STATE]
JointTrajectory = TYPESTORE.types[JOINT_TRAJECTORY]
Point = TYPESTORE.types['trajectory_msgs/msg/JointTrajectoryPoint']
EMPTY = np.array([], dtype=float)
GOOD_MOTION = 'joint_names: [a, b]\nduration: 2.0\nprofile: bang_bang\nstart: [0.0, 1.0]\ngoal: [1.0, -1.0]\n'
# Far more than any bounded refusal needs, far less than a value expanded by aliases takes.
MEMORY_BOUND = 64 * 2**20


def alias_bomb(levels: int, width: int = 9) -> str:
    """A YAML flow list whose items are anchors, each listing the one before `width` times, and last an alias of
    the last of them: width^(levels+1) values in a few hundred bytes."""
    items = [f'&a0 [{", ".join(["0"] * width)}]']
    items += [f'&a{i} [{", ".join([f"*a{i - 1}"] * width)}]' for i in range(1, levels + 1)]
    return f'[{", ".join(items)}, *a{levels}]'


def refused_within_memory(error, call, *arguments, memory: int = MEMORY_BOUND) -> str:
    tracemalloc.start()
    try:
        with pytest.raises(error) as refused:
            call(*arguments)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < memory, peak
    message = str(refused.value)
    assert len(message) < 1000, message[:1000]
    return message


LOADERS = {'motion': (load_motion, MotionError, 'joint_names'),
           'campaign': (load_campaign, CampaignError, 'description'),
           'settings': (load_settings, SettingsError, 'delays')}


def with_others(path, kind: str, line: str):
    """`line` and the other fields a good file of the kind has, so that the field of `line` is the one refused."""
    others = {'motion': GOOD_MOTION.replace('joint_names: [a, b]\n', ''), 'campaign': 'laws: [pd_gravity]\n',
              'settings': ''}[kind]
    path.write_text(line + others)
    return path


@pytest.mark.parametrize('kind', sorted(LOADERS))
def test_an_alias_bomb_is_refused_before_it_is_expanded(tmp_path, kind):
    load, error, field = LOADERS[kind]
    path = with_others(tmp_path / f'{kind}.yaml', kind, f'{field}: {alias_bomb(9)}\n')  # 9^10 values
    assert path.stat().st_size < 1000
    message = refused_within_memory(error, load, path)
    assert message.startswith(f'{path}: ') and f'more than {MAX_NODES} values' in message


@pytest.mark.parametrize('kind', ['motion', 'campaign'])
def test_a_value_repeated_by_aliases_within_the_bound_is_refused_by_its_field_and_shown_short(tmp_path, kind):
    load, error, field = LOADERS[kind]
    path = tmp_path / f'{kind}.yaml'
    with_others(path, kind, f'{field}: {alias_bomb(5, width=10)}\n')  # 2.2 million values, aliases expanded
    message = refused_within_memory(error, load, path, memory=2**20)  # their repr alone: 3 MB
    assert field in message and ('…' in message or '...' in message), message


def test_an_alias_inside_the_value_it_names_is_refused(tmp_path):
    path = tmp_path / 'motion.yaml'
    path.write_text(GOOD_MOTION.replace('joint_names: [a, b]', 'joint_names: &names [a, *names]'))
    with pytest.raises(MotionError, match="the alias 'names' is inside the value it names"):
        load_motion(path)


@pytest.mark.parametrize('kind', ['motion', 'campaign'])
def test_a_data_file_larger_than_its_bound_is_refused_before_it_is_read(tmp_path, kind, monkeypatch):
    load, error, _ = LOADERS[kind]
    path = tmp_path / f'{kind}.yaml'
    with path.open('wb') as file:  # sparse: no disk taken
        file.truncate(MAX_FILE_BYTES + 1)
    monkeypatch.setattr(files.DataLoader, 'get_single_data', lambda self: pytest.fail('the file was parsed'))
    with pytest.raises(error, match=f'holds {MAX_FILE_BYTES + 1} bytes, more than the {MAX_FILE_BYTES}'):
        load(path)


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    path = tmp_path / 'motion.yaml'
    os.mkfifo(path)

    def unblock():  # a reader that waits for a writer would otherwise wait for ever
        with open(path, 'wb'):
            pass

    guard = threading.Timer(30.0, unblock)
    guard.start()
    try:
        with pytest.raises(MotionError, match='is a FIFO, not a regular file'):
            load_motion(path)
    finally:
        guard.cancel()


def waypoint_file(count: int, joints: int = 1) -> str:
    names = ', '.join(f'j{i}' for i in range(joints))
    zeros = ', '.join(['0.5'] * joints)
    return f'joint_names: [{names}]\npoints:\n' + ''.join(
        f'  - {{positions: [{zeros}], time_from_start: {k / 100!r}}}\n' for k in range(count))


def test_a_motion_of_the_most_points_loads_and_one_more_is_refused_naming_points(tmp_path):
    path = tmp_path / 'motion.yaml'
    path.write_text(waypoint_file(MAX_POINTS))
    tracemalloc.start()
    try:
        motion = load_motion(path).motion
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(motion.times) == MAX_POINTS and motion.duration == (MAX_POINTS - 1) / 100
    # PyYAML's nodes took 1 GB for a file of this size; the values themselves, a small multiple of the file.
    assert peak < 40 * path.stat().st_size, (peak, path.stat().st_size)
    path.write_text(waypoint_file(MAX_POINTS + 1))
    with pytest.raises(MotionError, match=f'points holds {MAX_POINTS + 1} points, more than the {MAX_POINTS}'):
        load_motion(path)
    with pytest.raises(MotionError, match=f'{MAX_POINTS + 1} points, more than the {MAX_POINTS}'):
        WaypointMotion(np.arange(MAX_POINTS + 1) / 100, np.zeros((MAX_POINTS + 1, 1)))


def test_a_motion_of_more_joints_than_the_bound_is_refused_naming_joint_names(tmp_path):
    path = tmp_path / 'motion.yaml'
    count = MAX_JOINTS + 1
    path.write_text(f'joint_names: [{", ".join(f"j{i}" for i in range(count))}]\nduration: 1.0\nprofile: bang_bang\n'
                    f'start: [{", ".join(["0.0"] * count)}]\ngoal: [{", ".join(["1.0"] * count)}]\n')
    with pytest.raises(MotionError, match=f'joint_names names {count} joints, more than the {MAX_JOINTS}'):
        load_motion(path)


def test_a_campaign_of_more_jobs_than_the_bound_is_refused_before_any_job_is_built(tmp_path, monkeypatch):
    motions = ''.join(f'  - {{name: m{i}, trajectory: 1}}\n' for i in range(MAX_JOBS // 2 + 1))
    path = tmp_path / 'campaign.yaml'
    path.write_text(f'index: I\nlaws: [computed_torque, pd_gravity]\nmotions:\n{motions}')
    monkeypatch.setattr(campaign, '_job', lambda *arguments: pytest.fail('a job was built'))
    with pytest.raises(CampaignError, match=f'{MAX_JOBS + 2} jobs .* more than the {MAX_JOBS} a campaign may run'):
        load_campaign(path)


def test_a_campaign_number_beyond_a_float_is_refused_naming_it(tmp_path):
    path = tmp_path / 'campaign.yaml'
    path.write_text('index: I\nlaws: [pd_gravity]\nperiod: 1' + '0' * 400 + '\n')
    with pytest.raises(CampaignError, match='period: must be a finite number'):
        load_campaign(path)


def write_bag(path, topic: str, msgtype: str, messages: list):
    with Writer(path, version=9) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
        for k, message in enumerate(messages):
            writer.write(connection, 1_000_000 * (k + 1), TYPESTORE.serialize_cdr(message, msgtype))
    return path


def joint_state(k: int, names: list, position) -> JointState:
    return JointState(header=Header(stamp=Time(sec=1, nanosec=10_000_000 * k), frame_id=''), name=names,
                      position=np.asarray(position, dtype=float), velocity=EMPTY, effort=EMPTY)


def test_a_bag_whose_metadata_holds_aliases_is_refused_by_score_and_motion(tmp_path, capsys):
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, {'test': True}) as writer:  # every topic of an episode, marked complete
        writer.close(complete=True)
    metadata = (bag / 'metadata.yaml').read_text()
    assert '  custom_data:\n' in metadata
    # What publishes each topic, a JSON text in a bag ddarm writes: here a list of 9^10 values.
    (bag / 'metadata.yaml').write_text(metadata.replace('  custom_data:\n', '  custom_data:\n'
                                                        f'    ddarm.publishers: {alias_bomb(9)}\n'))
    message = refused_within_memory(BagError, score_bag, bag)
    assert message.startswith(f'{bag}: ') and 'anchor or alias' in message
    message = refused_within_memory(MotionError, from_bag.motion_file_from_bag, bag)
    assert message.startswith(f'{bag}: ') and 'anchor or alias' in message
    assert main(['score', str(bag)]) == 2
    assert 'anchor or alias' in capsys.readouterr().err


@pytest.mark.parametrize('mode', [CompressionMode.FILE, CompressionMode.MESSAGE], ids=['file', 'message'])
def test_a_compressed_bag_is_refused_before_rosbags_inflates_it(tmp_path, capsys, mode, monkeypatch):
    # rosbags inflates a file-compressed bag whole into the temporary folder: a few MB of zeros became 2 GiB there.
    bag = tmp_path / 'bag'
    writer = Writer(bag, version=9)
    writer.set_compression(mode, CompressionFormat.ZSTD)
    with writer:
        connection = writer.add_connection('/joint_states', JOINT_STATE, typestore=TYPESTORE)
        for k in range(3):
            writer.write(connection, 1_000_000 * (k + 1),
                         TYPESTORE.serialize_cdr(joint_state(k, ['j1'], [0.1 * k]), JOINT_STATE))
    temporary = tmp_path / 'tmp'
    temporary.mkdir()
    monkeypatch.setenv('TMPDIR', str(temporary))
    monkeypatch.setattr(tempfile, 'tempdir', None)  # tempfile reads TMPDIR once, then caches the folder
    named = f"{bag}: metadata.yaml: compression_mode '{mode.name.lower()}' (zstd): compressed bags are not read"
    for refused in (lambda: score_bag(bag), lambda: from_bag.motion_file_from_bag(bag)):
        with pytest.raises((BagError, MotionError), match=re.escape(named)):
            refused()
    assert main(['motion', str(bag), '--out', str(tmp_path / 'motion.yaml')]) == 2
    assert named in capsys.readouterr().err
    assert list(temporary.iterdir()) == [] and not (tmp_path / 'motion.yaml').exists()


def with_zstd_chunks(bag, chunks: list) -> list:
    """Put into the bag's MCAP file, after its header record, a zstd chunk of `inflated` zero bytes whose header
    states `declared`, for each (declared, inflated) of `chunks`, and leave its footer naming no summary: rosbags
    then walks the records, inflating each chunk it meets. The chunks' offsets."""
    (storage,) = bag.glob('*.mcap')
    data = storage.read_bytes()
    start = 8 + 9 + struct.unpack_from('<Q', data, 9)[0]  # the magic, the header record
    offsets, records = [], b''
    for declared, inflated in chunks:
        compressor = zstd.ZstdCompressor()  # a MiB of zeros at a time: the test holds no inflated chunk either
        compressed = b''.join(compressor.compress(bytes(2**20)) for _ in range(inflated // 2**20))
        compressed += compressor.compress(bytes(inflated % 2**20)) + compressor.flush()
        content = struct.pack('<QQQII', 0, 0, declared, 0, 4) + b'zstd' + struct.pack('<Q', len(compressed))
        offsets.append(start + len(records))
        records += struct.pack('<BQ', 0x06, len(content) + len(compressed)) + content + compressed
    footer = len(data) - 37  # opcode, length, summary_start, ...
    storage.write_bytes(data[:start] + records + data[start:footer + 9] + bytes(8) + data[footer + 17:])
    return offsets


@pytest.mark.parametrize('declared, refused', [
    (6 * 2**30, 'inflates to 6442450944 bytes (its uncompressed_size), the chunks to 6442450944 so far: more than '
                f'the {datafiles.MAX_INFLATED_BYTES} a bag may'),
    (1000, 'inflates to more than the 1000 bytes its uncompressed_size states'),
], ids=['stated', 'understated'])
def test_an_mcap_chunk_that_inflates_beyond_the_bound_is_refused_before_rosbags_inflates_it(tmp_path, capsys,
                                                                                          declared, refused):
    # A 230 kB bag whose one zstd chunk inflated to 6 GiB grew ddarm score to 6.5 GB before a MemoryError; here
    # 256 MiB (8 kB compressed), which rosbags inflates whole whatever the chunk's header states.
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, {'test': True}) as writer:  # marked complete: score reads its storage
        writer.close(complete=True)
    (offset,) = with_zstd_chunks(bag, [(declared, 2**28)])
    (storage,) = bag.glob('*.mcap')
    named = f'{bag}: storage file {storage.name}: the zstd chunk at byte {offset} {refused}'
    for call in (score_bag, from_bag.motion_file_from_bag):
        assert refused_within_memory((BagError, MotionError), call, bag) == named
    for command in (['score', str(bag)], ['motion', str(bag), '--out', str(tmp_path / 'motion.yaml')]):
        assert main(command) == 2
        printed = capsys.readouterr()
        assert named in printed.err and 'Traceback' not in printed.err + printed.out


def test_mcap_chunks_that_inflate_beyond_the_bound_together_are_refused(tmp_path, monkeypatch):
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, {'test': True}) as writer:
        writer.close(complete=True)
    offsets = with_zstd_chunks(bag, [(2**20, 2**20)] * 3)
    monkeypatch.setattr(datafiles, 'MAX_INFLATED_BYTES', 2**21 + 1)
    with pytest.raises(BagError, match=f'chunk at byte {offsets[2]} inflates to {2**20} bytes .*, the chunks to '
                                       f'{3 * 2**20} so far: more than the {2**21 + 1}'):
        score_bag(bag)


def test_an_mcap_file_of_more_records_than_the_bound_is_refused_before_they_are_walked(tmp_path, monkeypatch):
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, {'test': True}) as writer:
        writer.close(complete=True)
    with_zstd_chunks(bag, [(10, 10)] * 5)
    monkeypatch.setattr(datafiles, 'MAX_MCAP_RECORDS', 5)
    (storage,) = bag.glob('*.mcap')
    with pytest.raises(BagError, match=f'{bag}: storage file {storage.name} holds more than 5 MCAP records'):
        score_bag(bag)


def compressed_chunks_bag(path, count: int):
    """A bag of `count` /joint_states messages in zstd chunks of rosbags' own (its metadata states no
    compression), indexed in its summary."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        connection = writer.add_connection('/joint_states', JOINT_STATE, typestore=TYPESTORE)
        for k in range(count):
            writer.write(connection, 1_000_000 * (k + 1),
                         TYPESTORE.serialize_cdr(joint_state(k, ['j1'], [0.1 * k]), JOINT_STATE))
    return path


def test_a_bag_of_zstd_chunks_is_read_and_one_whose_chunk_index_misnames_its_chunk_is_refused(tmp_path):
    bag = compressed_chunks_bag(tmp_path / 'bag', 3)
    assert 'joint_names: [j1]' in from_bag.motion_file_from_bag(bag)
    (storage,) = bag.glob('*.mcap')
    data = bytearray(storage.read_bytes())
    offset = struct.unpack_from('<Q', data, len(data) - 37 + 9)[0]  # the footer's summary_start
    while data[offset] != 0x08:  # to the chunk index
        offset += 9 + struct.unpack_from('<Q', data, offset + 1)[0]
    end = offset + 9 + struct.unpack_from('<Q', data, offset + 1)[0]
    chunk, compressed = struct.unpack_from('<Q', data, offset + 9 + 16)[0], struct.unpack_from('<Q', data, end - 16)[0]
    struct.pack_into('<Q', data, end - 16, compressed + 9)  # the chunk's data and the record after it
    storage.write_bytes(data)
    with pytest.raises(MotionError, match=re.escape(f'{bag}: storage file {storage.name}: a chunk index names '
                                                    f'{compressed + 9} bytes of zstd data at byte {chunk}, where no '
                                                    'such chunk is')):
        from_bag.motion_file_from_bag(bag)


def test_a_topic_of_more_messages_than_the_bound_is_refused_as_they_are_counted(tmp_path, monkeypatch):
    bag = write_bag(tmp_path / 'bag', '/joint_states', JOINT_STATE,
                    [joint_state(k, ['a'], [0.1 * k]) for k in range(5)])
    monkeypatch.setattr(from_bag, 'MAX_TOPIC_MESSAGES', 4)
    with pytest.raises(MotionError, match='/joint_states holds more than 4 messages'):
        from_bag.motion_file_from_bag(bag)


def test_bag_messages_of_more_joints_than_the_bound_are_refused_at_once(tmp_path):
    names = [f'j{i}' for i in range(2000)]  # the old per-joint list searches were quadratic in this
    states = write_bag(tmp_path / 'states', '/joint_states', JOINT_STATE,
                       [joint_state(k, names, np.full(len(names), 0.1 * k)) for k in range(3)])
    with pytest.raises(MotionError, match=f'2000 joints.* more than the {MAX_JOINTS}'):
        from_bag.motion_file_from_bag(states)
    points = [Point(positions=np.full(len(names), float(k)), velocities=EMPTY, accelerations=EMPTY, effort=EMPTY,
                    time_from_start=Duration(sec=k, nanosec=0)) for k in range(2)]
    trajectory = write_bag(tmp_path / 'trajectory', '/reference', JOINT_TRAJECTORY, [JointTrajectory(
        header=Header(stamp=Time(sec=0, nanosec=0), frame_id=''), joint_names=names, points=points)])
    with pytest.raises(MotionError, match=f'names 2000 joints, more than the {MAX_JOINTS}'):
        from_bag.motion_file_from_bag(trajectory)


def test_ddarm_motion_takes_the_reference_ddarm_itself_recorded(tmp_path, capsys):
    from rclpy.serialization import serialize_message

    from ddarm.episodes.spec import EpisodeSpec, plan_episode
    from ddarm.ros.interface import reference_msg

    plan = plan_episode(EpisodeSpec(controller='computed_torque', kp=(900.0,) * 3, kv=(60.0,) * 3))
    assert np.any(plan.a_ref[-1] != 0.0)  # the bang-bang's deceleration, at T
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, {'test': True}) as writer:
        writer.write('/reference', 0, serialize_message(reference_msg(list(plan.joint_names), plan.times, plan.q_ref,
                                                                       plan.v_ref, plan.a_ref, plan.nominal)))
        writer.close(complete=True)
    out = tmp_path / 'reference.yaml'
    assert main(['motion', str(bag), '--topic', '/reference', '--out', str(out)]) == 0
    assert f'{len(plan.times)} points of 3 joints' in capsys.readouterr().out
    motion = load_motion(out).motion
    q, v, _ = motion.sample(plan.times)
    np.testing.assert_allclose(q, plan.q_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(v, plan.v_ref, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(motion.accelerations[-1], plan.a_ref[-1])  # as recorded, the last segment's end


class SilentListener:
    """A TCP port on 127.0.0.1 that accepts connections and never answers (a port of some other service)."""

    def __init__(self, reply: bytes = b'') -> None:
        self.server = socket.create_server(('127.0.0.1', 0))
        self.port = self.server.getsockname()[1]
        self.reply, self.connections = reply, []
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self) -> None:
        while True:
            try:
                connection, _ = self.server.accept()
            except OSError:
                return
            self.connections.append(connection)
            if self.reply:
                connection.sendall(self.reply)

    def close(self) -> None:
        self.server.close()
        for connection in self.connections:
            connection.close()


@pytest.mark.parametrize('reply', [b'', b'HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n'])
def test_ray_refuses_an_address_where_something_that_is_not_ray_listens(monkeypatch, reply):
    if importlib.util.find_spec('ray') is None:  # not imported here: RayCluster sets its switch first
        pytest.skip('Ray is not installed (pip install .[ray])')
    from ddarm.tuning.cluster import LOOPBACK_SWITCH, ClusterError, RayCluster

    monkeypatch.setenv(LOOPBACK_SWITCH, os.environ.get(LOOPBACK_SWITCH, '0'))  # as RayCluster sets it; restored after
    listener = SilentListener(reply)
    try:
        with pytest.raises(ClusterError, match=f"--ray 127.0.0.1:{listener.port}: something listens there, but it "
                                               "does not answer as a Ray cluster's GCS"):
            RayCluster(f'127.0.0.1:{listener.port}')
    finally:
        listener.close()


@pytest.mark.parametrize('change', ['fifo', 'outside', 'in a subfolder', 'not a list'])
def test_a_bag_whose_storage_file_is_no_regular_file_inside_it_is_refused_without_reading_it(tmp_path, capsys,
                                                                                              change):
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, {'test': True}) as writer:
        writer.close(complete=True)
    metadata = (bag / 'metadata.yaml').read_text()
    (storage,) = bag.glob('*.mcap')
    if change == 'fifo':  # reading it would wait for a writer for ever
        storage.unlink()
        os.mkfifo(storage)
        named = f'storage file {storage.name} is not a regular file'
    elif change == 'outside':
        (bag / 'metadata.yaml').write_text(metadata.replace(f'- {storage.name}', f'- ../{storage.name}'))
        named = f"relative_file_paths entry '../{storage.name}' is not a file inside the bag"
    elif change == 'in a subfolder':  # rosbags opens the name's last part, here a FIFO, whatever is in sub/
        (bag / 'sub').mkdir()
        storage.rename(bag / 'sub' / storage.name)
        os.mkfifo(storage)
        (bag / 'metadata.yaml').write_text(metadata.replace(f'- {storage.name}', f'- sub/{storage.name}'))
        named = f"relative_file_paths entry 'sub/{storage.name}' is not a file inside the bag"
    else:
        storage.unlink()
        os.mkfifo(bag / 'b')
        (bag / 'metadata.yaml').write_text(metadata.replace(f'  - {storage.name}', '  b', 1).replace(
            'relative_file_paths:\n  b', 'relative_file_paths: b'))
        named = 'relative_file_paths is str, not a list of file names'
    guard = threading.Timer(30.0, lambda: [open(fifo, 'wb').close() for fifo in bag.rglob('*') if fifo.is_fifo()])
    guard.start()
    try:
        for refused in (lambda: score_bag(bag), lambda: from_bag.motion_file_from_bag(bag)):
            with pytest.raises((BagError, MotionError), match=named):
                refused()
        assert main(['score', str(bag)]) == 2
        assert named in capsys.readouterr().err
    finally:
        guard.cancel()


def test_a_parameter_file_holding_an_alias_bomb_is_refused_before_it_is_expanded(tmp_path):
    from ddarm.ros.parameter_files import ParameterFileError, parameter_document

    path = tmp_path / 'controller.yaml'
    path.write_text(f'controller:\n  ros__parameters:\n    kp: {alias_bomb(9)}\n')
    message = refused_within_memory(ParameterFileError, parameter_document, str(path))
    assert message.startswith(f'parameter file {path} holds a YAML anchor or alias'), message


def test_a_parameter_file_larger_than_its_bound_is_refused_unread(tmp_path):
    from ddarm.ros.parameter_files import ParameterFileError, parameter_document

    path = tmp_path / 'controller.yaml'
    with path.open('wb') as file:
        file.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(ParameterFileError, match=f'holds {MAX_FILE_BYTES + 1} bytes'):
        parameter_document(str(path))


def test_a_parameter_file_of_more_values_than_its_bound_is_refused_before_a_node_takes_them(tmp_path, capsys):
    # 3,000,000 items (12 MB, within the byte bound) kept `ddarm controller` starting for over 11 minutes.
    from ddarm.datafiles import MAX_PARAMETER_VALUES
    from ddarm.ros.parameter_files import parameter_document

    def parameter_file(name: str, items: int):
        path = tmp_path / name
        path.write_text('computed_torque:\n  ros__parameters:\n    kp: [' + ', '.join(['1.0'] * items) + ']\n')
        return path
    # Three keys (the node, ros__parameters, kp) and the items are its values.
    assert len(parameter_document(str(parameter_file('most.yaml', MAX_PARAMETER_VALUES - 3)))['computed_torque'][
        'ros__parameters']['kp']) == MAX_PARAMETER_VALUES - 3
    path = parameter_file('more.yaml', MAX_PARAMETER_VALUES - 2)
    assert main(['controller', 'computed_torque', '--ros-args', '--params-file', str(path)]) == 2
    printed = capsys.readouterr()  # a node's refusal is on stdout, beside its log
    assert f'{path} holds more than {MAX_PARAMETER_VALUES} values' in printed.out, printed
    assert 'Traceback' not in printed.out + printed.err


@pytest.mark.parametrize('episode, named', [
    ({'test': True}, 'holds no spec'), ({'spec': {'period': 'x'}, 'joints': ['a']}, "holds the spec period 'x'"),
    ({'spec': {'period': 0.01}, 'joints': 'a'}, 'holds no joints'), ([1, 2], 'holds no spec'),
])
def test_a_bag_whose_episode_configuration_is_not_ddarms_is_refused_naming_the_field(tmp_path, capsys, episode,
                                                                                     named):
    bag = tmp_path / 'bag'
    with bags.EpisodeBagWriter(bag, episode) as writer:
        writer.close(complete=True)
    with pytest.raises(BagError, match=f'{bag}: /ddarm/episode {named}'):
        score_bag(bag)
    assert main(['score', str(bag)]) == 2
    assert 'not the configuration ddarm records' in capsys.readouterr().err


@pytest.fixture
def loop(tmp_path):
    """tmp_path/loop1, a symbolic link to tmp_path/loop2, which links back to it: os.stat says ELOOP."""
    os.symlink('loop2', tmp_path / 'loop1')
    os.symlink('loop1', tmp_path / 'loop2')
    return tmp_path / 'loop1'


def one_line_refusal(capsys, arguments: list) -> str:
    assert main([str(argument) for argument in arguments]) == 2
    out, err = capsys.readouterr()
    assert err.count('\n') == 1 and 'Traceback' not in err, (out, err)
    return err


LOOP_REASON = os.strerror(errno.ELOOP)  # 'Too many levels of symbolic links'


@pytest.mark.parametrize('option', ['--urdf', '--model-urdf'])
def test_a_urdf_in_a_symlink_loop_is_refused_as_a_loop_not_as_missing(capsys, tmp_path, loop, option):
    episode = ['episode', '--controller', 'computed_torque', '--omega', '15']
    err = one_line_refusal(capsys, [*episode, option, loop])
    assert f'URDF {loop} cannot be read: {LOOP_REASON}' in err and 'does not exist' not in err, err
    err = one_line_refusal(capsys, [*episode, option, tmp_path / 'absent.urdf'])  # ENOENT alone is 'does not exist'
    assert f'URDF {tmp_path / "absent.urdf"} does not exist' in err, err


def test_a_bag_in_a_symlink_loop_is_refused_as_a_loop_by_score_and_motion(capsys, tmp_path, loop):
    err = one_line_refusal(capsys, ['score', loop])
    assert err == f'ddarm score: {loop}: {LOOP_REASON}\n', err
    err = one_line_refusal(capsys, ['motion', loop, '--out', tmp_path / 'motion.yaml'])
    assert err == f'ddarm motion: {loop}: {LOOP_REASON}\n', err
    # A bag whose metadata.yaml is the loop: named with its reason, not as a bag without metadata.
    (tmp_path / 'bag').mkdir()
    os.symlink(loop, tmp_path / 'bag' / 'metadata.yaml')
    err = one_line_refusal(capsys, ['score', tmp_path / 'bag'])
    assert err == f'ddarm score: {tmp_path / "bag"}: metadata.yaml: {LOOP_REASON}\n', err
    err = one_line_refusal(capsys, ['motion', tmp_path / 'bag', '--out', tmp_path / 'motion.yaml'])
    assert err == f'ddarm motion: {tmp_path / "bag"}: metadata.yaml: {LOOP_REASON}\n', err
    err = one_line_refusal(capsys, ['score', tmp_path / 'absent'])  # ENOENT alone is 'no such bag'
    assert err == f'ddarm score: {tmp_path / "absent"}: no such bag\n', err
    assert not (tmp_path / 'motion.yaml').exists()
