"""Waypoint motions: q^d(t) through the points of a trajectory_msgs/JointTrajectory, splined as ros2_controllers does.

The interpolation is the joint_trajectory_controller's with interpolation_method "splines" (ros2_controllers,
Jazzy: joint_trajectory_controller/src/trajectory.cpp, Trajectory::sample and interpolate_between_points), so a
motion file's waypoints give the same q^d here as on a robot the JTC drives. Between points a and b, with
T = t_b - t_a and τ = t - t_a:

- linear, when either point lacks velocities: q = q_a + τ (q_b - q_a) / T, q̇ = (q_b - q_a) / T, q̈ = 0;
- cubic Hermite, when both have velocities but not both accelerations: q(0) = q_a, q̇(0) = q̇_a, q(T) = q_b,
  q̇(T) = q̇_b;
- quintic, when both have velocities and accelerations: q, q̇ and q̈ of both points.

The coefficients and the order of the sums are the JTC's, so the numbers agree to rounding; times are double
seconds here where the JTC counts integer nanoseconds. A sample time at a point's time belongs to the segment
that starts there (the JTC's `t0 <= t < t1`), which gives that point's q and q̇ exactly.

With a `start` (q at t = 0, at rest) before a first point at t_0 > 0, the first segment runs from the start
with zero velocity and acceleration, the JTC's segment from the state it holds when a trajectory arrives
(Trajectory::set_point_before_trajectory_msg): its type follows the first point's fields. (A JTC clears that
state's velocities or accelerations when the hardware has no such state interface, which makes the segment
linear or cubic there: the same q^d as ddarm's only on hardware that reports them.) Before t = 0 the motion
is at q0, after its last point it holds that point's positions, at rest: the last point's velocities are zero,
its accelerations (as the JTC allows) anything, the end of the last segment.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# The bang-bang phases' allowance for rounding, relative to the duration: a sample time within it of a point's
# time is that point's time (sample instants land on the points only up to rounding, j Δ against t_k).
from ddarm.motion.programmed import _PHASE_EDGE, MotionError

# A motion's points, bounded before any work on them: 100 s of a 1 kHz recording.
MAX_POINTS = 100_000
# The quintic's coefficients, the most of any segment type: every segment is kept as six, the lower types' with
# zeros, which add nothing to the JTC's sums.
_TERMS = 6


@dataclass(frozen=True)
class WaypointMotion:
    """q^d(t) through trajectory points (time_from_start, positions and optionally velocities, accelerations).

    times: (m,) each point's time_from_start, s, strictly increasing; 0 for the first unless `start` is given.
    positions: (m, n) each point's q. velocities, accelerations: one per point, an (n,) array or None where the
    point has none (the message's empty list); None for all: no point has them. start: q at t = 0, or None when
    the first point is at t = 0 (then it is the start).
    """

    times: np.ndarray
    positions: np.ndarray
    velocities: tuple | None = None
    accelerations: tuple | None = None
    start: np.ndarray | None = None
    # The spline, made once: the knots (the start, when given, and the points) and each segment's coefficients.
    _knot_times: np.ndarray = field(init=False, repr=False, compare=False)
    _knot_positions: np.ndarray = field(init=False, repr=False, compare=False)
    _coefficients: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Copies: the spline is made from them once, so a caller's later change to its arrays must not reach them.
        times = np.array(self.times, dtype=float)
        positions = np.array(self.positions, dtype=float)
        if times.ndim != 1 or positions.ndim != 2 or len(times) != len(positions) or not len(times) \
                or not positions.shape[1]:
            raise MotionError(f'times and positions must be (m,) and (m, n) for m points of n joints, got shapes '
                              f'{times.shape} and {positions.shape}')
        count, joints = positions.shape
        velocities = self._per_point('velocities', self.velocities, count, joints)
        accelerations = self._per_point('accelerations', self.accelerations, count, joints)
        start = None if self.start is None else np.array(self.start, dtype=float)
        if start is not None and start.shape != (joints,):
            raise MotionError(f'start must hold one position per joint ({joints}), got shape {start.shape}')
        if count > MAX_POINTS:
            raise MotionError(f'{count} points, more than the {MAX_POINTS} a waypoint motion may have')
        for name, values in (('times', times), ('positions', positions), ('start', start)):
            if values is not None and not np.all(np.isfinite(values)):
                at = np.argwhere(~np.isfinite(values))[0]
                raise MotionError(f'{name} must be finite, got {float(values[tuple(at)])!r} at '
                                  f'[{", ".join(map(str, at))}]')
        for i, (velocity, acceleration) in enumerate(zip(velocities, accelerations)):
            if acceleration is not None and velocity is None:
                # The JTC's spline has no segment for it: interpolate_between_points would leave q at zero.
                raise MotionError(f'points[{i}] has accelerations without velocities')
        if start is None and times[0] != 0.0:
            raise MotionError(f'points[0].time_from_start is {float(times[0])!r} s, not 0: give start, q at t = 0')
        if start is not None and not times[0] > 0.0:
            raise MotionError(f'points[0].time_from_start is {float(times[0])!r} s with a start: after start (t = 0), '
                              'the first point must come later; without start, points[0] is the start')
        if not times[-1] > 0.0:
            raise MotionError('one point at t = 0 and no start is no motion: give start, or a later point')
        edge = _PHASE_EDGE * times[-1]
        for i in range(1, count):
            # Two points within the rounding allowance of each other would leave a sample time between them to
            # either: refused, as two equal times are.
            if not times[i] - times[i - 1] > 2 * edge:
                raise MotionError(f'points[{i}].time_from_start {float(times[i])!r} s is not after '
                                  f"points[{i - 1}]'s {float(times[i - 1])!r} s (times must strictly increase, by "
                                  f'more than {2 * edge:.3g} s)')
        # Its accelerations may be anything, as the JTC takes them: they shape the last segment only (ddarm's own
        # recorded reference ends on the bang-bang's deceleration), and the arm is at rest after it.
        if velocities[-1] is not None and np.any(velocities[-1] != 0.0):
            raise MotionError(f'points[{count - 1}] (the last) has velocities {velocities[-1].tolist()}: they must be '
                              'zero, the arm is held at the last positions after the motion')
        object.__setattr__(self, 'times', times)
        object.__setattr__(self, 'positions', positions)
        object.__setattr__(self, 'velocities', velocities)
        object.__setattr__(self, 'accelerations', accelerations)
        object.__setattr__(self, 'start', start)
        if start is not None:
            # The JTC's state before the trajectory: at rest, with zeros for each field the first point has.
            times = np.concatenate([[0.0], times])
            positions = np.vstack([start, positions])
            velocities = (None if velocities[0] is None else np.zeros(joints), *velocities)
            accelerations = (None if accelerations[0] is None else np.zeros(joints), *accelerations)
        object.__setattr__(self, '_knot_times', times)
        object.__setattr__(self, '_knot_positions', positions)
        object.__setattr__(self, '_coefficients', _segment_coefficients(times, positions, velocities, accelerations))

    @staticmethod
    def _per_point(name: str, values, count: int, joints: int) -> tuple:
        if values is None:
            return (None,) * count
        if len(values) != count:
            raise MotionError(f'{name} must be given for each of the {count} points (None where a point has none), '
                              f'got {len(values)}')
        arrays = tuple(None if value is None else np.array(value, dtype=float) for value in values)
        for i, array in enumerate(arrays):
            if array is not None and (array.shape != (joints,) or not np.all(np.isfinite(array))):
                raise MotionError(f'points[{i}].{name} must be {joints} finite numbers, got {array.tolist()}')
        return arrays

    # q0 and qf are fresh arrays, as ProgrammedMotion's copies are: a caller may change its copy.
    @property
    def q0(self) -> np.ndarray:
        return self._knot_positions[0].copy()

    @property
    def qf(self) -> np.ndarray:
        return self.positions[-1].copy()

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    @property
    def dof(self) -> int:
        return self.positions.shape[1]

    def sample(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration at times t (shape (..., n) for t of shape (...))."""
        t = np.asarray(t, dtype=float)
        knots = self._knot_times
        edge = _PHASE_EDGE * self.duration
        # The segment that starts at or before t (within the allowance: then it starts at t, τ = 0); -1 before
        # the start, the last knot's index once the motion has played out.
        segment = np.searchsorted(knots, t + edge, side='right') - 1
        moving = (segment >= 0) & (segment < len(knots) - 1)
        index = np.clip(segment, 0, len(knots) - 2)
        tau = t - knots[index]
        tau = np.where(moving & (tau > edge), tau, 0.0)[..., None]
        c = [self._coefficients[index, k] for k in range(_TERMS)]
        # The JTC's generate_powers: τ^k as a running product.
        p = [np.ones_like(tau)]
        for _ in range(1, _TERMS):
            p.append(p[-1] * tau)
        position = p[0] * c[0] + p[1] * c[1] + p[2] * c[2] + p[3] * c[3] + p[4] * c[4] + p[5] * c[5]
        velocity = (p[0] * c[1] + p[1] * 2.0 * c[2] + p[2] * 3.0 * c[3] + p[3] * 4.0 * c[4]
                    + p[4] * 5.0 * c[5])
        acceleration = p[0] * 2.0 * c[2] + p[1] * 6.0 * c[3] + p[2] * 12.0 * c[4] + p[3] * 20.0 * c[5]
        moving = moving[..., None]
        held = np.where((segment < 0)[..., None], self._knot_positions[0], self._knot_positions[-1])
        return (np.where(moving, position, held), np.where(moving, velocity, 0.0),
                np.where(moving, acceleration, 0.0))


def _segment_coefficients(times: np.ndarray, positions: np.ndarray, velocities: tuple,
                          accelerations: tuple) -> np.ndarray:
    """(segments, 6, n): c_k of q(τ) = Σ c_k τ^k on each segment, by the JTC's formulas for its type."""
    joints = positions.shape[1]
    has_velocity = np.array([v is not None for v in velocities])
    has_acceleration = np.array([a is not None for a in accelerations])
    v = np.array([np.zeros(joints) if value is None else value for value in velocities])
    a = np.array([np.zeros(joints) if value is None else value for value in accelerations])
    cubic = has_velocity[:-1] & has_velocity[1:] & ~(has_acceleration[:-1] & has_acceleration[1:])
    quintic = has_velocity[:-1] & has_velocity[1:] & has_acceleration[:-1] & has_acceleration[1:]
    linear = ~(cubic | quintic)
    coefficients = np.zeros((len(times) - 1, _TERMS, joints))
    coefficients[:, 0] = positions[:-1]
    # Each type's formulas on its own segments only: another type's would overflow where this one need not.
    def ends(kind: np.ndarray) -> tuple[np.ndarray, ...]:
        return (positions[:-1][kind], v[:-1][kind], a[:-1][kind], positions[1:][kind], v[1:][kind], a[1:][kind],
                np.diff(times)[kind][:, None])

    start_pos, _, _, end_pos, _, _, T1 = ends(linear)
    coefficients[linear, 1] = (end_pos - start_pos) / T1
    start_pos, start_vel, _, end_pos, end_vel, _, T1 = ends(cubic)
    T2 = T1 * T1
    T3 = T2 * T1
    coefficients[cubic, 1] = start_vel
    coefficients[cubic, 2] = (-3.0 * start_pos + 3.0 * end_pos - 2.0 * start_vel * T1 - end_vel * T1) / T2
    coefficients[cubic, 3] = (2.0 * start_pos - 2.0 * end_pos + start_vel * T1 + end_vel * T1) / T3
    start_pos, start_vel, start_acc, end_pos, end_vel, end_acc, T1 = ends(quintic)
    T2 = T1 * T1
    T3 = T2 * T1
    T4 = T3 * T1
    T5 = T4 * T1
    coefficients[quintic, 1] = start_vel
    coefficients[quintic, 2] = 0.5 * start_acc
    coefficients[quintic, 3] = (-20.0 * start_pos + 20.0 * end_pos - 3.0 * start_acc * T2 + end_acc * T2
                                - 12.0 * start_vel * T1 - 8.0 * end_vel * T1) / (2.0 * T3)
    coefficients[quintic, 4] = (30.0 * start_pos - 30.0 * end_pos + 3.0 * start_acc * T2 - 2.0 * end_acc * T2
                                + 16.0 * start_vel * T1 + 14.0 * end_vel * T1) / (2.0 * T4)
    coefficients[quintic, 5] = (-12.0 * start_pos + 12.0 * end_pos - start_acc * T2 + end_acc * T2
                                - 6.0 * start_vel * T1 - 6.0 * end_vel * T1) / (2.0 * T5)
    return coefficients
