"""Motion files from bags: /joint_states and a JointTrajectory written to a bag with rosbags, converted, loaded back
to the same motion bit for bit; every refusal names the bag and the topic; `ddarm motion` writes a new file only."""

import argparse
import sqlite3

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ddarm.cli.motion import add_motion_parser, command_motion
from ddarm.motion.files import load_motion
from ddarm.motion.from_bag import motion_file_from_bag
from ddarm.motion.programmed import MotionError
from ddarm.motion.waypoints import WaypointMotion

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
JOINT_STATE = 'sensor_msgs/msg/JointState'
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
Header = TYPESTORE.types['std_msgs/msg/Header']
Time = TYPESTORE.types['builtin_interfaces/msg/Time']
Duration = TYPESTORE.types['builtin_interfaces/msg/Duration']
JointState = TYPESTORE.types[JOINT_STATE]
JointTrajectory = TYPESTORE.types[JOINT_TRAJECTORY]
Point = TYPESTORE.types['trajectory_msgs/msg/JointTrajectoryPoint']
String = TYPESTORE.types['std_msgs/msg/String']
EMPTY = np.array([], dtype=float)


def bits(values) -> bytes:
    return np.asarray(values, dtype=float).tobytes()


def write_bag(path, topics: dict, storage='mcap'):
    """topics: name -> (msgtype, [message, ...]); each message recorded at 1 ms after the previous."""
    with Writer(path, version=9, storage_plugin=STORAGES[storage]) as writer:
        for topic, (msgtype, messages) in topics.items():
            connection = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            for k, message in enumerate(messages):
                writer.write(connection, 1_000_000 * (k + 1), TYPESTORE.serialize_cdr(message, msgtype))
    return path


def joint_state(stamp_ns, names, position, velocity=EMPTY):
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return JointState(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=''), name=list(names),
                      position=np.array(position, dtype=float), velocity=np.array(velocity, dtype=float), effort=EMPTY)


# 1 kHz-ish samples from 1700000000.25 s on, with uneven spacing; the names change order halfway.
STAMPS = [1_700_000_000_250_000_000 + dt for dt in (0, 10_000_000, 20_000_001, 30_000_000, 45_500_000, 50_000_000)]
RNG = np.random.default_rng(4)
Q = RNG.normal(size=(6, 3))
V = RNG.normal(size=(6, 3))


def states(velocities=True):
    messages = []
    for k, stamp in enumerate(STAMPS):
        order = [0, 1, 2] if k < 3 else [2, 0, 1]
        names = [['j1', 'j2', 'j3'][i] for i in order]
        messages.append(joint_state(stamp, names, Q[k, order], V[k, order] if velocities else EMPTY))
    return messages


def trajectory(first_time=(0, 0), effort=False, last_velocity=0.0):
    points = [
        Point(positions=np.array([0.0, 1.0]), velocities=EMPTY, accelerations=EMPTY, effort=EMPTY,
              time_from_start=Duration(sec=first_time[0], nanosec=first_time[1])),
        Point(positions=np.array([0.5, 0.7]), velocities=np.array([1.0, -0.3]), accelerations=EMPTY,
              effort=np.array([2.0, 1.0]) if effort else EMPTY, time_from_start=Duration(sec=0, nanosec=400_000_000)),
        Point(positions=np.array([0.9, 0.1]), velocities=np.array([0.2, -0.1]), accelerations=np.array([1.5, 0.5]),
              effort=EMPTY, time_from_start=Duration(sec=1, nanosec=1)),
        Point(positions=np.array([1.0, 0.0]), velocities=np.array([0.0, last_velocity]), accelerations=np.zeros(2),
              effort=EMPTY, time_from_start=Duration(sec=2, nanosec=0)),
    ]
    return JointTrajectory(header=Header(stamp=Time(sec=0, nanosec=0), frame_id=''), joint_names=['shoulder', 'elbow'],
                           points=points)


