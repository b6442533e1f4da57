"""Motion files: the paper's two motions read back bit for bit, and every bad file is refused naming the file
and the field."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ddarm.motion.files import load_motion
from ddarm.motion.programmed import PAPER_TRAJECTORIES, MotionError, paper_motion_joints, paper_trajectory
from ddarm.physics.arm import Arm

DATA = Path(__file__).resolve().parent.parent / 'ddarm' / 'paper' / 'data'
# spec §4, as the code wrote them before they were files.
ENDPOINTS = {1: ((0.0, np.pi / 3, -2 * np.pi / 3), (np.pi / 2, 0.0, 0.0)),
             2: ((np.pi / 2, 0.0, 0.0), (np.pi, np.pi / 2, -np.pi))}
GOOD = """joint_names: [a, b]
duration: 2.0
profile: bang_bang
start: [0.0, 1.0]
goal: [1.0, -1.0]
"""


def bits(values) -> bytes:
    return np.asarray(values, dtype=float).tobytes()


def test_the_paper_numbers_its_motions_by_their_files():
    assert PAPER_TRAJECTORIES == (1, 2)
    assert sorted(path.name for path in DATA.glob('trajectory-*.yaml')) == ['trajectory-1.yaml', 'trajectory-2.yaml']


@pytest.mark.parametrize('number', [1, 2])
def test_the_paper_motion_files_hold_the_endpoints_bit_for_bit_and_the_urdf_joints(number):
    loaded = load_motion(DATA / f'trajectory-{number}.yaml')
    start, goal = ENDPOINTS[number]
    assert bits(loaded.motion.q0) == bits(start) and bits(loaded.motion.qf) == bits(goal)
    assert loaded.motion.duration == 1.0
    assert list(loaded.joint_names) == Arm.from_urdf().joint_names == ['joint1', 'joint2', 'joint3']


@pytest.mark.parametrize('number', [1, 2])
@pytest.mark.parametrize('duration', [0.5, 1.0, 1.7])
def test_paper_trajectory_is_the_file_with_the_duration_replaced(number, duration):
    motion = paper_trajectory(number, duration)
    start, goal = ENDPOINTS[number]
    assert bits(motion.q0) == bits(start) and bits(motion.qf) == bits(goal)
    assert motion.duration == duration
    motion.q0[0] = 99.0  # a caller's copy: the next call is the file's motion again
    assert bits(paper_trajectory(number, duration).q0) == bits(start)


def test_an_unknown_paper_trajectory_is_refused():
    with pytest.raises(MotionError, match=r'trajectory must be one of \[1, 2\], got 3'):
        paper_trajectory(3, 1.0)
    with pytest.raises(MotionError, match=r'trajectory must be one of \[1, 2\], got 0'):
        paper_motion_joints(0)


@pytest.mark.parametrize('number', [1, 2])
def test_a_paper_motion_names_the_joints_of_its_file(number):
    assert paper_motion_joints(number) == load_motion(DATA / f'trajectory-{number}.yaml').joint_names
    assert paper_motion_joints(number) == ('joint1', 'joint2', 'joint3')


def test_only_files_named_trajectory_and_a_number_are_paper_motions():
    """A stray file beside the paper's motions is ignored, never a crash of every command at import."""
    code = '''
import pathlib
real = pathlib.Path.glob
def glob(self, pattern):
    found = list(real(self, pattern))
    if pattern == 'trajectory-*.yaml':
        found += [self / name for name in ('trajectory-x.yaml', 'trajectory-01.yaml', 'trajectory-.yaml',
                                           'trajectory-2b.yaml', 'trajectory-0.yaml', 'trajectory- 3.yaml')]
    return found
pathlib.Path.glob = glob
from ddarm.motion.programmed import PAPER_TRAJECTORIES
print(PAPER_TRAJECTORIES)
'''
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parent.parent)
    assert done.returncode == 0 and done.stdout.strip() == '(1, 2)', done.stderr


def test_any_double_written_with_repr_reads_back_bit_for_bit(tmp_path):
    values = np.random.default_rng(0).normal(scale=[1e-300, 1e-8, 1.0, 1e8, 1e300], size=(40, 5)).ravel()
    values = np.concatenate([values, [0.0, -0.0, 5e-324, np.nextafter(1.0, 2.0), np.pi]])
    for chunk in np.array_split(values, 4):  # a motion drives at most MAX_JOINTS joints
        names = [f'j{i}' for i in range(len(chunk))]
        path = tmp_path / 'motion.yaml'
        path.write_text(f'joint_names: [{", ".join(names)}]\nduration: 0.1\nprofile: bang_bang\n'
                        f'start: [{", ".join(repr(float(v)) for v in chunk)}]\n'
                        f'goal: [{", ".join(repr(float(v)) for v in chunk[::-1])}]\n')
        loaded = load_motion(path)
        assert loaded.joint_names == tuple(names)
        assert bits(loaded.motion.q0) == bits(chunk) and bits(loaded.motion.qf) == bits(chunk[::-1])


