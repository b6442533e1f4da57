"""The programmed motions of spec §4 and the nominal torque and limits of section 7."""

import numpy as np
import pytest

from ddarm.physics.arm import Arm
from ddarm.motion.programmed import (ProgrammedMotion, nominal_torque, paper_torque_limit, paper_trajectory,
                                  sample_count, sample_times)


@pytest.fixture(scope='module')
def arm():
    return Arm.from_urdf()


@pytest.mark.parametrize('number', [1, 2])
@pytest.mark.parametrize('duration', [0.5, 1.0, 1.7])
def test_free_end_stays_on_the_ground_plane(arm, number, duration):
    motion = paper_trajectory(number, duration)
    positions, _, _ = motion.sample(np.linspace(0, duration, 301))
    for q in positions:
        assert abs(arm.frame_position(q, 'tool')[2]) <= 1e-12


@pytest.mark.parametrize('number, start, end', [(1, (1, 0, 0), (0, 2, 0)), (2, (0, 2, 0), (0, 0, 0))])
def test_trajectories_start_and_end_where_the_paper_says(arm, number, start, end):
    motion = paper_trajectory(number, 1.0)
    (q_start, q_end), (v_start, v_end), _ = motion.sample(np.array([0.0, 1.0]))
    np.testing.assert_array_equal(q_start, motion.q0)
    np.testing.assert_allclose(q_end, motion.qf, atol=1e-15)
    np.testing.assert_array_equal(v_start, 0.0)
    np.testing.assert_allclose(v_end, 0.0, atol=1e-15)
    np.testing.assert_allclose(arm.frame_position(q_start, 'tool'), start, atol=1e-12)
    np.testing.assert_allclose(arm.frame_position(q_end, 'tool'), end, atol=1e-12)


def test_bang_bang_phases_and_the_hold_after_t():
    motion = ProgrammedMotion(np.zeros(1), np.ones(1), 2.0)
    times = sample_times(2.0, 0.01)
    q, v, a = motion.sample(times)
    assert a[0, 0] == 1.0 and a[99, 0] == 1.0  # 4 (qf - q0) / T²
    assert a[100, 0] == -1.0  # t = T/2 exactly: deceleration (spec §5)
    assert a[200, 0] == -1.0  # t = T: deceleration too
    assert q[100, 0] == pytest.approx(0.5) and v[100, 0] == pytest.approx(1.0)
    q_after, v_after, a_after = motion.sample(2.5)
    assert (q_after[0], v_after[0], a_after[0]) == (1.0, 0.0, 0.0)


def test_sample_times_are_products_not_sums():
    times = sample_times(1.0, 0.01)
    assert len(times) == 101
    assert times[50] == 50 * 0.01 and times[100] == 100 * 0.01


@pytest.mark.parametrize('duration, period', [(1.0, 0.003), (1.0, 0.0), (1.0, -0.01), (1.0, float('nan'))])
def test_bad_sampling_is_refused(duration, period):
    with pytest.raises(ValueError):
        sample_count(duration, period)


def test_nominal_torque_is_the_inverse_dynamics_of_the_motion(arm):
    motion = paper_trajectory(1, 1.0)
    times = sample_times(1.0, 0.01)
    nominal = nominal_torque(arm, motion, times)
    q, v, a = motion.sample(times[37])
    np.testing.assert_allclose(nominal[37], arm.mass_matrix(q) @ a + arm.bias(q, v), atol=1e-9)
    limit = paper_torque_limit(nominal)
    np.testing.assert_allclose(limit, 2 * np.abs(nominal).max(axis=0))