def converted(tmp_path, bag, name='motion.yaml', **options):
    text = motion_file_from_bag(bag, **options)
    path = tmp_path / name
    path.write_text(text)
    return text, load_motion(path)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_joint_states_become_one_point_per_message_read_back_bit_for_bit(tmp_path, storage):
    bag = write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, states())}, storage)
    text, loaded = converted(tmp_path, bag)
    motion = loaded.motion
    assert isinstance(motion, WaypointMotion) and loaded.joint_names == ('j1', 'j2', 'j3') and loaded.locked == ()
    assert text.startswith(f"# Motion from the bag {str(bag)!r}, topic '/joint_states' ({JOINT_STATE})")
    assert motion.start is None
    assert bits(motion.positions) == bits(Q)  # put back in the first message's order by name
    assert bits(np.array(motion.velocities[:-1])) == bits(V[:-1])
    assert motion.velocities[-1].tolist() == [0.0, 0.0, 0.0] and 'velocities are written as zero' in text
    assert bits(motion.times) == bits([(stamp - STAMPS[0]) / 1e9 for stamp in STAMPS])
    assert motion.accelerations == (None,) * len(STAMPS)


def test_positions_only_when_some_message_lacks_velocities(tmp_path):
    messages = states()
    messages[2] = joint_state(STAMPS[2], ['j1', 'j2', 'j3'], Q[2])
    text, loaded = converted(tmp_path, write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, messages)}))
    assert loaded.motion.velocities == (None,) * len(STAMPS) and 'velocities' not in text.split('joint_names')[1]
    assert 'Positions only' in text
    assert bits(loaded.motion.positions) == bits(Q)


def test_the_joints_are_chosen_by_name_in_the_order_asked_within_the_window(tmp_path):
    bag = write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, states())})
    # messages 1 to 4 lie within [0.005, 0.0455] s of the first
    text, loaded = converted(tmp_path, bag, joints=['j3', 'j1'], start=0.005, end=0.0455)
    assert loaded.joint_names == ('j3', 'j1')
    assert bits(loaded.motion.positions) == bits(Q[1:5][:, [2, 0]])
    assert bits(loaded.motion.times) == bits([(stamp - STAMPS[1]) / 1e9 for stamp in STAMPS[1:5]])
    assert 'messages 1 to 4 of 6' in text
    assert bits(np.array(loaded.motion.velocities[:-1])) == bits(V[1:4][:, [2, 0]])


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_joint_trajectory_is_its_first_message_as_it_is(tmp_path, storage):
    later = trajectory()
    later.joint_names = ['other', 'names']
    bag = write_bag(tmp_path / 'bag', {'/arm/joint_trajectory': (JOINT_TRAJECTORY, [trajectory(effort=True), later])},
                    storage)
    text, loaded = converted(tmp_path, bag)
    message = trajectory()
    assert loaded.joint_names == ('shoulder', 'elbow')
    assert text.startswith(f"# Motion from the bag {str(bag)!r}, topic '/arm/joint_trajectory' ({JOINT_TRAJECTORY})")
    assert 'of its first message (of 2)' in text and "effort is left out" in text
    assert 'time_from_start: {sec: 1, nanosec: 1}' in text
    expected = WaypointMotion(
        [p.time_from_start.sec + p.time_from_start.nanosec / 1e9 for p in message.points],
        [p.positions for p in message.points],
        tuple(p.velocities if len(p.velocities) else None for p in message.points),
        tuple(p.accelerations if len(p.accelerations) else None for p in message.points))
    motion = loaded.motion
    assert bits(motion.times) == bits(expected.times) and bits(motion.positions) == bits(expected.positions)
    assert motion.velocities[0] is None and motion.accelerations[:2] == (None, None)
    times = np.linspace(-0.5, 2.5, 301)
    for got, want in zip(motion.sample(times), expected.sample(times)):
        assert bits(got) == bits(want)