def test_a_good_file_loads(tmp_path):
    path = tmp_path / 'good.yaml'
    path.write_text(GOOD)
    loaded = load_motion(path)
    assert loaded.joint_names == ('a', 'b') and loaded.motion.duration == 2.0
    assert loaded.motion.q0.tolist() == [0.0, 1.0] and loaded.motion.qf.tolist() == [1.0, -1.0]


def edited(field: str, value: str | None) -> str:
    """GOOD with `field`'s line replaced by `value` (None: removed)."""
    lines = [line for line in GOOD.splitlines() if not line.startswith(f'{field}:')]
    return '\n'.join(lines + ([] if value is None else [f'{field}: {value}'])) + '\n'


@pytest.mark.parametrize('text, field', [
    (GOOD + 'speed: 3\n', "'speed'"),
    (edited('goal', None), "'goal'"),
    (GOOD + 'goal: [2.0, 2.0]\n', "'goal'"),
    (edited('joint_names', 'joint1'), 'joint_names'),
    (edited('joint_names', '[]'), 'joint_names'),
    (edited('joint_names', '[a, 7]'), 'joint_names'),
    (edited('joint_names', '[a, a]'), 'joint_names'),
    (edited('duration', '0.0'), 'duration'),
    (edited('duration', '-1.0'), 'duration'),
    (edited('duration', '.nan'), 'duration'),
    (edited('duration', '.inf'), 'duration'),
    (edited('duration', 'fast'), 'duration'),
    (edited('duration', 'true'), 'duration'),
    (edited('profile', 'trapezoid'), 'profile'),
    (edited('start', '[0.0]'), 'start'),
    (edited('start', '[0.0, 1.0, 2.0]'), 'start'),
    (edited('start', '0.0'), 'start'),
    (edited('goal', '[1.0, .inf]'), 'goal[1]'),
    (edited('goal', '[1.0, -.nan]'), 'goal[1]'),
    (edited('goal', '[one, 1.0]'), 'goal[0]'),
    (edited('start', '[0.0, false]'), 'start[1]'),
    # YAML 1.1's other numbers are text to YAML 1.2: never 60 s, 15, 3 or 10.
    (edited('duration', '1:00'), 'duration'),
    (edited('duration', '017'), 'duration'),
    (edited('duration', '0b11'), 'duration'),
    (edited('duration', '1_0'), 'duration'),
    (edited('duration', '0x10'), 'duration'),
    (edited('goal', '[1.0, 1_000.5]'), 'goal[1]'),
    (edited('goal', '[1:30.5, 1.0]'), 'goal[0]'),
    (edited('start', '[0.0, !!int 017]'), "'017' is not a YAML 1.2 decimal integer"),
    # A complex key, and integers beyond a float's range or beyond what Python converts from text.
    (GOOD + '? [a, b]\n: 1\n', "unknown key ? ['a', 'b']"),
    (edited('goal', '[1.0, {? [a]: 1}]'), 'goal[1]'),
    (edited('duration', '1' + '0' * 400), 'duration must be a finite number, got an integer beyond the range'),
    (edited('start', '[0.0, -' + '9' * 400 + ']'), 'start[1] must be a finite number, got an integer beyond'),
    (edited('duration', '9' * 5000), 'duration must be a finite number, got an integer of 5000 digits'),
    (edited('joint_names', '[a, ' + '9' * 5000 + ']'), 'joint_names must be a non-empty list of names'),
])
def test_every_refusal_names_the_file_and_the_field(tmp_path, text, field):
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(MotionError) as refused:
        load_motion(path)
    message = str(refused.value)
    assert message.startswith(f'{path}: ') and field in message, message


@pytest.mark.parametrize('text', ['- joint_names\n- duration\n', 'joint_names: [a, b\n', '', '\xff',
                                  'start: ' + '[' * 100_000 + ']' * 100_000 + '\n'])
def test_a_file_that_is_not_a_motion_mapping_is_refused_naming_it(tmp_path, text):
    path = tmp_path / 'bad.yaml'
    path.write_bytes(text.encode('latin-1'))
    with pytest.raises(MotionError, match='^' + str(path).replace('.', r'\.') + ': '):
        load_motion(path)


