"""Waypoint motions: each segment against its closed form (linear, cubic Hermite, quintic), knots hit exactly, the
start at rest, the hold after the end, vectorised shapes, and the JTC's own arithmetic transcribed point by point."""

import numpy as np
import pytest

from ddarm.motion.programmed import MotionError, sample_times
from ddarm.motion.waypoints import WaypointMotion


def hermite(t, ta, tb, qa, va, qb, vb):
    """The cubic Hermite segment in its basis-function form (not the JTC's power form)."""
    T = tb - ta
    s = (t - ta) / T
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    d00, d10, d01, d11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    e00, e10, e01, e11 = 12 * s - 6, 6 * s - 4, -12 * s + 6, 6 * s - 2
    q = h00 * qa + h10 * T * va + h01 * qb + h11 * T * vb
    v = (d00 * qa + d10 * T * va + d01 * qb + d11 * T * vb) / T
    a = (e00 * qa + e10 * T * va + e01 * qb + e11 * T * vb) / T**2
    return q, v, a


def quintic(t, ta, tb, qa, va, aa, qb, vb, ab):
    """The quintic through both ends' q, q̇, q̈: the 6 x 6 boundary system solved numerically."""
    T = tb - ta
    rows = np.array([[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], [0, 0, 2, 0, 0, 0],
                     [1, T, T**2, T**3, T**4, T**5], [0, 1, 2 * T, 3 * T**2, 4 * T**3, 5 * T**4],
                     [0, 0, 2, 6 * T, 12 * T**2, 20 * T**3]], dtype=float)
    c = np.linalg.solve(rows, np.array([qa, va, aa, qb, vb, ab], dtype=float))
    x = t - ta
    q = sum(c[k] * x**k for k in range(6))
    v = sum(k * c[k] * x ** (k - 1) for k in range(1, 6))
    a = sum(k * (k - 1) * c[k] * x ** (k - 2) for k in range(2, 6))
    return q, v, a


def inside(ta, tb, count=7):
    return np.linspace(ta, tb, count + 2)[1:-1]