def test_joint_states_is_the_default_and_else_the_only_joint_trajectory(tmp_path):
    both = write_bag(tmp_path / 'both', {'/joint_states': (JOINT_STATE, states()),
                                         '/reference': (JOINT_TRAJECTORY, [trajectory()])})
    assert "topic '/joint_states'" in motion_file_from_bag(both).splitlines()[0]
    assert "topic '/reference'" in motion_file_from_bag(both, topic='/reference').splitlines()[0]
    one = write_bag(tmp_path / 'one', {'/reference': (JOINT_TRAJECTORY, [trajectory()]),
                                       '/chatter': ('std_msgs/msg/String', [String(data='hi')])})
    assert "topic '/reference'" in motion_file_from_bag(one).splitlines()[0]


def test_joint_names_that_yaml_would_read_as_something_else_are_quoted(tmp_path):
    names = ['true', '1e5', 'a b', 'null', 'x"y\\z', 'é\x7f']
    messages = [joint_state(stamp, names, [0.1 * k] * len(names)) for k, stamp in enumerate(STAMPS[:3])]
    _, loaded = converted(tmp_path, write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, messages)}))
    assert loaded.joint_names == tuple(names)


def test_a_trajectory_recorded_with_velocities_left_at_the_end_is_refused_naming_the_point(tmp_path):
    bag = write_bag(tmp_path / 'bag', {'/reference': (JOINT_TRAJECTORY, [trajectory(last_velocity=0.5)])})
    with pytest.raises(MotionError, match=r": /reference: points\[3\] \(the last\) has velocities \[0.0, 0.5\]"):
        motion_file_from_bag(bag)


def refusal(bag, **options) -> str:
    with pytest.raises(MotionError) as refused:
        motion_file_from_bag(bag, **options)
    return str(refused.value)


def test_a_folder_that_is_no_bag_is_refused_naming_it(tmp_path):
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'file').write_text('not a bag')
    for path in (tmp_path / 'empty', tmp_path / 'file', tmp_path / 'absent'):
        assert refusal(path).startswith(f'{path}: no metadata.yaml in it')


def test_a_damaged_bag_is_refused_as_unreadable(tmp_path):
    bag = write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, states())}, 'sqlite3')
    database = next(bag.glob('*.db3'))
    with sqlite3.connect(database) as connection:
        connection.execute('DROP TABLE messages')
    assert refusal(bag).startswith(f'{bag}: unreadable bag (')