def test_a_missing_file_is_refused_naming_it(tmp_path):
    with pytest.raises(MotionError, match='cannot read the motion file'):
        load_motion(tmp_path / 'absent.yaml')


@pytest.mark.parametrize('text, value', [
    ('1e-05', 1e-05), ('2.5E+3', 2500.0), ('.5', 0.5), ('3.', 3.0), ('+1.5', 1.5), ('2', 2.0), ('017.5', 17.5),
    ('!!float 3', 3.0),
])
def test_yaml_1_2_numbers_are_read_as_yaml_1_2_has_them(tmp_path, text, value):
    path = tmp_path / 'motion.yaml'
    path.write_text(edited('duration', text))
    assert load_motion(path).motion.duration == value


def test_yaml_1_2_names_are_names_where_yaml_1_1_reads_booleans(tmp_path):
    path = tmp_path / 'motion.yaml'
    path.write_text(edited('joint_names', '[yes, off]'))
    assert load_motion(path).joint_names == ('yes', 'off')
    path.write_text(edited('joint_names', '[yes, true]'))
    with pytest.raises(MotionError, match='joint_names must be a non-empty list of names'):
        load_motion(path)


# The waypoint form and `locked`: every new field read back as written, every bad one refused by its name.
WAYPOINTS = """joint_names: [a, b]
start: [0.0, 1.0]
points:
  - positions: [0.5, 0.5]
    velocities: [1.0, -1.0]
    time_from_start: 0.5
  - positions: [1.0, -1.0]
    velocities: [0.0, 0.0]
    accelerations: [0.0, 0.0]
    time_from_start: {sec: 1, nanosec: 250000000}
locked: {c: 0.25, d: -1.5}
"""


def written(tmp_path, text: str, name: str = 'motion.yaml') -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_waypoint_file_loads_as_its_points(tmp_path):
    from ddarm.motion.waypoints import WaypointMotion

    loaded = load_motion(written(tmp_path, WAYPOINTS))
    motion = loaded.motion
    assert isinstance(motion, WaypointMotion)
    assert loaded.joint_names == ('a', 'b') and loaded.locked == (('c', 0.25), ('d', -1.5))
    assert motion.times.tolist() == [0.5, 1.25] and motion.duration == 1.25 and motion.dof == 2
    assert motion.positions.tolist() == [[0.5, 0.5], [1.0, -1.0]]
    assert motion.start.tolist() == [0.0, 1.0] and motion.q0.tolist() == [0.0, 1.0]
    assert motion.qf.tolist() == [1.0, -1.0]
    assert [v.tolist() for v in motion.velocities] == [[1.0, -1.0], [0.0, 0.0]]
    assert motion.accelerations[0] is None and motion.accelerations[1].tolist() == [0.0, 0.0]


def test_time_from_start_as_the_message_writes_it_is_the_same_time_in_seconds(tmp_path):
    as_message = load_motion(written(tmp_path, WAYPOINTS, 'a.yaml')).motion
    in_seconds = load_motion(written(tmp_path, WAYPOINTS.replace('{sec: 1, nanosec: 250000000}', '1.25'),
                                     'b.yaml')).motion
    assert bits(as_message.times) == bits(in_seconds.times)
    times = np.linspace(-0.1, 1.5, 33)
    for a, b in zip(as_message.sample(times), in_seconds.sample(times)):
        assert bits(a) == bits(b)
    # nanoseconds counted exactly and rounded once: 0.1 s is the double nearest 0.1
    one_tenth = WAYPOINTS.replace('{sec: 1, nanosec: 250000000}', '{sec: 0, nanosec: 900000000}')
    assert load_motion(written(tmp_path, one_tenth, 'c.yaml')).motion.times[-1] == 0.9


def test_a_waypoint_file_without_start_starts_at_its_first_point(tmp_path):
    text = """joint_names: [a]
points:
  - {positions: [0.25], velocities: [2.0], time_from_start: 0}
  - {positions: [1.0], time_from_start: 0.5}
"""
    motion = load_motion(written(tmp_path, text)).motion
    assert motion.start is None and motion.q0.tolist() == [0.25]
    q, v, _ = motion.sample(0.0)
    assert q.tolist() == [0.25] and v.tolist() == [1.5]  # point 1 has no velocities: the segment is linear


