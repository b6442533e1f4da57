"""Episodes recorded as rosbag2 bags and scored from the bag alone; broken, duplicated or foreign evidence and
failed writes refused by name (docs/faults.md 17-19, 25)."""

import errno
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader, Writer

from ddarm.recording.bags import (PUBLISHERS_KEY, SAMPLED_TOPICS, STORAGES, TOPICS, TYPESTORE, BagError,
                              EpisodeBagWriter, bag_status, checked_output_path, child_path, deserialize,
                              read_episode_bag, score_bag)
from ddarm.cli.main import main
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.ros.node_parameters import episode_record
from ddarm.ros.session import run_graph_episode
from graph_helpers import InProcessGraph

SPECS = {
    'computed_torque': EpisodeSpec(controller='computed_torque', kp=(900.0,) * 3, kv=(60.0,) * 3, tau=0.1,
                                   torque_limit='paper'),
    'pd_gravity': EpisodeSpec(controller='pd_gravity', kp=(28000.0, 27000.0, 3500.0), kv=(1760.0, 1700.0, 220.0),
                              delay=0, tau=0.1, torque_limit='paper'),
}


def record(context, spec, path, storage='mcap'):
    graph = InProcessGraph(context, spec)
    with EpisodeBagWriter(path, episode_record(spec, graph.plan, 'ros-lockstep', 'test'), storage) as bag:
        graph.bag = bag
        try:
            result = graph.run()
            bag.close(complete=True)
        finally:
            graph.close()
    return result


@pytest.fixture(scope='module')
def good_bag(tmp_path_factory):
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    path = tmp_path_factory.mktemp('bags') / 'good'
    try:
        record(context, SPECS['computed_torque'], path)
    finally:
        rclpy.try_shutdown(context=context)
    return path


@pytest.mark.parametrize('controller', ['computed_torque', 'pd_gravity'])
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_scores_from_the_bag_equal_the_in_process_indices(ros_context, tmp_path, controller, storage):
    spec = SPECS[controller]
    record(ros_context, spec, tmp_path / 'bag', storage)
    scored, reference = score_bag(tmp_path / 'bag'), run_episode(spec)
    assert np.any(np.abs(reference.scored('command')) > reference.plan.torque_limit)  # the limits matter here
    for key in ('I1', 'I2', 'I'):
        assert scored[key] == pytest.approx(reference.indices()[key], rel=1e-9)
    assert scored['spec'] == spec.to_dict()


def test_ddarm_episode_ros_bag_records_what_it_prints(tmp_path, capsys):
    arguments = ['episode', '--controller', 'pd_gravity', '--omega', '10', '--delay', '0', '--tau', '0.05',
                 '--limited', '--ros', '--bag', str(tmp_path / 'bag'), '--json']
    assert main(arguments) == 0
    printed = json.loads(capsys.readouterr().out)
    assert main(['score', str(tmp_path / 'bag'), '--json']) == 0
    scored = json.loads(capsys.readouterr().out)
    for key in ('I1', 'I2', 'I', 'max_abs_error_deg', 'max_abs_torque', 'spec'):
        assert scored[key] == printed[key]
    episode = read_episode_bag(tmp_path / 'bag').episode
    assert episode['command'].startswith('ddarm episode --controller pd_gravity')


def custom_data(bag) -> dict:
    return yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']['custom_data'] or {}


def copy_bag(source, target, keep=lambda topic: True, transform=None, storage='sqlite3', qos=None, custom=None,
             extra=()):
    """A copy of a bag with some topics dropped, some messages changed or added (`extra`: (topic, timestamp,
    CDR)), some topics' offered QoS (`qos`) or custom data entries (`custom`) replaced."""
    qos, custom = qos or {}, custom or {}
    with Reader(source) as reader, Writer(target, version=9, storage_plugin=STORAGES[storage]) as writer:
        connections = {}
        for connection in reader.connections:
            if keep(connection.topic):
                connections[connection.id] = writer.add_connection(
                    connection.topic, connection.msgtype, typestore=TYPESTORE,
                    offered_qos_profiles=qos.get(connection.topic, connection.ext.offered_qos_profiles))
        for connection, timestamp, raw in reader.messages():
            if connection.id not in connections:
                continue
            if transform is not None:
                message = transform(connection.topic, deserialize(raw, connection.msgtype))
                raw = TYPESTORE.serialize_cdr(message, connection.msgtype)
            writer.write(connections[connection.id], timestamp, raw)
        by_topic = {connection.topic: connection for connection in connections.values()}
        for topic, timestamp, raw in extra:
            writer.write(by_topic[topic], timestamp, raw)
        for key, value in {**custom_data(source), **custom}.items():
            writer.set_custom_data(key, value)
    return target