@pytest.mark.parametrize('build, options, refused', [
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(topic='/reference'),
     "no topic /reference (the bag has /joint_states (sensor_msgs/msg/JointState))"),
    (lambda: {'/chatter': ('std_msgs/msg/String', [String(data='hi')])}, dict(topic='/chatter'),
     '/chatter carries std_msgs/msg/String'),
    (lambda: {'/joint_states': ('std_msgs/msg/String', [String(data='hi')])}, {},
     '/joint_states carries std_msgs/msg/String'),
    (lambda: {'/chatter': ('std_msgs/msg/String', [String(data='hi')])}, {},
     'no /joint_states and no JointTrajectory topic: choose a topic (the bag has /chatter (std_msgs/msg/String))'),
    (lambda: {'/a': (JOINT_TRAJECTORY, [trajectory()]), '/b': (JOINT_TRAJECTORY, [trajectory()])}, {},
     'no /joint_states and 2 JointTrajectory topics: choose a topic (the bag has '
     '/a (trajectory_msgs/msg/JointTrajectory), /b (trajectory_msgs/msg/JointTrajectory))'),
    (lambda: {'/joint_states': (JOINT_STATE, [])}, {}, '/joint_states: no messages'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [])}, {}, '/reference: no messages'),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(joints=['j1', 'j4']),
     "/joint_states: message 0 has no joint 'j4' (it has ['j1', 'j2', 'j3'])"),
    (lambda: {'/joint_states': (JOINT_STATE, states()[:3] + [joint_state(STAMPS[3], ['j1', 'j2'], [0.0, 0.0])])}, {},
     "/joint_states: message 3 has no joint 'j3'"),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(joints=['j1', 'j1']), 'asked for more than once'),
    (lambda: {'/joint_states': (JOINT_STATE, [joint_state(s, ['a', 'a'], [0.0, 0.0]) for s in STAMPS])}, {},
     'message 0 names a joint more than once'),
    (lambda: {'/joint_states': (JOINT_STATE, [joint_state(s, [], []) for s in STAMPS])}, {}, 'no joints to take'),
    (lambda: {'/joint_states': (JOINT_STATE, states()[:2] + [joint_state(STAMPS[2], ['j1'], [0.0, 1.0])])}, {},
     'message 2 has 2 positions for 1 joints'),
    (lambda: {'/joint_states': (JOINT_STATE, states()[:2] + [joint_state(STAMPS[2], ['j1'], [0.0], [1.0, 2.0])])},
     dict(joints=['j1']), 'message 2 has 2 velocities for 1 joints'),
    (lambda: {'/joint_states': (JOINT_STATE, states()[:2] + [joint_state(STAMPS[1], ['j1', 'j2', 'j3'], Q[2])])}, {},
     '/joint_states: message 2 is stamped 1700000000.26 s, not after message 1 (1700000000.26 s): the header stamps '
     'must increase'),
    (lambda: {'/joint_states': (JOINT_STATE, [joint_state(0, ['j1'], [float(k)]) for k in range(3)])}, {},
     'message 1 is stamped 0.0 s, not after message 0'),
    (lambda: {'/joint_states': (JOINT_STATE, states()[:2] + [joint_state(STAMPS[2], ['j1', 'j2', 'j3'],
                                                                          [0.0, np.nan, 0.0])])}, {},
     "/joint_states: message 2 position of joint 'j2' is nan: a motion needs finite values"),
    (lambda: {'/joint_states': (JOINT_STATE, states()[:2] + [joint_state(STAMPS[2], ['j1', 'j2', 'j3'], Q[2],
                                                                          [0.0, 0.0, -np.inf])])}, {},
     "message 2 velocity of joint 'j3' is -inf"),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(start=0.046, end=0.049),
     '0 of its 6 messages (t = 0.0 to 0.05 s) within the window [0.046, 0.049] s: a motion needs two'),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(end=0.005),
     '1 of its 6 messages (t = 0.0 to 0.05 s) within the window [0.0, 0.005] s: a motion needs two'),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(start=0.04, end=0.01),
     'the window start 0.04 s is after'),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(start=float('nan')),
     'the window start must be a finite number of seconds >= 0 after the topic\'s first message, got nan'),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(start=-0.5),
     'the window start must be a finite number of seconds >= 0 after the topic\'s first message, got -0.5'),
    (lambda: {'/joint_states': (JOINT_STATE, states())}, dict(end=-0.0001), 'the window end must be a finite'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [trajectory()])}, dict(joints=['shoulder']),
     '/reference: a JointTrajectory is taken whole'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [trajectory()])}, dict(end=1.0), 'a JointTrajectory is taken whole'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [trajectory(first_time=(0, 500_000_000))])}, {},
     '/reference: points[0] is at 0.5 s, not 0'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [JointTrajectory(
        header=Header(stamp=Time(sec=0, nanosec=0), frame_id=''), joint_names=['a'], points=[])])}, {},
     '/reference: its first message has no points'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [JointTrajectory(
        header=Header(stamp=Time(sec=0, nanosec=0), frame_id=''), joint_names=['a'],
        points=[Point(positions=EMPTY, velocities=np.array([1.0]), accelerations=EMPTY, effort=EMPTY,
                      time_from_start=Duration(sec=0, nanosec=0))])])}, {}, '/reference: points[0] has no positions'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [JointTrajectory(
        header=Header(stamp=Time(sec=0, nanosec=0), frame_id=''), joint_names=['a'],
        points=[Point(positions=np.array([0.0]), velocities=EMPTY, accelerations=EMPTY, effort=EMPTY,
                      time_from_start=Duration(sec=0, nanosec=0)),
                Point(positions=np.array([np.inf]), velocities=EMPTY, accelerations=EMPTY, effort=EMPTY,
                      time_from_start=Duration(sec=1, nanosec=0))])])}, {},
     '/reference: points[1].positions[0] is inf'),
    (lambda: {'/reference': (JOINT_TRAJECTORY, [JointTrajectory(
        header=Header(stamp=Time(sec=0, nanosec=0), frame_id=''), joint_names=['a', 'b'],
        points=[Point(positions=np.array([0.0, 0.0]), velocities=np.array([1.0]), accelerations=EMPTY, effort=EMPTY,
                      time_from_start=Duration(sec=0, nanosec=0)),
                Point(positions=np.array([1.0, 1.0]), velocities=EMPTY, accelerations=EMPTY, effort=EMPTY,
                      time_from_start=Duration(sec=1, nanosec=0))])])}, {},
     '/reference: points[0].velocities must list one number per joint of joint_names (2)'),
])
def test_every_refusal_names_the_bag_and_the_topic(tmp_path, build, options, refused):
    bag = write_bag(tmp_path / 'bag', build())
    message = refusal(bag, **options)
    assert message.startswith(f'{bag}: ') and refused in message, message