def test_waypoint_floats_written_with_repr_read_back_bit_for_bit(tmp_path):
    values = np.random.default_rng(3).normal(scale=[1e-300, 1e-8, 1.0, 1e8, 1e300], size=(6, 5))
    rows = [f'  - positions: [{", ".join(repr(float(v)) for v in row)}]\n'
            f'    velocities: [{", ".join(repr(float(v)) for v in row[::-1])}]\n'
            f'    time_from_start: {repr(0.1 * (k + 1) / 3)}\n' for k, row in enumerate(values)]
    rows[-1] = rows[-1].replace(rows[-1].splitlines()[1], '    velocities: [0.0, 0.0, 0.0, 0.0, 0.0]')
    text = ('joint_names: [j0, j1, j2, j3, j4]\nstart: [0.0, -0.0, 5e-324, 1e-05, 3.141592653589793]\npoints:\n'
            + ''.join(rows))
    motion = load_motion(written(tmp_path, text)).motion
    assert bits(motion.positions) == bits(values)
    assert all(bits(v) == bits(row[::-1]) for v, row in zip(motion.velocities[:-1], values[:-1]))
    assert bits(motion.times) == bits([0.1 * (k + 1) / 3 for k in range(6)])
    assert bits(motion.start) == bits([0.0, -0.0, 5e-324, 1e-05, np.pi])


def test_locked_joints_go_with_a_bang_bang_motion_too_and_default_to_none(tmp_path):
    assert load_motion(written(tmp_path, GOOD, 'a.yaml')).locked == ()
    assert load_motion(written(tmp_path, GOOD + 'locked: {}\n', 'b.yaml')).locked == ()
    loaded = load_motion(written(tmp_path, GOOD + 'locked: {z: 1, y: 0.5}\n', 'c.yaml'))
    assert loaded.locked == (('z', 1.0), ('y', 0.5)) and isinstance(loaded.locked[0][1], float)
    assert loaded.motion.q0.tolist() == [0.0, 1.0]


def waypoints_edited(old: str, new: str) -> str:
    assert old in WAYPOINTS
    return WAYPOINTS.replace(old, new)


LAST_TIME = 'time_from_start: {sec: 1, nanosec: 250000000}'