def test_a_bag_without_the_commands_is_refused(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / 'no_commands', keep=lambda topic: topic != '/effort_command')
    with pytest.raises(BagError, match=r"missing topics \['/effort_command'\]"):
        score_bag(bag)


def test_a_bag_from_another_robot_is_refused(good_bag, tmp_path):
    def rename(topic, message):
        if topic == '/joint_states':
            message.name = ['shoulder', 'elbow', 'wrist']
        return message

    bag = copy_bag(good_bag, tmp_path / 'foreign', transform=rename)
    with pytest.raises(BagError, match='another robot'):
        score_bag(bag)


def test_a_bag_missing_samples_is_incomplete(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / 'holes', transform=lambda topic, message: message)
    with Reader(bag) as reader:
        kept = [(c, t, r) for c, t, r in reader.messages() if not (c.topic == '/joint_states' and t > 5e8)]
    truncated = tmp_path / 'half'
    with Reader(bag) as reader, Writer(truncated, version=9) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE)
                       for c in reader.connections}
        for connection, timestamp, raw in kept:
            writer.write(connections[connection.id], timestamp, raw)
        writer.set_custom_data('ddarm.status', 'complete')
    with pytest.raises(BagError, match='missing: the episode is incomplete'):
        score_bag(truncated)


def test_a_recording_that_never_closed_is_reported_incomplete(good_bag, tmp_path):
    killed = tmp_path / 'killed'
    killed.mkdir()
    for item in good_bag.iterdir():
        if item.name != 'metadata.yaml':  # what a SIGKILL leaves: storage without metadata
            (killed / item.name).write_bytes(item.read_bytes())
    with pytest.raises(BagError, match='never closed'):
        score_bag(killed)