def parsed(argv):
    parser = argparse.ArgumentParser(prog='ddarm')
    add_motion_parser(parser.add_subparsers(dest='command', required=True))
    return parser.parse_args(argv)


def test_ddarm_motion_writes_the_file_and_says_what_it_holds(tmp_path, capsys):
    bag = write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, states())})
    out = tmp_path / 'recorded.yaml'
    args = parsed(['motion', str(bag), '--joints', 'j2', 'j3', '--start', '0.01', '--out', str(out)])
    assert args.handler is command_motion and command_motion(args) == 0
    assert out.read_text() == motion_file_from_bag(bag, joints=['j2', 'j3'], start=0.01)
    assert capsys.readouterr().out == f"{out}: 5 points of 2 joints (j2, j3), 0.04 s\n"
    assert load_motion(out).joint_names == ('j2', 'j3')


def test_ddarm_motion_never_overwrites_and_needs_the_folder(tmp_path):
    bag = write_bag(tmp_path / 'bag', {'/joint_states': (JOINT_STATE, states())})
    existing = tmp_path / 'existing.yaml'
    existing.write_text('mine')
    with pytest.raises(MotionError, match='exists already, not overwriting'):
        command_motion(parsed(['motion', str(bag), '--out', str(existing)]))
    assert existing.read_text() == 'mine'
    with pytest.raises(MotionError, match='no folder'):
        command_motion(parsed(['motion', str(bag), '--out', str(tmp_path / 'absent' / 'motion.yaml')]))
    refused = tmp_path / 'refused.yaml'
    with pytest.raises(MotionError, match='no topic /nothing'):
        command_motion(parsed(['motion', str(bag), '--topic', '/nothing', '--out', str(refused)]))
    assert not refused.exists()


def test_ddarm_motion_needs_out_and_finite_times(tmp_path, capsys):
    for argv in (['motion', 'bag'], ['motion', 'bag', '--out', 'x.yaml', '--start', 'nan']):
        with pytest.raises(SystemExit):
            parsed(argv)
    assert 'required: --out' in capsys.readouterr().err


def test_ddarm_motion_refuses_in_one_line_once_it_is_a_command(tmp_path, capsys):
    from ddarm.cli.main import build_parser, main

    commands = next(action for action in build_parser()._actions if isinstance(action, argparse._SubParsersAction))
    if 'motion' not in commands.choices:
        pytest.skip('ddarm motion is not wired into ddarm.cli.main yet')
    assert main(['motion', str(tmp_path / 'absent'), '--out', str(tmp_path / 'm.yaml')]) == 2
    assert capsys.readouterr().err == f'ddarm motion: {tmp_path / "absent"}: no metadata.yaml in it: not a rosbag2 ' \
                                      'bag, or a recording that never closed\n'