@pytest.mark.parametrize('text, field', [
    # the two forms
    (WAYPOINTS + 'profile: bang_bang\n', 'both profile'),
    (GOOD + 'points: []\n', 'both profile'),
    (WAYPOINTS + 'duration: 1.0\n', "unknown key 'duration' (a waypoint motion file"),
    (WAYPOINTS + 'goal: [1.0, 1.0]\n', "unknown key 'goal' (a waypoint motion file"),
    (edited('profile', None), "missing key 'profile' (or points, for a waypoint motion)"),
    (GOOD.replace('start', 'begin'), "unknown key 'begin' (a bang-bang motion file"),
    # points
    (waypoints_edited('points:\n', 'points: []\n').split('  - positions')[0] + 'locked: {}\n', 'points must be'),
    ('joint_names: [a]\npoints: 3\n', 'points must be a non-empty list'),
    ('joint_names: [a]\npoints: [3]\n', 'points[0] must be a mapping'),
    (waypoints_edited('    time_from_start: 0.5', '    time_from_start: 0.5\n    effort: [0.0, 0.0]'),
     "points[0]: unknown key 'effort'"),
    (waypoints_edited('  - positions: [0.5, 0.5]\n    velocities', '  - velocities'),
     "points[0]: missing key 'positions'"),
    (waypoints_edited('    time_from_start: 0.5\n', ''), "points[0]: missing key 'time_from_start'"),
    (waypoints_edited('positions: [1.0, -1.0]', 'positions: [1.0]'), 'points[1].positions must list one position'),
    (waypoints_edited('positions: [1.0, -1.0]', 'positions: 1.0'), 'points[1].positions must list'),
    (waypoints_edited('velocities: [1.0, -1.0]', 'velocities: [1.0, -1.0, 0.0]'), 'points[0].velocities must list'),
    (waypoints_edited('velocities: [1.0, -1.0]', 'velocities: [1.0, .nan]'), 'points[0].velocities[1]'),
    (waypoints_edited('velocities: [1.0, -1.0]', 'velocities: [1.0, fast]'), 'points[0].velocities[1]'),
    (waypoints_edited('accelerations: [0.0, 0.0]', 'accelerations: [0.0, .inf]'), 'points[1].accelerations[1]'),
    (waypoints_edited('positions: [0.5, 0.5]', 'positions: [0.5, -.inf]'), 'points[0].positions[1]'),
    (waypoints_edited('    velocities: [1.0, -1.0]\n', '    accelerations: [1.0, -1.0]\n'),
     'points[0] has accelerations without velocities'),
    # times
    (waypoints_edited('time_from_start: 0.5', 'time_from_start: -0.5'),
     'points[0].time_from_start must not be negative'),
    (waypoints_edited('time_from_start: 0.5', 'time_from_start: soon'), 'points[0].time_from_start must be a finite'),
    (waypoints_edited('time_from_start: 0.5', 'time_from_start: .nan'), 'points[0].time_from_start must be a finite'),
    (waypoints_edited('time_from_start: 0.5', 'time_from_start: 1:30'), 'points[0].time_from_start must be a finite'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: 1}'), 'points[1].time_from_start must be a number of seconds'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: 1, nanosec: 0, ns: 1}'), 'points[1].time_from_start must be'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: 1, nanosec: 1000000000}'),
     'points[1].time_from_start.nanosec must be an integer in [0, 999999999]'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: -1, nanosec: 0}'), 'points[1].time_from_start.sec'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: 1.0, nanosec: 0}'), 'points[1].time_from_start.sec'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: true, nanosec: 0}'), 'points[1].time_from_start.sec'),
    (waypoints_edited(LAST_TIME, 'time_from_start: {sec: 2147483648, nanosec: 0}'), 'points[1].time_from_start.sec'),
    (waypoints_edited(LAST_TIME, 'time_from_start: 0.25'), 'points[1].time_from_start 0.25 s is not after points[0]'),
    (waypoints_edited(LAST_TIME, 'time_from_start: 0.5'), 'points[1].time_from_start 0.5 s is not after points[0]'),
    (waypoints_edited('start: [0.0, 1.0]\n', ''), 'points[0].time_from_start is 0.5 s, not 0: give start'),
    (waypoints_edited('time_from_start: 0.5', 'time_from_start: 0'), 'points[0].time_from_start is 0.0 s with a start'),
    ('joint_names: [a]\npoints:\n  - {positions: [1.0], time_from_start: 0.0}\n', 'no motion'),
    # the end, held at rest
    (waypoints_edited('velocities: [0.0, 0.0]', 'velocities: [0.0, 0.1]'), 'points[1] (the last) has velocities'),
    # start
    (waypoints_edited('start: [0.0, 1.0]', 'start: [0.0]'), 'start must list one position per joint'),
    (waypoints_edited('start: [0.0, 1.0]', 'start:'), 'start must list one position per joint'),
    (waypoints_edited('start: [0.0, 1.0]', 'start: [0.0, .nan]'), 'start[1]'),
    # locked, in either form
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: [c, d]'), 'locked must be a mapping'),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked:'), 'locked must be a mapping'),
    (GOOD + 'locked: 0.5\n', 'locked must be a mapping'),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {1: 0.25}'), 'locked: 1 is not a joint name'),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {"": 0.25}'), "locked: '' is not a joint name"),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {? [c]: 0.25}'), 'is not a joint name'),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {c: .nan}'), "locked['c'] must be a finite number"),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {c: up}'), "locked['c'] must be a finite number"),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {c: [0.0]}'), "locked['c'] must be a finite number"),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {c: 0.0, c: 1.0}'), "duplicate key 'c'"),
    (waypoints_edited('locked: {c: 0.25, d: -1.5}', 'locked: {b: 0.0}'), "locked['b']: the motion drives 'b'"),
    (GOOD + 'locked: {a: 0.0}\n', "locked['a']: the motion drives 'a'"),
])
def test_every_refusal_of_the_waypoint_form_and_locked_names_the_file_and_the_field(tmp_path, text, field):
    path = written(tmp_path, text, 'bad.yaml')
    with pytest.raises(MotionError) as refused:
        load_motion(path)
    message = str(refused.value)
    assert message.startswith(f'{path}: ') and field in message, message


def test_a_refused_waypoint_file_is_one_line_from_the_command(tmp_path, capsys):
    """A user's mistake in a motion file is a refusal, never a traceback: the same MotionError the CLI prints."""
    path = written(tmp_path, waypoints_edited('velocities: [0.0, 0.0]', 'velocities: [0.0, 0.1]'))
    code = 'import sys\nfrom ddarm.motion.files import load_motion\nload_motion(sys.argv[1])\n'
    done = subprocess.run([sys.executable, '-c', code, str(path)], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parent.parent)
    assert done.returncode != 0 and done.stderr.strip().splitlines()[-1].startswith(
        f'ddarm.motion.programmed.MotionError: {path}: points[1] (the last) has velocities')
    assert 'During handling' not in done.stderr  # no chained traceback under the refusal