def test_a_truncated_storage_file_is_unreadable_not_scored(good_bag, tmp_path):
    broken = tmp_path / 'broken'
    broken.mkdir()
    for item in good_bag.iterdir():
        data = item.read_bytes()
        (broken / item.name).write_bytes(data if item.name == 'metadata.yaml' else data[: len(data) // 2])
    with pytest.raises(BagError, match='unreadable|missing'):
        score_bag(broken)


def test_a_bag_marked_incomplete_is_not_scored(tmp_path):
    spec = SPECS['computed_torque']
    with EpisodeBagWriter(tmp_path / 'bag', {'spec': spec.to_dict(), 'joints': ['joint1', 'joint2', 'joint3']}):
        pass  # left by an exception: closed as incomplete
    with pytest.raises(BagError, match='marked incomplete'):
        score_bag(tmp_path / 'bag')


def test_non_bags_are_refused(tmp_path, capsys):
    (tmp_path / 'folder').mkdir()
    (tmp_path / 'garbage').mkdir()
    (tmp_path / 'garbage' / 'metadata.yaml').write_text('not: [a bag')
    assert main(['score', str(tmp_path / 'folder'), str(tmp_path / 'garbage'), str(tmp_path / 'none')]) == 2
    errors = capsys.readouterr().err
    assert 'no metadata.yaml' in errors and 'unreadable bag' in errors and 'no such bag' in errors


def test_output_paths_that_escape_or_overwrite_are_refused(tmp_path):
    (tmp_path / 'existing').mkdir()
    with pytest.raises(BagError, match='exists already'):
        checked_output_path(tmp_path / 'existing')
    with pytest.raises(BagError, match='".." is not allowed'):
        checked_output_path(tmp_path / 'a' / '..' / 'b')
    os.symlink(tmp_path / 'existing', tmp_path / 'link')
    with pytest.raises(BagError, match='symlink'):
        checked_output_path(tmp_path / 'link' / 'bag')
    for name in ('../x', 'a/b', '..', ''):
        with pytest.raises(BagError, match='plain file name'):
            child_path(tmp_path, name)
    assert child_path(tmp_path, 'episode_001') == tmp_path / 'episode_001'


def test_separate_processes_record_a_scorable_bag(tmp_path):
    spec = SPECS['pd_gravity']
    result = run_graph_episode(spec, bag=tmp_path / 'bag', storage='sqlite3')
    assert score_bag(tmp_path / 'bag')['I'] == pytest.approx(result.indices()['I'], rel=1e-12)



EPISODE = {'spec': SPECS['computed_torque'].to_dict(), 'joints': ['joint1', 'joint2', 'joint3']}


# Duplicated or foreign evidence (docs/faults.md 25) -------------------------------------------------------------

def offered_qos(bag, topic):
    with Reader(bag) as reader:
        return next(connection.ext.offered_qos_profiles for connection in reader.connections
                    if connection.topic == topic)


def recorded_at(bag, topic, timestamp):
    """The message the bag recorded on `topic` at `timestamp` (ns)."""
    with Reader(bag) as reader:
        wanted = [connection for connection in reader.connections if connection.topic == topic]
        return next(deserialize(raw, TOPICS[topic]) for _, stamp, raw in reader.messages(connections=wanted)
                    if stamp == timestamp)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_faithful_copy_scores_as_the_original(good_bag, tmp_path, storage):
    # Two publishers on /diagnostics do not matter: the indices do not depend on it.
    publishers = {**{topic: ['/plant'] for topic in SAMPLED_TOPICS}, '/diagnostics': ['/plant', '/aggregator']}
    bag = copy_bag(good_bag, tmp_path / 'copy', storage=storage,
                   qos={'/diagnostics': offered_qos(good_bag, '/diagnostics') * 2},
                   custom={PUBLISHERS_KEY: json.dumps(publishers)})
    assert score_bag(bag) == {**score_bag(good_bag), 'bag': str(bag)}


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('topic, refused', [
    ('/joint_states', r'/joint_states holds more than one message for samples \[5\]'),
    ('/effort_command', r'/effort_command holds more than one message for samples \[5\]'),
    ('/clock', r'/clock holds more than one message at t = \[0\.05\] s'),
])
def test_two_messages_for_one_sample_are_refused(good_bag, tmp_path, storage, topic, refused):
    message = recorded_at(good_bag, topic, 50_000_000)  # sample 5
    if topic != '/clock':  # a second source, with its own idea of sample 5
        message.effort = np.asarray(message.effort) + 1.0
    bag = copy_bag(good_bag, tmp_path / 'twice', storage=storage,
                   extra=[(topic, 50_000_000, TYPESTORE.serialize_cdr(message, TOPICS[topic]))])
    with pytest.raises(BagError, match=refused):
        score_bag(bag)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('topic', SAMPLED_TOPICS)
def test_a_sampled_topic_offered_by_two_publishers_is_refused(good_bag, tmp_path, storage, topic):
    bag = copy_bag(good_bag, tmp_path / 'two', storage=storage, qos={topic: offered_qos(good_bag, topic) * 2})
    with pytest.raises(BagError, match=f'{topic} was recorded from 2 publishers'):
        score_bag(bag)


@pytest.mark.parametrize('topic', SAMPLED_TOPICS)
def test_a_sampled_topic_published_by_two_nodes_is_refused(good_bag, tmp_path, topic):
    publishers = {name: ['/plant'] for name in SAMPLED_TOPICS}
    publishers[topic] = ['/plant', '/impostor/plant']
    bag = copy_bag(good_bag, tmp_path / 'two', custom={PUBLISHERS_KEY: json.dumps(publishers)})
    with pytest.raises(BagError, match=f'{topic} had 2 publishers \\(/plant, /impostor/plant\\)'):
        score_bag(bag)


def test_unreadable_publishers_are_refused(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / 'garbled', custom={PUBLISHERS_KEY: '{"/clock": "/plant"}'})
    with pytest.raises(BagError, match=f'custom_data {PUBLISHERS_KEY} is not a JSON object of node-name lists'):
        score_bag(bag)


def test_a_topic_on_two_connections_is_refused(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / 'copy')
    twice = tmp_path / 'twice'
    with Reader(bag) as reader, Writer(twice, version=9) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE,
                                                   offered_qos_profiles=c.ext.offered_qos_profiles)
                       for c in reader.connections}
        # Another offer on the same topic: rosbag2 records it as a second connection.
        other = writer.add_connection('/joint_states', TOPICS['/joint_states'], typestore=TYPESTORE)
        for connection, timestamp, raw in reader.messages():
            writer.write(connections[connection.id], timestamp, raw)
        timestamp = 20_000_000_000
        writer.write(other, timestamp, TYPESTORE.serialize_cdr(recorded_at(bag, '/joint_states', 50_000_000),
                                                               TOPICS['/joint_states']))
        for key, value in custom_data(bag).items():
            writer.set_custom_data(key, value)
    with pytest.raises(BagError, match='/joint_states is recorded on 2 connections'):
        score_bag(twice)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_the_publishers_heard_are_recorded(tmp_path, storage):
    publishers = {'/joint_states': ['/plant'], '/reference': ['/ddarm_episode_driver'], '/diagnostics': []}
    with EpisodeBagWriter(tmp_path / 'bag', EPISODE, storage) as bag:
        bag.set_publishers({'/clock': ['/someone']})
        bag.set_publishers(publishers)  # replaces
        bag.close(complete=True)
    assert json.loads(custom_data(tmp_path / 'bag')[PUBLISHERS_KEY]) == publishers