def test_a_linear_segment_is_the_straight_line_at_constant_velocity():
    motion = WaypointMotion([0.0, 2.0], [[1.0, -1.0], [2.0, 3.0]])
    t = inside(0.0, 2.0)
    q, v, a = motion.sample(t)
    np.testing.assert_allclose(q, [1.0, -1.0] + np.outer(t / 2.0, [1.0, 4.0]), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(v, np.tile([0.5, 2.0], (len(t), 1)))
    np.testing.assert_array_equal(a, 0.0)


def test_a_cubic_segment_is_the_hermite_cubic():
    qa, va, qb, vb = np.array([0.2, -1.0]), np.array([1.5, 0.0]), np.array([1.0, 0.5]), np.array([0.0, 0.0])
    motion = WaypointMotion([0.0, 0.8], [qa, qb], velocities=(va, vb))
    t = inside(0.0, 0.8)
    got = motion.sample(t)
    for joint in range(2):
        expected = hermite(t, 0.0, 0.8, qa[joint], va[joint], qb[joint], vb[joint])
        for g, e in zip(got, expected):
            np.testing.assert_allclose(g[:, joint], e, rtol=1e-12, atol=1e-12)


def test_a_quintic_segment_meets_both_ends_in_position_velocity_and_acceleration():
    ends = dict(qa=[0.0, 1.0], va=[0.5, -2.0], aa=[3.0, 0.0], qb=[1.0, 0.0], vb=[0.0, 0.0], ab=[0.0, 0.0])
    motion = WaypointMotion([0.0, 1.3], [ends['qa'], ends['qb']], velocities=(ends['va'], ends['vb']),
                            accelerations=(ends['aa'], ends['ab']))
    t = inside(0.0, 1.3)
    got = motion.sample(t)
    for joint in range(2):
        expected = quintic(t, 0.0, 1.3, *(ends[key][joint] for key in ('qa', 'va', 'aa', 'qb', 'vb', 'ab')))
        for g, e in zip(got, expected):
            np.testing.assert_allclose(g[:, joint], e, rtol=1e-9, atol=1e-9)
    q, v, a = motion.sample(0.0)
    assert q.tolist() == ends['qa'] and v.tolist() == ends['va'] and a.tolist() == ends['aa']


def test_mid_segment_values_worked_by_hand():
    # Rest to rest, 0 to 1 in 1 s: the cubic 3s^2 - 2s^3 and the quintic 10s^3 - 15s^4 + 6s^5.
    rest = (np.zeros(1), np.zeros(1))
    cubic = WaypointMotion([0.0, 1.0], [[0.0], [1.0]], velocities=rest)
    quintic_ = WaypointMotion([0.0, 1.0], [[0.0], [1.0]], velocities=rest, accelerations=rest)
    assert [x.item() for x in cubic.sample(0.5)] == [0.5, 1.5, 0.0]
    assert [x.item() for x in cubic.sample(0.25)] == [0.15625, 1.125, 3.0]
    assert [x.item() for x in quintic_.sample(0.5)] == [0.5, 1.875, 0.0]
    q, v, a = (x.item() for x in quintic_.sample(0.25))
    assert q == pytest.approx(0.103515625, abs=1e-15)  # 10/64 - 15/256 + 6/1024
    assert v == pytest.approx(1.0546875, abs=1e-15)  # 30 s^2 - 60 s^3 + 30 s^4
    assert a == pytest.approx(5.625, abs=1e-14)  # 60 s - 180 s^2 + 120 s^3


MIXED_TIMES = [0.0, 0.4, 0.9, 1.5, 2.0, 2.6]
MIXED_POSITIONS = [[0.0, 1.0], [0.5, 0.8], [1.2, 0.1], [0.9, -0.4], [1.5, 0.0], [1.0, 0.3]]
MIXED_VELOCITIES = (None, [1.0, -0.5], [0.3, -1.0], [-0.2, 0.4], [0.6, 0.2], [0.0, 0.0])
MIXED_ACCELERATIONS = (None, None, [2.0, 0.0], [-1.0, 3.0], None, None)


def mixed() -> WaypointMotion:
    return WaypointMotion(MIXED_TIMES, MIXED_POSITIONS, MIXED_VELOCITIES, MIXED_ACCELERATIONS)


def test_each_segment_takes_the_type_its_two_points_allow():
    motion = mixed()
    q, v, a = (np.array(x, dtype=float) for x in (MIXED_POSITIONS, MIXED_VELOCITIES[1:], MIXED_ACCELERATIONS[2:4]))
    t = MIXED_TIMES
    kinds = ['linear', 'cubic', 'quintic', 'cubic', 'cubic']  # point 0 has no velocities; points 2-3 have both
    for segment, kind in enumerate(kinds):
        times = inside(t[segment], t[segment + 1])
        got = motion.sample(times)
        for joint in range(2):
            if kind == 'linear':
                slope = (q[1, joint] - q[0, joint]) / (t[1] - t[0])
                expected = (q[0, joint] + slope * (times - t[0]), np.full_like(times, slope), np.zeros_like(times))
            elif kind == 'cubic':
                expected = hermite(times, t[segment], t[segment + 1], q[segment, joint], v[segment - 1, joint],
                                   q[segment + 1, joint], v[segment, joint])
            else:
                expected = quintic(times, t[2], t[3], q[2, joint], v[1, joint], a[0, joint], q[3, joint],
                                   v[2, joint], a[1, joint])
            for g, e in zip(got, expected):
                np.testing.assert_allclose(g[:, joint], e, rtol=1e-10, atol=1e-10, err_msg=f'{kind} {segment}')


def test_each_point_is_hit_exactly_in_the_fields_its_segment_uses():
    motion = mixed()
    for k, t in enumerate(MIXED_TIMES[:-1]):
        q, v, a = motion.sample(t)
        assert q.tolist() == MIXED_POSITIONS[k]
        if k >= 1:  # the segment from point k is cubic or quintic: it starts at the point's velocity
            assert v.tolist() == MIXED_VELOCITIES[k]
        if k == 2:  # the quintic segment starts at the point's acceleration
            assert a.tolist() == MIXED_ACCELERATIONS[k]
    q, v, a = motion.sample(MIXED_TIMES[-1])
    assert q.tolist() == MIXED_POSITIONS[-1] and v.tolist() == [0.0, 0.0] and a.tolist() == [0.0, 0.0]


def left_limit(motion, t):
    return [np.array(x) for x in motion.sample(t - 1e-7)]


def test_position_is_continuous_at_every_point_and_velocity_where_both_segments_use_the_points_velocity():
    motion = mixed()
    for k in range(1, len(MIXED_TIMES)):
        before, at = left_limit(motion, MIXED_TIMES[k]), motion.sample(MIXED_TIMES[k])
        np.testing.assert_allclose(before[0], at[0], atol=1e-6)
        if k >= 2:  # cubic or quintic on both sides (after the last point: held at rest, its velocity zero)
            np.testing.assert_allclose(before[1], at[1], atol=1e-5)
    # the quintic segment (points 2 to 3) ends at point 3's acceleration
    np.testing.assert_allclose(left_limit(motion, MIXED_TIMES[3])[2], MIXED_ACCELERATIONS[3], atol=1e-3)


def test_quintic_segments_join_continuously_in_acceleration():
    times = [0.0, 0.5, 1.2, 2.0]
    positions = [[0.0], [1.0], [0.4], [2.0]]
    velocities = ([0.0], [1.5], [-0.5], [0.0])
    accelerations = ([0.0], [-4.0], [6.0], [0.0])
    motion = WaypointMotion(times, positions, velocities, accelerations)
    for k in (1, 2, 3):
        before, at = left_limit(motion, times[k]), motion.sample(times[k])
        for field, tolerance in enumerate((1e-6, 1e-5, 1e-3)):  # 1e-7 s before: within the jerk's reach
            np.testing.assert_allclose(before[field], at[field], atol=tolerance)
        assert at[2].tolist() == accelerations[k]


def test_a_velocity_jump_is_where_a_linear_segment_meets_a_cubic():
    # The linear segment's velocity is its slope, the cubic's starts at the point's velocity: they differ.
    motion = mixed()
    left = motion.sample(MIXED_TIMES[1] - 1e-7)[1]
    right = motion.sample(MIXED_TIMES[1])[1]
    assert not np.allclose(left, right, atol=1e-3)
    np.testing.assert_array_equal(right, MIXED_VELOCITIES[1])


@pytest.mark.parametrize('fields, kind', [((None, None), 'linear'), (([1.0, 0.0], None), 'cubic'),
                                          (([1.0, 0.0], [0.5, -2.0]), 'quintic')])
def test_the_segment_from_the_start_starts_at_rest_and_follows_the_first_points_fields(fields, kind):
    velocity, acceleration = fields
    start, first, goal = np.array([0.0, 0.5]), np.array([1.0, 1.5]), np.array([2.0, 1.0])
    motion = WaypointMotion([0.6, 1.0], [first, goal], velocities=None if velocity is None else (velocity, [0.0, 0.0]),
                            accelerations=None if acceleration is None else (acceleration, [0.0, 0.0]), start=start)
    assert motion.q0.tolist() == start.tolist() and motion.qf.tolist() == goal.tolist()
    assert motion.duration == 1.0 and motion.dof == 2
    t = inside(0.0, 0.6)
    got = motion.sample(t)
    for joint in range(2):
        if kind == 'linear':
            slope = (first[joint] - start[joint]) / 0.6
            expected = (start[joint] + slope * t, np.full_like(t, slope), np.zeros_like(t))
        elif kind == 'cubic':
            expected = hermite(t, 0.0, 0.6, start[joint], 0.0, first[joint], velocity[joint])
        else:
            expected = quintic(t, 0.0, 0.6, start[joint], 0.0, 0.0, first[joint], velocity[joint], acceleration[joint])
        for g, e in zip(got, expected):
            np.testing.assert_allclose(g[:, joint], e, rtol=1e-10, atol=1e-10)
    q, v, a = motion.sample(0.0)
    assert q.tolist() == start.tolist()
    if kind != 'linear':
        assert v.tolist() == [0.0, 0.0]
    if kind == 'quintic':
        assert a.tolist() == [0.0, 0.0]
    q, v, _ = motion.sample(0.6)
    assert q.tolist() == first.tolist()
    assert v.tolist() == (((goal - first) / 0.4).tolist() if kind == 'linear' else velocity)


def test_before_the_start_and_after_the_last_point_the_arm_is_at_rest():
    motion = WaypointMotion([0.5, 1.0], [[1.0, 2.0], [3.0, -1.0]], velocities=([2.0, 0.0], [0.0, 0.0]),
                            start=[0.5, 0.5])
    for t in (-3.0, -1e-3):
        q, v, a = motion.sample(t)
        assert q.tolist() == [0.5, 0.5] and v.tolist() == [0.0, 0.0] and a.tolist() == [0.0, 0.0]
    for t in (1.0, 1.0 + 1e-6, 7.0):
        q, v, a = motion.sample(t)
        assert q.tolist() == [3.0, -1.0] and v.tolist() == [0.0, 0.0] and a.tolist() == [0.0, 0.0]


@pytest.mark.parametrize('shape', [(), (5,), (2, 3)])
def test_sample_is_vectorised_over_any_shape_of_times(shape):
    motion = mixed()
    t = np.random.default_rng(1).uniform(-0.5, 3.0, size=shape)
    got = motion.sample(t)
    for values in got:
        assert values.shape == (*shape, 2)
    for index in np.ndindex(*shape):
        for g, e in zip(got, motion.sample(float(t[index]))):
            np.testing.assert_array_equal(g[index], e)


def test_a_python_float_gives_one_vector_per_field():
    q, v, a = mixed().sample(0.7)
    assert q.shape == v.shape == a.shape == (2,)


def test_sample_times_that_land_on_a_point_only_up_to_rounding_give_the_point():
    # j Δ with Δ = 0.01 is 0.35000000000000003 for j = 35, 0.7000000000000001 for j = 70: still the points.
    times = sample_times(1.0, 0.01)
    assert times[35] != 0.35 and times[70] != 0.7
    motion = WaypointMotion([0.0, 0.35, 0.7, 1.0], [[0.0], [1.0], [-1.0], [0.5]],
                            velocities=([0.0], [2.0], [-3.0], [0.0]), accelerations=([0.0], [1.0], [4.0], [0.0]))
    q, v, a = motion.sample(times)
    for j, k in ((0, 0), (35, 1), (70, 2), (100, 3)):
        assert q[j].item() == motion.positions[k].item()
        assert v[j].item() == motion.velocities[k].item() and a[j].item() == motion.accelerations[k].item()
    for t, k in ((0.35 - 1e-12, 1), (0.35 + 1e-12, 1), (0.7 - 1e-12, 2), (1.0 - 1e-12, 3)):  # within 1e-9 T
        q, v, a = motion.sample(t)
        assert (q.item(), v.item(), a.item()) == (motion.positions[k].item(), motion.velocities[k].item(),
                                                  motion.accelerations[k].item())
    # just beyond the allowance, the sample is inside the segment again
    assert motion.sample(0.35 + 1e-6)[0].item() != 1.0
    assert motion.sample(0.35 - 1e-6)[0].item() != 1.0


def jtc_interpolate(ta, pa, tb, pb, t):
    """Trajectory::interpolate_between_points (ros2_controllers, Jazzy), one joint at a time, as the C++ loops it."""
    so_far, between = t - ta, tb - ta
    has_velocity = pa['v'] is not None and pb['v'] is not None
    has_accel = pa['a'] is not None and pb['a'] is not None
    x = [1.0]
    for _ in range(5):
        x.append(x[-1] * so_far)
    out = []
    for i in range(len(pa['q'])):
        if not has_velocity and not has_accel:
            c1 = (pb['q'][i] - pa['q'][i]) / between
            out.append((x[0] * pa['q'][i] + x[1] * c1, x[0] * c1, 0.0))
        elif has_velocity and not has_accel:
            T = [1.0, between, between * between, between * between * between]
            sp, sv, ep, ev = pa['q'][i], pa['v'][i], pb['q'][i], pb['v'][i]
            c = [sp, sv, (-3.0 * sp + 3.0 * ep - 2.0 * sv * T[1] - ev * T[1]) / T[2],
                 (2.0 * sp - 2.0 * ep + sv * T[1] + ev * T[1]) / T[3]]
            out.append((x[0] * c[0] + x[1] * c[1] + x[2] * c[2] + x[3] * c[3],
                        x[0] * c[1] + x[1] * 2.0 * c[2] + x[2] * 3.0 * c[3],
                        x[0] * 2.0 * c[2] + x[1] * 6.0 * c[3]))
        else:
            T = [1.0]
            for _ in range(5):
                T.append(T[-1] * between)
            sp, sv, sa, ep, ev, ea = pa['q'][i], pa['v'][i], pa['a'][i], pb['q'][i], pb['v'][i], pb['a'][i]
            c = [sp, sv, 0.5 * sa,
                 (-20.0 * sp + 20.0 * ep - 3.0 * sa * T[2] + ea * T[2] - 12.0 * sv * T[1] - 8.0 * ev * T[1])
                 / (2.0 * T[3]),
                 (30.0 * sp - 30.0 * ep + 3.0 * sa * T[2] - 2.0 * ea * T[2] + 16.0 * sv * T[1] + 14.0 * ev * T[1])
                 / (2.0 * T[4]),
                 (-12.0 * sp + 12.0 * ep - sa * T[2] + ea * T[2] - 6.0 * sv * T[1] - 6.0 * ev * T[1]) / (2.0 * T[5])]
            out.append((x[0] * c[0] + x[1] * c[1] + x[2] * c[2] + x[3] * c[3] + x[4] * c[4] + x[5] * c[5],
                        x[0] * c[1] + x[1] * 2.0 * c[2] + x[2] * 3.0 * c[3] + x[3] * 4.0 * c[4] + x[4] * 5.0 * c[5],
                        x[0] * 2.0 * c[2] + x[1] * 6.0 * c[3] + x[2] * 12.0 * c[4] + x[3] * 20.0 * c[5]))
    return [np.array(field) for field in zip(*out)]


def test_the_samples_are_the_jtcs_own_arithmetic_to_the_bit():
    motion = mixed()
    points = [dict(q=np.array(q, dtype=float), v=None if v is None else np.array(v, dtype=float),
                   a=None if a is None else np.array(a, dtype=float))
              for q, v, a in zip(MIXED_POSITIONS, MIXED_VELOCITIES, MIXED_ACCELERATIONS)]
    for t in np.random.default_rng(2).uniform(0.0, MIXED_TIMES[-1], size=200):
        k = int(np.searchsorted(MIXED_TIMES, t, side='right')) - 1
        expected = jtc_interpolate(MIXED_TIMES[k], points[k], MIXED_TIMES[k + 1], points[k + 1], t)
        for g, e in zip(motion.sample(t), expected):
            np.testing.assert_array_equal(g, e)


@pytest.mark.parametrize('arguments, message', [
    (dict(times=[0.0, 1.0], positions=[[0.0], [1.0]], accelerations=([0.0], [0.0])),
     'points[0] has accelerations without velocities'),
    (dict(times=[0.0, 1.0], positions=[[0.0], [1.0]], velocities=([0.0], [0.5])),
     'points[1] (the last) has velocities'),
    (dict(times=[0.5, 1.0], positions=[[0.0], [1.0]]), 'points[0].time_from_start is 0.5 s, not 0: give start'),
    (dict(times=[0.0, 1.0], positions=[[0.0], [1.0]], start=[0.0]), 'points[0].time_from_start is 0.0 s with a start'),
    (dict(times=[0.0, 1.0, 1.0], positions=[[0.0], [1.0], [2.0]]), 'points[2].time_from_start 1.0 s is not after'),
    (dict(times=[0.0, 1.0, 1.0 + 1e-10], positions=[[0.0], [1.0], [2.0]]), 'points[2].time_from_start'),
    (dict(times=[0.0], positions=[[0.0]]), 'no motion'),
    (dict(times=[0.0, 1.0], positions=[[0.0], [np.nan]]), 'positions must be finite'),
    (dict(times=[0.0, 1.0], positions=[[0.0], [1.0]], start=[0.0, 1.0]), 'start must hold one position per joint'),
    (dict(times=[0.0, 1.0], positions=[[0.0], [1.0]], velocities=([0.0],)), 'velocities must be given for each'),
    (dict(times=[0.0, 1.0], positions=[[0.0], [1.0]], velocities=([np.inf], [0.0])), 'points[0].velocities must be'),
    (dict(times=[0.0, 1.0], positions=[0.0, 1.0]), 'times and positions must be'),
])
def test_a_waypoint_motion_refuses_what_no_spline_or_hold_can_follow(arguments, message):
    with pytest.raises(MotionError) as refused:
        WaypointMotion(**arguments)
    assert message in str(refused.value), str(refused.value)
