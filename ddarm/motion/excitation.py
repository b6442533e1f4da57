"""Excitation motions for identification: a finite Fourier series per joint whose regressor is well conditioned.

The motion of Swevers, Ganseman, Tükel, De Schutter and Van Brussel, "Optimal robot excitation and identification"
(IEEE T-RA 13(5), 1997), eq. (10): with ω = 2π/T and L harmonics,

    q_i(t) = q0_i + Σ_l [a_il/(ω l) sin(ω l t) − b_il/(ω l) cos(ω l t)] + offset_i,

its coefficients chosen to minimise the condition number of the base regressor (ddarm.physics.regressor) at
SAMPLES instants, within the URDF's limits less a margin at a dense set of instants. It is written as a waypoint
motion file (ddarm.motion.files) through points of the series with their velocities and accelerations, which
the JTC's quintic spline follows within SPLINE_TOLERANCE: every command plays it, and records it as any episode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize

from ddarm.motion.files import MotionFile, flow_names, flow_numbers, parse_motion
from ddarm.motion.programmed import MotionError
from ddarm.motion.waypoints import MAX_POINTS
from ddarm.physics.arm import Arm
from ddarm.physics.regressor import base_columns, condition_number, stacked_regressor
from ddarm.reporting.text import visible

# Of each joint's position range, kept free at both ends; the velocity and effort limits' share the motion may use.
# Both leave room for what happens between the instants the limits are checked at, and for the tracking error of
# the controller that plays the motion (its torques are the nominal ones plus its feedback).
POSITION_MARGIN = 0.05
LIMIT_SHARE = 0.8
# The instants the condition number is taken at, (k + 1/2) T / SAMPLES: none at t = 0 or T, where q̇ = 0 and
# the Coulomb columns sign(q̇) are 0.
SAMPLES = 200
# The limits are checked at this many instants per period of the highest harmonic (T/L): a sinusoid of that period
# peaks at most 1 − cos(π/20) = 1.2 % above its largest sample, well inside the margins above.
DENSE_PER_PERIOD = 20
# The waypoints per period of the highest harmonic, at least: the quintic between two points misses a harmonic of
# amplitude A by at most A (2π/16)^6 / 46080 = 8e-8 A (Hermite interpolation's error bound), below SPLINE_TOLERANCE.
POINTS_PER_PERIOD = 16
SPLINE_TOLERANCE = 1e-6  # rad (m): how far the written spline may be from the series
# The random start fills this share of each joint's position and velocity room, leaving the search room to move.
START_FILL = 0.5
# SLSQP's iterations: bounded by count, not by the clock, so that a seed gives the same motion on any machine
# (a few seconds for the Panda's 7 joints and 5 harmonics).
MAX_ITERATIONS = 20
# The largest condition number accepted. The least-squares estimate's relative error is at most the condition
# number times the torques' relative error (noise, friction that is not Coulomb's): beyond 1000, a 0.1 % torque
# error may be the whole of a parameter. Optimised motions of the Panda and the UR5 reach well below it.
CONDITION_BOUND = 1000.0
# The sharpness of the smooth maximum the search bounds each joint's torque by (torque_kept).
_RHO = 200.0
_NO_EXCITATION = 'lengthen --duration, lower --harmonics or give --start inside the limits less their margin'


@dataclass(frozen=True)
class FourierSeries:
    """Swevers' eq. (10) per joint: q0 (n,), a and b (L, n) (rad/s, m/s), over T = `duration`."""

    q0: np.ndarray
    a: np.ndarray
    b: np.ndarray
    duration: float

    @property
    def harmonics(self) -> np.ndarray:
        return np.arange(1, len(self.a) + 1)

    def sample(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ at times t (each (len(t), n)), in closed form."""
        omega_l = 2 * math.pi / self.duration * self.harmonics
        phase = np.outer(np.asarray(t, dtype=float), omega_l)
        sin, cos = np.sin(phase), np.cos(phase)
        offset = np.sum(self.b / omega_l[:, None], axis=0)  # q(0) = q0
        q = self.q0 + offset + sin @ (self.a / omega_l[:, None]) - cos @ (self.b / omega_l[:, None])
        return q, cos @ self.a + sin @ self.b, cos @ (self.b * omega_l[:, None]) - sin @ (self.a * omega_l[:, None])


@dataclass(frozen=True)
class Excitation:
    """An excitation motion file's text and what it was made from; `condition` is its spline's, `start_condition`
    the seeded random start's (before the search), `base` the base parameters of `parameters`."""

    text: str
    file: MotionFile
    condition: float
    start_condition: float
    base: int
    parameters: int


def sample_instants(duration: float, count: int = SAMPLES) -> np.ndarray:
    """The instants the condition number is taken at: (k + 1/2) T / count."""
    return (np.arange(count) + 0.5) * duration / count


def nominal_torque(arm: Arm, q, v, a) -> np.ndarray:
    """τ = M(q) q̈ + V(q, q̇) + G(q) (armature included) + damping q̇ + friction sign(q̇), per row of q, q̇, q̈.
    """
    rigid = np.array([arm.inverse_dynamics(*sample) for sample in zip(q, v, a)])
    return rigid + np.asarray(arm.model.damping) * v + np.asarray(arm.model.friction) * np.sign(v)


def base_condition(arm: Arm, q, v, a) -> tuple[float, int, int]:
    """The condition number of the base regressor at samples q, q̇, q̈, its base parameters and all of them."""
    stacked = stacked_regressor(arm, q, v, a)
    columns = base_columns(stacked)
    return condition_number(stacked, columns), len(columns), stacked.shape[1]


class _Limits:
    """The motion's bounds: q within the URDF's position limits less `margin` of their range, |q̇| and |τ| within
    `share` of the velocity and effort limits."""

    def __init__(self, arm: Arm, share: float = LIMIT_SHARE, margin: float = POSITION_MARGIN) -> None:
        self.joint_names = arm.joint_names
        span = np.where(np.isfinite(arm.upper - arm.lower), arm.upper - arm.lower, 0.0)
        self.lower = arm.lower + margin * span  # ±inf stays so for a continuous joint
        self.upper = arm.upper - margin * span
        self.velocity = share * arm.velocity_limit
        self.effort = share * arm.effort_limit

    def usage(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """(instants, 3, n): the share of each bound used, signed, ±1 at it (position about the middle of its
        interval, velocity, torque); 0 where there is no bound."""
        bounded = np.isfinite(self.upper - self.lower)
        middle = np.where(bounded, (self.lower + self.upper) / 2, 0.0)
        half = np.where(bounded, (self.upper - self.lower) / 2, np.inf)
        return np.stack([(q - middle) / half, v / self.velocity, tau / self.effort], axis=1)

    def problem(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, times: np.ndarray, level: float = 1.0
                ) -> str | None:
        """The first bound (each shrunk to `level` of itself about its middle) q, q̇, τ pass at `times` (rows),
        named; None if they keep every one."""
        outside = np.abs(self.usage(q, v, tau)) > level
        if not outside.any():
            return None
        k, kind, i = np.argwhere(outside)[0]
        middle, half = (self.lower[i] + self.upper[i]) / 2, (self.upper[i] - self.lower[i]) / 2
        name, values, low, high, unit = (('position', q, middle - level * half, middle + level * half, 'rad (m)'),
                                         ('velocity', v, -level * self.velocity[i], level * self.velocity[i],
                                          'rad/s (m/s)'),
                                         ('nominal torque', tau, -level * self.effort[i], level * self.effort[i],
                                          'N m (N)'))[kind]
        return (f'the {name} of {self.joint_names[i]} at t = {times[k]:.4g} s, {values[k, i]:.6g} {unit}, is outside '
                f'[{low:.6g}, {high:.6g}]')


def _centre(arm: Arm, start) -> np.ndarray:
    """q0: `start` if given (within the limits), else the middle of each joint's limits (0 for a continuous one)."""
    names = arm.joint_names
    if start is None:
        return np.where(np.isfinite(arm.upper - arm.lower), (arm.lower + arm.upper) / 2, 0.0)
    q0 = np.asarray(start, dtype=float)
    if q0.shape != (arm.dof,):
        raise MotionError(f'--start gives {q0.size} positions for the {arm.dof} joints {names}')
    for name, value, low, high in zip(names, q0, arm.lower, arm.upper):
        if not low <= value <= high:
            raise MotionError(f'--start: {name} at {float(value)!r} is outside its limits [{float(low)!r}, '
                              f'{float(high)!r}]')
    return q0


def _null_space_bases(harmonics: int) -> tuple[np.ndarray, np.ndarray]:
    """Bases (L, L − 1) of the a and b with Σ_l a_l = 0 and Σ_l l b_l = 0: then q̇ = q̈ = 0 at t = 0 and T. These
    two linear conditions, rather than a window over the series, keep it a sum of L harmonics, which the search
    shapes and which the spline follows; and the offset puts q(0) = q(T) at q0."""
    ones, weights = np.ones((1, harmonics)), np.arange(1.0, harmonics + 1)[None, :]
    return scipy.linalg.null_space(ones), scipy.linalg.null_space(weights)


def optimised_series(arm: Arm, duration: float, harmonics: int, seed: int, start=None
                     ) -> tuple[FourierSeries, FourierSeries]:
    """The series that minimises the base regressor's condition number within the limits (Swevers' eq. (10) and
    (13)), and the seeded random start it was searched from. MotionError if none keeps the limits."""
    for name, limit, low, high in zip(arm.joint_names, arm.velocity_limit, arm.lower, arm.upper):
        if not (math.isfinite(limit) and limit > 0):
            raise MotionError(f'joint {name} has velocity limit {float(limit)!r} in URDF {arm.urdf_path}: an '
                              'excitation needs a positive one to bound its amplitude')
        if not low < high:
            raise MotionError(f'joint {name} has position limits [{float(low)!r}, {float(high)!r}] in URDF '
                              f'{arm.urdf_path}: it cannot move, lock it')
    q0 = _centre(arm, start)
    limits = _Limits(arm)
    n, count = arm.dof, harmonics - 1
    basis_a, basis_b = _null_space_bases(harmonics)
    dense = _dense_instants(duration, harmonics)
    rest = np.zeros((1, n))
    # The search's smooth maximum of the torque (torque_kept) exceeds a usage constant over the instants by
    # ln(instants)/ρ: at rest at q0, the usage must leave that room for the search to start within its bounds.
    level = 1 - math.log(len(dense)) / _RHO
    if (problem := limits.problem(q0[None, :], rest, nominal_torque(arm, q0[None, :], rest, rest), rest[0], level)):
        raise MotionError(f'no excitation within the limits found ({problem}): {_NO_EXCITATION}')
    room = np.minimum(q0 - limits.lower, limits.upper - q0)
    if np.any(room <= 0):
        i = int(np.argmax(room <= 0))
        raise MotionError(f'no excitation within the limits found ({arm.joint_names[i]} starts at {float(q0[i])!r}, '
                          f'the edge of [{limits.lower[i]:.6g}, {limits.upper[i]:.6g}], its limits less the margin): '
                          f'{_NO_EXCITATION}')

    def series(x: np.ndarray) -> FourierSeries:
        x = x.reshape(2, count, n)
        return FourierSeries(q0, basis_a @ x[0], basis_b @ x[1], duration)

    # q − q0 and q̇ are linear in x, and so are their bounds' rows 1 ∓ usage ≥ 0, one per instant: SLSQP takes
    # them with their constant Jacobian (found by unit steps) and steps within them.
    def motion_rows(x: np.ndarray) -> np.ndarray:
        q, v, _ = series(x).sample(dense)
        used = limits.usage(q, v, np.zeros_like(q))[:, :2]
        return np.concatenate([1 - used, 1 + used]).ravel()

    rest_rows = motion_rows(np.zeros(2 * count * n))
    motion_jacobian = np.column_stack([motion_rows(unit) - rest_rows for unit in np.eye(2 * count * n)])

    def torque_kept(x: np.ndarray) -> np.ndarray:
        # 1 − the Kreisselmeier-Steinhauser function of each joint's torque usage over the instants, a smooth upper
        # bound of the largest (by at most ln(instants)/ρ here): n constraints, where one per instant made SLSQP's
        # subproblem the slowest part of the search.
        q, v, a = series(x).sample(dense)
        used = limits.usage(q, v, nominal_torque(arm, q, v, a))[:, 2]
        signed = np.concatenate([used, -used])
        top = signed.max(axis=0)
        return 1 - top - np.log(np.sum(np.exp(_RHO * (signed - top)), axis=0)) / _RHO

    def kept(x: np.ndarray) -> bool:
        return bool(np.all(rest_rows + motion_jacobian @ x >= 0) and np.all(torque_kept(x) >= 0))

    rng = np.random.default_rng(seed)
    x = rng.standard_normal(2 * count * n)
    q, v, _ = series(x).sample(dense)
    used = np.maximum(np.max(np.abs(q - q0), axis=0) / room, np.max(np.abs(v), axis=0) / limits.velocity)
    x = (x.reshape(2, count, n) * (START_FILL / used)).ravel()
    # Slower is closer to the torque at rest, within the search's bounds (checked above).
    while not kept(x):
        x = x / 2
    start_series = series(x)
    samples = sample_instants(duration)
    columns = base_columns(stacked_regressor(arm, *start_series.sample(samples)))

    def log_condition(x: np.ndarray) -> float:
        # The condition number of the base columns, each scaled to unit norm, is √(λmax/λmin) of their normalised
        # Gram matrix: a 63 × 63 eigenproblem where condition_number's SVD takes a 1400 × 63 one. The columns are
        # the start's: fixed, so that the objective is smooth; the printed number is condition_number's.
        base = stacked_regressor(arm, *series(x).sample(samples))[:, columns]
        gram = base.T @ base
        norms = np.sqrt(np.diag(gram))
        eigenvalues = np.linalg.eigvalsh(gram / np.outer(norms, norms))
        return 0.5 * math.log(eigenvalues[-1] / max(eigenvalues[0], 1e-16 * eigenvalues[-1]))

    # SLSQP ends where its tolerance allows, possibly a hair outside a bound: the motion kept is the best iterate
    # that keeps every bound at every instant (the start does).
    best = [log_condition(x), x]

    def keep_best(xk: np.ndarray) -> None:
        if kept(xk) and (value := log_condition(xk)) < best[0]:
            best[:] = [value, xk.copy()]

    result = scipy.optimize.minimize(log_condition, x, method='SLSQP', callback=keep_best,
                                     constraints=[{'type': 'ineq', 'fun': lambda x: rest_rows + motion_jacobian @ x,
                                                   'jac': lambda x: motion_jacobian},
                                                  {'type': 'ineq', 'fun': torque_kept}],
                                     options={'maxiter': MAX_ITERATIONS})
    keep_best(result.x)
    return series(best[1]), start_series


def _dense_instants(duration: float, harmonics: int) -> np.ndarray:
    return np.linspace(0.0, duration, DENSE_PER_PERIOD * harmonics + 1)


def excitation_motion(arm: Arm, duration: float, harmonics: int, seed: int, start=None, point_period: float = 0.02,
                      locked: dict[str, float] | None = None, command: str = '', source: str = '<excitation>'
                      ) -> Excitation:
    """The excitation motion file of `arm`'s controlled joints over T = `duration`, checked: its spline follows the
    series within SPLINE_TOLERANCE and keeps the URDF's limits, and its base regressor's condition number is at most
    CONDITION_BOUND. `locked`: the URDF's other movable joints' positions written (as the arm was loaded with);
    `command` is recorded in the file's comments; `source` names the file in refusals."""
    if not (math.isfinite(duration) and duration > 0):
        raise MotionError(f'--duration must be a positive number of seconds, got {duration!r}')
    if not (math.isfinite(point_period) and point_period > 0):
        raise MotionError(f'--point-period must be a positive number of seconds, got {point_period!r}')
    # Points every point_period or a little less, the last at T.
    points = math.ceil(duration / point_period * (1 - 1e-12))
    if points > MAX_POINTS:
        raise MotionError(f'--duration {duration!r} s at --point-period {point_period!r} s is {points} points, more '
                          f'than the {MAX_POINTS} a motion file may have: lengthen --point-period')
    if points < POINTS_PER_PERIOD * harmonics:
        raise MotionError(f'--point-period {point_period!r} s leaves {points / harmonics:.3g} points per period of '
                          f'the highest harmonic (T/L = {duration / harmonics:.4g} s), fewer than the '
                          f'{POINTS_PER_PERIOD} the spline needs to follow the series: lower --point-period or '
                          '--harmonics, or lengthen --duration')
    series, start_series = optimised_series(arm, duration, harmonics, seed, start)
    dense = _dense_instants(duration, harmonics)
    q, v, a = series.sample(dense)
    limits = _Limits(arm)
    if (problem := limits.problem(q, v, nominal_torque(arm, q, v, a), dense)) is not None:
        raise MotionError(f'no excitation within the limits found ({problem}): {_NO_EXCITATION}')
    times = np.arange(1, points + 1) * (duration / points)
    q, v, a = series.sample(times)
    # The series is at q0 and at rest at T exactly; sin(2π l) and cos(2π l) would leave rounding's 1e-16 off.
    q[-1], v[-1], a[-1] = series.q0, 0.0, 0.0
    body = [f'joint_names: {flow_names(arm.joint_names)}', f'start: {flow_numbers(series.q0)}', 'points:']
    for k in range(points):
        body += [f'  - positions: {flow_numbers(q[k])}', f'    velocities: {flow_numbers(v[k])}',
                 f'    accelerations: {flow_numbers(a[k])}', f'    time_from_start: {float(times[k])!r}']
    body.append('locked: {' + ', '.join(f'{flow_names([name])[1:-1]}: {float(value)!r}'
                                        for name, value in (locked or {}).items()) + '}')
    written = parse_motion('\n'.join(body) + '\n', source)
    _check_spline(arm, series, written, np.union1d(dense, (times[1:] + times[:-1]) / 2))
    condition, base, parameters = base_condition(arm, *written.motion.sample(sample_instants(duration)))
    start_condition = base_condition(arm, *start_series.sample(sample_instants(duration)))[0]
    if not condition <= CONDITION_BOUND:
        raise MotionError(f'the motion excites the parameters poorly (condition number {condition:.6g} > '
                          f'{CONDITION_BOUND:g}): raise --harmonics or --duration, or move more joints')
    header = [f'# An excitation motion for identification, made by: {visible(command)}',
              f'# A finite Fourier series per joint (Swevers et al. 1997, eq. (10)): T = {duration!r} s, L = '
              f'{harmonics} harmonics, seed {seed}, around q0 = start; points every {duration / points!r} s with the '
              "series' velocities and accelerations (the spline follows it within 1e-6 rad).",
              f'# Condition number of the base regressor: {condition!r} ({base} base parameters of {parameters}; '
              f'samples {SAMPLES} at (k + 1/2) T/{SAMPLES}); at the seeded random start: {start_condition!r}.',
              f'# Within the URDF limits less {POSITION_MARGIN:.0%} of each position range, {LIMIT_SHARE:.0%} of the '
              f'velocity and effort limits (nominal torque).']
    text = '\n'.join(header + body) + '\n'
    file = parse_motion(text, source)
    # The header is comments only (visible() keeps each on one line): a name or a path in it must not become YAML.
    if (file.joint_names, file.locked) != (written.joint_names, written.locked) or not all(
            np.array_equal(ours, theirs)
            for ours, theirs in zip(file.motion.sample(times), written.motion.sample(times))):
        raise MotionError(f'{source}: the file with its comments reads as another motion than without (a bug)')
    return Excitation(text, file, condition, start_condition, base, parameters)


def _check_spline(arm: Arm, series: FourierSeries, written: MotionFile, times: np.ndarray) -> None:
    """Refuse (a bug) a written motion whose spline strays from the series or passes the URDF's limits at `times`."""
    q, v, a = written.motion.sample(times)
    error = np.abs(q - series.sample(times)[0])
    if error.max() > SPLINE_TOLERANCE:
        k, i = np.unravel_index(np.argmax(error), error.shape)
        raise MotionError(f'the written spline is {error[k, i]:.3g} rad (m) from the Fourier series at t = '
                          f'{times[k]:.6g} s for {arm.joint_names[i]}, more than {SPLINE_TOLERANCE:g} (a bug)')
    if (problem := _Limits(arm, 1.0, 0.0).problem(q, v, nominal_torque(arm, q, v, a), times)) is not None:
        raise MotionError(f'the written spline passes a limit: {problem} (a bug)')