@pytest.mark.parametrize('publishers, refused', [
    ({'/joint_state': ['/plant']}, r"publishers for \['/joint_state'\], which are not topics"),
    ({'/joint_states': '/plant'}, 'the publishers of /joint_states must be a list of fully qualified node names'),
    ({'/joint_states': ['plant']}, 'the publishers of /joint_states must be a list of fully qualified node names'),
])
def test_publishers_must_be_named_fully(tmp_path, publishers, refused):
    with EpisodeBagWriter(tmp_path / 'bag', EPISODE) as bag:
        with pytest.raises(BagError, match=refused):
            bag.set_publishers(publishers)


# Write failures: named, never a traceback, never a complete bag -------------------------------------------------

FILE_SIZE_LIMITED = r'''
import json, resource, signal, sys
import numpy as np
from ddarm.recording.bags import TYPESTORE, BagError, EpisodeBagWriter

path, storage, limit, count = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
types = TYPESTORE.types
state = types['sensor_msgs/msg/JointState'](
    header=types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](sec=0, nanosec=0), frame_id=''),
    name=['joint1', 'joint2', 'joint3'], position=np.zeros(3), velocity=np.zeros(3), effort=np.zeros(3))
cdr = TYPESTORE.serialize_cdr(state, 'sensor_msgs/msg/JointState')
# Past the limit a write fails with EFBIG (File too large) instead of the process being killed.
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
stage, bag, report = 'open', None, {}
try:
    bag = EpisodeBagWriter(path, json.loads(sys.argv[5]), storage)
    stage = 'write'
    for n in range(count):
        bag.write('/joint_states', n * 10_000_000, cdr)
    stage = 'close'
    bag.close(complete=True)
    stage = 'none'
except BagError as error:
    report['error'] = str(error)
    if bag is not None:
        try:
            bag.close(complete=True)
        except BagError as again:
            report['close_again'] = str(again)
print(json.dumps({'stage': stage, **report}))
'''


