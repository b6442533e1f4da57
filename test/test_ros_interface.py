"""Message <-> array conversion: every malformed message is refused with its problem named
(docs/faults.md 1, 4-6, 8)."""

import numpy as np
import pytest
from trajectory_msgs.msg import JointTrajectory

from ddarm.ros.interface import (joint_state_msg, read_joint_state, read_reference, reference_msg, sample_index,
                                     time_msg)
from ddarm.samples import MAX_JOINTS, MessageError

JOINTS = ['joint1', 'joint2', 'joint3']


def state(t=0.05, names=JOINTS, q=(0.1, 0.2, 0.3), v=(1.0, 2.0, 3.0), effort=None):
    msg = joint_state_msg(names, t, np.array(q), np.array(v), None if effort is None else np.array(effort))
    return msg


def test_a_good_state_reads_back_exactly():
    sample = read_joint_state(state(), JOINTS, 0.01)
    assert sample.n == 5
    np.testing.assert_array_equal(sample.q, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(sample.v, [1.0, 2.0, 3.0])


def test_reordered_names_are_mapped_by_name():
    sample = read_joint_state(state(names=['joint3', 'joint1', 'joint2']), JOINTS, 0.01)
    np.testing.assert_array_equal(sample.q, [0.2, 0.3, 0.1])


@pytest.mark.parametrize('message, problem', [
    (state(q=(0.1, np.nan, 0.3)), 'position is not finite at index'),
    (state(v=(0.1, np.inf, 0.3)), 'velocity is not finite'),
    (state(q=(0.1, 0.2)), 'position has 2 values for 3 joints'),
    (state(names=['joint1', 'joint2', 'elbow']), "unknown joints ['elbow']"),
    (state(names=['joint1', 'joint2']), "missing joints ['joint3']"),
    (state(names=['joint1', 'joint1', 'joint2']), 'duplicate joint names'),
    (state(t=0.0543), 'not a sample instant'),
    (state(names=[f'j{i}' for i in range(MAX_JOINTS + 1)]), 'more than'),
])
def test_bad_states_are_refused_with_the_problem_named(message, problem):
    with pytest.raises(MessageError, match=problem.replace('[', r'\[').replace(']', r'\]')):
        read_joint_state(message, JOINTS, 0.01)


def test_negative_stamps_are_refused():
    msg = state()
    msg.header.stamp.sec = -1
    with pytest.raises(MessageError, match='not a sample instant'):
        read_joint_state(msg, JOINTS, 0.01)


def test_commands_need_effort_and_not_state():
    command = read_joint_state(joint_state_msg(JOINTS, 0.02, effort=np.array([1.0, 2.0, 3.0])), JOINTS, 0.01,
                               need_state=False, need_effort=True)
    assert command.q is None and command.n == 2
    with pytest.raises(MessageError, match='effort has 0 values'):
        read_joint_state(joint_state_msg(JOINTS, 0.02), JOINTS, 0.01, need_state=False, need_effort=True)


@pytest.mark.parametrize('n', [0, 1, 50, 99, 100, 12345])
def test_stamps_round_trip_to_sample_indices(n):
    assert sample_index(time_msg(n * 0.01), 0.01) == n


def make_reference(joints=JOINTS, count=3):
    times = np.arange(4) * 0.01
    values = np.arange(4 * count, dtype=float).reshape(4, count)
    return reference_msg(joints, times, values, values + 1, values + 2, values + 3)


def test_a_reference_reads_back_with_its_nominal_torque():
    reference = read_reference(make_reference(), JOINTS, 0.01)
    assert len(reference.times) == 4
    np.testing.assert_array_equal(reference.nominal[1], [6.0, 7.0, 8.0])
    q, v, a = reference.point(10)  # after the motion: q_f at rest
    np.testing.assert_array_equal(q, reference.q[-1])
    assert not v.any() and not a.any()


def test_references_with_wrong_joints_or_times_are_refused():
    with pytest.raises(MessageError, match='missing joints'):
        read_reference(make_reference(joints=['joint1', 'joint2'], count=2), JOINTS, 0.01)
    with pytest.raises(MessageError, match='not at sample time'):
        read_reference(make_reference(), JOINTS, 0.02)
    with pytest.raises(MessageError, match='no points'):
        read_reference(JointTrajectory(joint_names=JOINTS), JOINTS, 0.01)
    bad = make_reference()
    bad.points[2].accelerations[1] = float('nan')
    with pytest.raises(MessageError, match='reference point 2: accelerations is not finite'):
        read_reference(bad, JOINTS, 0.01)
