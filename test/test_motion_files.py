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
    names = [f'j{i}' for i in range(len(values))]
    path = tmp_path / 'motion.yaml'
    path.write_text(f'joint_names: [{", ".join(names)}]\nduration: 0.1\nprofile: bang_bang\n'
                    f'start: [{", ".join(repr(float(v)) for v in values)}]\n'
                    f'goal: [{", ".join(repr(float(v)) for v in values[::-1])}]\n')
    loaded = load_motion(path)
    assert loaded.joint_names == tuple(names)
    assert bits(loaded.motion.q0) == bits(values) and bits(loaded.motion.qf) == bits(values[::-1])


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