@pytest.mark.parametrize('storage, limit, count, stage, reason', [
    # MCAP buffers a chunk (1 MiB) in memory: a short recording fails when it is flushed, at close.
    ('mcap', 0, 10, 'close', 'File too large'),
    ('mcap', 100_000, 20_000, 'write', 'File too large'),
    # sqlite reports EFBIG as an I/O error without the OS's reason.
    ('sqlite3', 0, 10, 'open', r'disk I/O error \(SQLITE_IOERR_WRITE\)'),
    ('sqlite3', 100_000, 20_000, 'write', r'disk I/O error \(SQLITE_IOERR_WRITE\)'),
])
def test_a_bag_that_outgrows_the_file_size_limit_is_named_and_never_complete(tmp_path, storage, limit, count,
                                                                              stage, reason):
    path = tmp_path / 'bag'
    done = subprocess.run([sys.executable, '-c', FILE_SIZE_LIMITED, str(path), storage, str(limit), str(count),
                           json.dumps(EPISODE)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr  # a BagError, not a traceback
    report = json.loads(done.stdout.splitlines()[-1])
    assert report['stage'] == stage
    assert report['error'].startswith(f'{path}: cannot write the bag: ')
    assert re.search(reason, report['error'])
    if stage != 'open':  # close(complete=True) after the failure does not pretend
        assert report['close_again'] == report['error']
    assert not (path / 'metadata.yaml').exists()
    with pytest.raises(BagError, match='no metadata.yaml'):
        score_bag(path)


class FullDisk:
    """A storage file on a disk with no space left: every write fails as the OS fails it."""

    def __init__(self, file):
        self.file = file

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self.file, name)


def fill_disk(bag: EpisodeBagWriter) -> None:
    bag.writer.storage.bio = FullDisk(bag.writer.storage.bio)  # rosbags' MCAP storage writes through .bio


def test_no_space_left_at_close_is_named_and_the_bag_never_complete(tmp_path):
    bag = EpisodeBagWriter(tmp_path / 'bag', EPISODE)
    fill_disk(bag)
    with pytest.raises(BagError) as failure:
        bag.close(complete=True)
    assert str(failure.value) == f'{tmp_path / "bag"}: cannot write the bag: No space left on device'
    with pytest.raises(BagError, match='No space left on device'):
        bag.write('/clock', 0, b'')
    bag.close(complete=False)  # what a context manager does next: nothing left to do
    with pytest.raises(BagError, match='no metadata.yaml'):
        score_bag(tmp_path / 'bag')


def test_the_error_that_ended_a_recording_stays_the_one_raised(tmp_path):
    with pytest.raises(RuntimeError, match='the plant died') as raised:
        with EpisodeBagWriter(tmp_path / 'bag', EPISODE) as bag:
            fill_disk(bag)
            raise RuntimeError('the plant died')
    assert raised.value.__notes__ == [f'{tmp_path / "bag"}: cannot write the bag: No space left on device']
    assert not (tmp_path / 'bag' / 'metadata.yaml').exists()


def test_a_closed_bag_takes_nothing_more_and_cannot_become_complete(tmp_path):
    bag = EpisodeBagWriter(tmp_path / 'bag', EPISODE, 'sqlite3')
    with pytest.raises(BagError, match=r'/nowhere is not a topic of an episode bag'):
        bag.write('/nowhere', 0, b'')
    bag.close(complete=False)
    bag.close(complete=False)
    with pytest.raises(BagError, match='already closed and marked incomplete; it cannot become complete'):
        bag.close(complete=True)
    with pytest.raises(BagError, match=r'closed \(marked incomplete\); cannot record /clock'):
        bag.write('/clock', 0, b'')
    assert bag_status(tmp_path / 'bag') == 'incomplete'


def test_a_writer_dropped_unclosed_still_leaves_a_bag_marked_incomplete(tmp_path):
    """A signal can land between a writer's opening and the `with` that would close it."""
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3)
    EpisodeBagWriter(tmp_path / 'bag', {'spec': spec.to_dict(), 'joints': ['joint1', 'joint2', 'joint3']})
    assert bag_status(tmp_path / 'bag') == 'incomplete'
    with pytest.raises(BagError, match='marked incomplete'):
        score_bag(tmp_path / 'bag')


# Bags whose configuration or reference cannot be scored: named, never a traceback ------------------------------

SYNTHETIC_JOINTS = ['joint1', 'joint2', 'joint3']
SYNTHETIC_SPEC = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, duration=0.03)


def _stamp(t: float, kind: str = 'builtin_interfaces/msg/Time'):
    nanoseconds = round(t * 1e9)
    return TYPESTORE.types[kind](sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


def _joint_state(t: float, position=(), velocity=(), effort=()):
    types = TYPESTORE.types
    return types['sensor_msgs/msg/JointState'](
        header=types['std_msgs/msg/Header'](stamp=_stamp(t), frame_id=''), name=list(SYNTHETIC_JOINTS),
        position=np.array(position, dtype=float), velocity=np.array(velocity, dtype=float),
        effort=np.array(effort, dtype=float))


def synthetic_bag(path, episode=None, change_reference=None, change_state=None):
    """A complete bag of a four-sample episode written with EpisodeBagWriter, from made-up numbers.

    `episode` replaces the /ddarm/episode record; `change_reference(times, fields)` and
    `change_state(n, (position, velocity, effort))` may alter what is written."""
    types = TYPESTORE.types
    period, k_max = SYNTHETIC_SPEC.period, 3
    times = [j * period for j in range(k_max + 1)]
    fields = {'positions': np.linspace(0.0, 0.3, 12).reshape(4, 3), 'velocities': np.full((4, 3), 0.5),
              'accelerations': np.zeros((4, 3)), 'effort': np.array([[1.0, 20.0, 5.0]] * 4)}
    if change_reference is not None:
        change_reference(times, fields)
    record = episode if episode is not None else {'spec': SYNTHETIC_SPEC.to_dict(), 'joints': SYNTHETIC_JOINTS,
                                                  'k_max': k_max, 'torque_limit': None}
    with EpisodeBagWriter(path, record) as bag:
        points = [types['trajectory_msgs/msg/JointTrajectoryPoint'](
            **{name: values[j] for name, values in fields.items()},
            time_from_start=_stamp(t, 'builtin_interfaces/msg/Duration')) for j, t in enumerate(times)]
        bag.write_message('/reference', 0, types['trajectory_msgs/msg/JointTrajectory'](
            header=types['std_msgs/msg/Header'](stamp=_stamp(0.0), frame_id=''), joint_names=SYNTHETIC_JOINTS,
            points=points))
        for n in range(k_max + 2):
            t = n * period
            state = (fields['positions'][min(n, k_max)] - 0.01, fields['velocities'][min(n, k_max)],
                     () if n == 0 else [1.5, 19.0, 5.5])
            if change_state is not None:
                t, state = change_state(n, t, state)
            bag.write_message('/joint_states', round(t * 1e9), _joint_state(t, *state))
            if n <= k_max:
                bag.write_message('/effort_command', round(t * 1e9), _joint_state(t, effort=[1.5, 19.0, 5.5]))
        bag.close(complete=True)
    return path


def test_a_synthetic_bag_scores(tmp_path):
    scored = score_bag(synthetic_bag(tmp_path / 'bag'))
    # |e| = 0.01 rad on every joint at each of the 4 samples, over k_max = 3; the torques 0.5 N m off the nominal.
    assert scored['I1'] == pytest.approx(4 * 3 * np.degrees(0.01) / 3)
    assert scored['I2'] == pytest.approx(4 * (0.5 * 10 / 1.0 + 1.0 * 10 / 20.0 + 0.5 * 10 / 5.0) / 3)
    assert scored['samples_scored'] == 4 and not scored['diverged']


def _spec_with(**changes):
    return {'spec': {**SYNTHETIC_SPEC.to_dict(), **changes}, 'joints': SYNTHETIC_JOINTS, 'k_max': 3,
            'torque_limit': None}


@pytest.mark.parametrize('episode, refused', [
    (_spec_with(gain_schedule=True), r"holds a spec that cannot be run: .*unexpected keyword argument 'gain_schedule'"),
    (_spec_with(kp='stiff'), r"holds the spec kp 'stiff', not a tuple\[float, \.\.\.\]"),
    (_spec_with(kp=225.0), r'holds the spec kp 225.0, not a tuple\[float, \.\.\.\]'),
    (_spec_with(kp=['225', '225', '225']), r"holds the spec kp \['225', '225', '225'\], not a tuple"),
    (_spec_with(kv=[True, 30.0, 30.0]), r'holds the spec kv \[True, 30.0, 30.0\], not a tuple'),
    (_spec_with(tau=True), "holds the spec tau True, not a <class 'float'>"),
    (_spec_with(trajectory=1.0), "holds the spec trajectory 1.0, not a <class 'int'>"),
    (_spec_with(urdf=5), r'holds the spec urdf 5, not a str \| None'),
    (_spec_with(torque_limit=[1, 'a', 2]), r"holds the spec torque_limit \[1, 'a', 2\], not a str \| tuple"),
    (_spec_with(controller='lqr'), 'holds a spec that cannot be run: controller must be one of'),
    (_spec_with(torque_limit='maximum'), "holds a spec that cannot be run: torque_limit must be 'none', 'paper'"),
    (_spec_with(tau=5.0), 'holds a spec that cannot be run: .*tau'),
    ({**_spec_with(), 'torque_limit': [1.0, 2.0]}, 'torque_limit needs 3 values'),
    ({**_spec_with(), 'torque_limit': [1.0, -2.0, 3.0]}, 'torque_limit must be finite and positive'),
])
def test_a_configuration_that_is_not_a_spec_is_refused_naming_the_bag(tmp_path, episode, refused):
    bag = synthetic_bag(tmp_path / 'bag', episode=episode)
    with pytest.raises(BagError, match=f'^{re.escape(str(bag))}: .*{refused}'):
        score_bag(bag)


def _nan_nominal(times, fields):
    fields['effort'][1, 2] = np.nan


def _infinite_position(times, fields):
    fields['positions'][2, 0] = np.inf


def _off_the_samples(times, fields):
    times[2] = 0.025


def _no_torque_on_joint_2(times, fields):
    fields['effort'][:, 1] = 0.0


def _short_point(times, fields):
    fields['velocities'] = [row[:2] for row in fields['velocities']]


@pytest.mark.parametrize('change, refused', [
    (_nan_nominal, r'/reference: reference point 1: effort is not finite at index \[2\]'),
    (_infinite_position, r'/reference: reference point 2: positions is not finite at index \[0\]'),
    (_off_the_samples, r'/reference: reference: point 2 is at 0.025 s, not at sample time 0.02 s'),
    (_short_point, r'/reference: reference point 0: velocities has 2 values for 3 joints'),
    (_no_torque_on_joint_2, 'every joint needs a nonzero finite nominal torque'),  # an IndicesError
])
def test_a_reference_the_indices_cannot_use_is_refused_naming_the_bag(tmp_path, change, refused):
    bag = synthetic_bag(tmp_path / 'bag', change_reference=change)
    with pytest.raises(BagError, match=f'^{re.escape(str(bag))}: {refused}'):
        score_bag(bag)


def _nan_velocity(n, t, state):
    return t, (state[0], [0.0, np.nan, 0.0], state[2]) if n == 2 else state


def _between_samples(n, t, state):
    return (t + 0.004 if n == 2 else t), state


def _no_effort(n, t, state):
    return t, (state[0], state[1], ()) if n == 3 else state


def _diverged_without_effort(n, t, state):
    return t, ((), (), ()) if n == 3 else state


@pytest.mark.parametrize('change, refused', [
    (_nan_velocity, r'/joint_states sample 2: velocity is not finite at index \[1\]'),
    (_between_samples, '/joint_states: stamp 0.024000000 s is not a sample instant'),
    (_no_effort, r'the torques applied over samples \[2\] \(each the effort of the next state\) are missing: '
                 'the episode is incomplete'),
    (_diverged_without_effort, r'the torques applied over samples \[2\] \(each the effort of the next state\) '
                               'are missing'),
])
def test_recorded_states_the_scorer_cannot_use_are_refused_naming_the_bag(tmp_path, change, refused):
    bag = synthetic_bag(tmp_path / 'bag', change_state=change)
    with pytest.raises(BagError, match=f'^{re.escape(str(bag))}: {refused}'):
        score_bag(bag)


def test_a_divergence_is_scored_on_the_samples_before_it(tmp_path):
    def diverge(n, t, state):
        return t, ((), (), state[2]) if n == 3 else state  # the plant left its bounds during sample 2

    scored = score_bag(synthetic_bag(tmp_path / 'bag', change_state=diverge))
    assert scored['diverged'] and scored['diverged_at'] == 3 and scored['samples_scored'] == 3
    assert scored['I1'] == pytest.approx(3 * 3 * np.degrees(0.01) / 3)


def test_ddarm_score_names_each_bad_bag_and_scores_the_others(tmp_path, capsys):
    bad_spec = synthetic_bag(tmp_path / 'bad_spec', episode=_spec_with(gain_schedule=True))
    good = synthetic_bag(tmp_path / 'good')
    bad_reference = synthetic_bag(tmp_path / 'bad_reference', change_reference=_nan_nominal)
    bad_stamp = synthetic_bag(tmp_path / 'bad_stamp', change_state=_between_samples)
    assert main(['score', str(bad_spec), str(good), str(bad_reference), f'{bad_stamp}/', '--json']) == 2
    captured = capsys.readouterr()
    assert [json.loads(line)['bag'] for line in captured.out.splitlines()] == [str(good)]
    errors = captured.err.splitlines()
    assert len(errors) == 3 and 'Traceback' not in captured.err
    assert errors[0].startswith(f'ddarm score: {bad_spec}: /ddarm/episode holds a spec that cannot be run')
    assert errors[1].startswith(f'ddarm score: {bad_reference}: /reference: reference point 1: effort is not finite')
    assert errors[2].startswith(f'ddarm score: {bad_stamp}: /joint_states: stamp')


def _beyond(field: int, value: float):
    def change(n, t, state):
        if n != 2:
            return t, state
        changed = [list(part) for part in state]
        changed[field][1] = value
        return t, tuple(changed)
    return change


@pytest.mark.parametrize('field, value', [(0, 150.0), (0, -1e300), (1, 2000.0), (1, -1000.5)])
def test_a_state_beyond_the_plants_bounds_is_scored_as_a_divergence_there(tmp_path, field, value):
    scored = score_bag(synthetic_bag(tmp_path / 'bag', change_state=_beyond(field, value)))
    assert scored['diverged'] and scored['diverged_at'] == 2 and scored['samples_scored'] == 2
    assert scored['I1'] == pytest.approx(2 * 3 * np.degrees(0.01) / 3)


def test_a_state_on_the_plants_bounds_is_not_a_divergence(tmp_path):
    scored = score_bag(synthetic_bag(tmp_path / 'bag', change_state=_beyond(1, -1000.0)))
    assert not scored['diverged'] and scored['samples_scored'] == 4


def test_an_initial_state_beyond_the_plants_bounds_is_refused(tmp_path):
    def change(n, t, state):
        return t, ([0.0, 0.0, 101.0], *state[1:]) if n == 0 else state
    bag = synthetic_bag(tmp_path / 'bag', change_state=change)
    with pytest.raises(BagError, match=f"^{re.escape(str(bag))}: the state of sample 0 is beyond the plant's bounds"):
        score_bag(bag)


@pytest.mark.parametrize('topic', ['/joint_states', '/effort_command'])
def test_messages_whose_header_stamps_run_backwards_are_refused(good_bag, tmp_path, capsys, topic):
    period = SPECS['computed_torque'].period

    def swap_5_and_6(recorded, message):
        if recorded == topic:
            sample = round((message.header.stamp.sec + message.header.stamp.nanosec * 1e-9) / period)
            if sample in (5, 6):
                message.header.stamp = _stamp((11 - sample) * period)
        return message

    bag = copy_bag(good_bag, tmp_path / 'bag', transform=swap_5_and_6)
    assert main(['score', str(bag)]) == 2
    assert capsys.readouterr().err == (f'ddarm score: {bag}: {topic} message 6 is stamped for sample 5, after '
                                       'message 5 for sample 6: the header stamps must increase in the order '
                                       'recorded\n')


@pytest.mark.parametrize('prismatic', [5, [True], 'yes', [1, 0, 0], [None, False, False], {'joint1': True}])
def test_a_prismatic_field_that_is_not_one_flag_per_joint_is_refused_naming_it(tmp_path, capsys, prismatic):
    bag = synthetic_bag(tmp_path / 'bag', episode={**_spec_with(), 'prismatic': prismatic})
    assert main(['score', str(bag)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'ddarm score: {bag}: /ddarm/episode holds prismatic ') and 'Traceback' not in err
    assert 'not one true or false per joint (3)' in err


def test_a_prismatic_field_of_one_flag_per_joint_is_taken(tmp_path):
    scored = score_bag(synthetic_bag(tmp_path / 'bag', episode={**_spec_with(), 'prismatic': [True, False, False]}))
    assert scored['max_abs_error_deg'][0] is None and scored['max_abs_error_deg'][1] == pytest.approx(np.degrees(0.01))


def test_a_second_episode_configuration_is_refused(good_bag, tmp_path, capsys):
    with Reader(good_bag) as reader:
        (connection,) = [c for c in reader.connections if c.topic == '/ddarm/episode']
        ((_, timestamp, raw),) = list(reader.messages(connections=[connection]))
    bag = copy_bag(good_bag, tmp_path / 'bag', extra=[('/ddarm/episode', timestamp + 1, raw)])
    assert main(['score', str(bag)]) == 2
    assert capsys.readouterr().err == (f'ddarm score: {bag}: /ddarm/episode holds 2 configurations, not one: which '
                                       'one the episode ran is unknown\n')
