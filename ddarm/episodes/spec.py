"""What defines an episode (EpisodeSpec) and what it needs before it starts (EpisodePlan)."""

from __future__ import annotations

import os
from dataclasses import MISSING, asdict, dataclass, fields, replace
from functools import lru_cache

import numpy as np

from ddarm.control.gains import omega_rule_gains
from ddarm.control.laws import CONTROLLERS, GainError, checked_delay, checked_gains
from ddarm.control.stability import StabilityError, growing_modes, sampled_loop_transition
from ddarm.errors import DdarmError
from ddarm.motion.files import MotionFile, load_motion, motion_of_duration
from ddarm.motion.programmed import (MotionError, ProgrammedMotion, checked_tau, disturbed_start, nominal_torque,
                                     paper_motion_file, paper_torque_limit, sample_count, sample_times)
from ddarm.physics.arm import Arm, ModelError, load_arm, movable_joints
from ddarm.physics.dynamics import Chain, load_chain
from ddarm.physics.mujoco_plant import Robot, RobotError, load_robot
from ddarm.physics.plant import DEFAULT_MAX_POSITION, DEFAULT_SUBSTEPS, PlantError, PlantOptions, checked_mass_scale
from ddarm.samples import DEFAULT_PERIOD, MAX_SAMPLES, PERIOD_RANGE

# T in s, a motion file's too: hours of motion, and T/Δ is computed without overflow at every Δ of PERIOD_RANGE.
MAX_DURATION = 10_000.0


# 'paper': Table 2's 2 x max |P^nom| per joint (spec §7); 'urdf': the plant URDF's <limit effort>.
TORQUE_LIMITS = ('none', 'paper', 'urdf')


# The options of ddarm's own plant, which an MJCF robot does not take.
ROBOT_EXCLUDED = ('mass_scale', 'external_torque', 'viscous_friction', 'coulomb_friction')


class EpisodeError(DdarmError, ValueError):
    """An episode specification that cannot be run."""


def _optional_tuple(values) -> tuple[float, ...] | None:
    return None if values is None else tuple(float(v) for v in values)


@dataclass(frozen=True)
class EpisodeSpec:
    """Everything that defines an episode; its defaults are the spec's (§14; and the user's delay of 1).

    Without kp and kv it is a template: the episode but its gains, which a search, a campaign job or a command that
    chooses the gains starts from; `with_gains` makes the episode. A template is checked for all but its gains, and
    never run.
    """

    controller: str
    kp: tuple[float, ...] | None = None  # K_p diagonal, in the motion's joint order; None: a template
    kv: tuple[float, ...] | None = None  # K_v diagonal, likewise
    trajectory: int = 1  # the paper's motion, when no motion file is given
    duration: float | None = None  # T; None: the motion's own (a bang-bang motion is stretched to T)
    period: float = DEFAULT_PERIOD
    delay: int = 1
    tau: float = 0.0
    torque_limit: str | tuple[float, ...] = 'none'  # 'none', 'paper' (2 x max nominal), 'urdf' or N m per joint
    external_torque: tuple[float, ...] | None = None
    viscous_friction: tuple[float, ...] | None = None
    coulomb_friction: tuple[float, ...] | None = None
    mass_scale: tuple[float, ...] | None = None  # the plant's links against the controller's model
    substeps: int = DEFAULT_SUBSTEPS
    urdf: str | None = None  # the plant's arm; None: the paper's (config/ddarm.urdf)
    model_urdf: str | None = None  # the controller's model of it; None: the plant's URDF
    motion: str | None = None  # a motion file (ddarm.motion.files); None: the paper's trajectory `trajectory`
    mjcf: str | None = None  # the plant is this MuJoCo robot (MJCF, or a URDF MuJoCo compiles); None: ddarm's, on urdf
    mjcf_joints: tuple[str, ...] | None = None  # the MJCF's name of each controlled joint; None: the same names

    def __post_init__(self) -> None:
        duration_field = None  # where T came from, when it is the motion file's
        if self.duration is None:  # read here only: a spec read back from a bag needs no file
            try:
                motion = motion_file(self).motion
            except MotionError as error:
                raise EpisodeError(str(error)) from error
            duration_field = ('its duration' if isinstance(motion, ProgrammedMotion)
                              else "the last point's time_from_start")
            if not motion.duration <= MAX_DURATION:
                instead = ' (or give the episode its own, --duration)' if duration_field == 'its duration' else ''
                raise EpisodeError(f'motion {motion_source(self)}: {duration_field} {motion.duration!r} s is '
                                   f'more than {MAX_DURATION:g} s{instead}')
            object.__setattr__(self, 'duration', float(motion.duration))
        period = checked_period(self.period)
        try:
            checked_duration(self.duration, period)
            sample_count(self.duration, period)
        except (EpisodeError, ValueError) as error:
            if duration_field is None:
                raise EpisodeError(str(error)) from error
            raise EpisodeError(f'motion {motion_source(self)}: {duration_field}, the episode\'s T: {error}') \
                from error
        for name in ('kp', 'kv', 'external_torque', 'viscous_friction', 'coulomb_friction', 'mass_scale'):
            object.__setattr__(self, name, _optional_tuple(getattr(self, name)))
        if not isinstance(self.torque_limit, str):
            object.__setattr__(self, 'torque_limit', _optional_tuple(self.torque_limit))
        elif self.torque_limit not in TORQUE_LIMITS:
            raise EpisodeError(f"torque_limit must be 'none', 'paper', 'urdf' or one number per joint, "
                               f'got {self.torque_limit!r}')
        if self.controller not in CONTROLLERS:
            raise EpisodeError(f'controller must be one of {CONTROLLERS}, got {self.controller!r}')
        if self.mjcf_joints is not None:
            object.__setattr__(self, 'mjcf_joints', tuple(self.mjcf_joints))
            if self.mjcf is None:
                raise EpisodeError('mjcf_joints (--joint-map) names the joints of an MJCF robot: give its mjcf (--mjcf)')
        if self.mjcf is not None:
            # The robot is MuJoCo's: what changes ddarm's own plant does not apply to it.
            given = [name for name in ROBOT_EXCLUDED if getattr(self, name) is not None]
            if given:
                raise EpisodeError(f'{", ".join(given)} change ddarm\'s own plant; with an MJCF robot ({self.mjcf}) '
                                   "the robot is MuJoCo's: give its friction, torques and masses in the MJCF (the "
                                   "law's model friction F̂ is the model URDF's <dynamics>)")
        try:
            checked_tau(self.tau, self.duration)
            checked_delay(self.delay)
        except (GainError, ValueError) as error:
            raise EpisodeError(str(error)) from error

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def is_template(self) -> bool:
        return self.kp is None and self.kv is None

    def with_gains(self, kp, kv) -> EpisodeSpec:
        """The episode of this template (or spec) with these gains."""
        return replace(self, kp=tuple(np.asarray(kp, dtype=float)), kv=tuple(np.asarray(kv, dtype=float)))


# The episode's defaults, by field: what the CLI, campaign files, controller YAMLs and the nodes' parameters
# (ddarm.ros.parameter_schema) default to.
EPISODE_DEFAULTS = {field.name: field.default for field in fields(EpisodeSpec) if field.default is not MISSING}


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def checked_period(period) -> float:
    """Δ in s within PERIOD_RANGE; EpisodeError naming it otherwise."""
    if not (_is_number(period) and PERIOD_RANGE[0] <= period <= PERIOD_RANGE[1]):
        raise EpisodeError(f'the sampling period Δ must be within [{PERIOD_RANGE[0]:g}, {PERIOD_RANGE[1]:g}] s, '
                           f'got {period!r}')
    return float(period)


def checked_duration(duration, period: float) -> float:
    """T in s within [PERIOD_RANGE[0], MAX_DURATION] and at most MAX_SAMPLES periods (a `period` checked_period
    took); EpisodeError naming it otherwise."""
    if not (_is_number(duration) and np.isfinite(duration)):
        raise EpisodeError(f'the duration T must be a finite number of s, got {duration!r}')
    # Compared as a product: T/Δ itself is not formed before it is known to be a bounded count.
    if duration > MAX_SAMPLES * period:
        raise EpisodeError(f'the duration {duration} s at the period {period} s is more than {MAX_SAMPLES} samples')
    if not PERIOD_RANGE[0] <= duration <= MAX_DURATION:
        raise EpisodeError(f'the duration T must be within [{PERIOD_RANGE[0]:g}, {MAX_DURATION:g}] s, '
                           f'got {duration!r}')
    return float(duration)


@dataclass(frozen=True)
class EpisodePlan:
    """What an episode needs before it starts: samples, programmed motion, nominal torque, limits, start."""

    times: np.ndarray
    q_ref: np.ndarray
    v_ref: np.ndarray
    a_ref: np.ndarray
    nominal: np.ndarray
    torque_limit: np.ndarray | None
    q0: np.ndarray
    v0: np.ndarray
    motion: object | None = None  # ProgrammedMotion or WaypointMotion; None for a plan read back from a recording
    warnings: tuple[str, ...] = ()  # the motion against the URDF's position and velocity limits
    joint_names: tuple[str, ...] = ()  # the controlled joints, in the order of every per-joint array
    prismatic: tuple[bool, ...] = ()  # per joint: positions in m (else rad)

    @property
    def k_max(self) -> int:
        return len(self.times) - 1


@lru_cache(maxsize=64)
def _read_motion(path: str, stamp: tuple[int, int]) -> MotionFile:
    with np.errstate(over='ignore', invalid='ignore'):  # a spline beyond floats is refused by name (sampled_motion)
        return load_motion(path)


def read_motion_file(motion: str | None, trajectory: int = 1) -> MotionFile:
    """A motion file (read again when it changes on disk), or with `motion` None the paper's `trajectory`."""
    if motion is None:
        return paper_motion_file(trajectory)
    try:
        status = os.stat(motion)
    except OSError as error:
        raise MotionError(f'motion file {motion}: {error.strerror}') from error
    return _read_motion(motion, (status.st_mtime_ns, status.st_size))


def motion_file(spec: EpisodeSpec) -> MotionFile:
    """The episode's motion file: the user's, or the paper's trajectory."""
    return read_motion_file(spec.motion, spec.trajectory)


def episode_motion(spec: EpisodeSpec):
    """q^d of the episode (`motion_of_duration` of its motion file at T)."""
    return motion_of_duration(motion_file(spec), spec.duration)


def arm_joints(spec: EpisodeSpec) -> tuple[tuple[str, ...], tuple[tuple[str, float], ...]]:
    """The controlled joints, in the motion's (= the URDF's) order, and the locked ones with their positions."""
    motion = motion_file(spec)
    return motion.joint_names, motion.locked


def motion_source(spec: EpisodeSpec) -> str:
    """The episode's motion as messages name it: its file, or the paper's trajectory."""
    return spec.motion or f'trajectory {spec.trajectory}'


def _reduced(load, urdf: str | None, spec: EpisodeSpec, *arguments):
    joints, locked = arm_joints(spec)
    try:
        if spec.motion is None and urdf is not None:
            # The paper's motion names the paper arm's joints: on another arm it would lock the rest at 0 unasked.
            movable = movable_joints(urdf)
            if sorted(movable) != sorted(joints):
                raise EpisodeError(f'URDF {urdf}: give a motion file (--motion) for its joints {list(movable)}; '
                                   f"the paper's trajectory {spec.trajectory} drives the paper arm's {list(joints)}")
        return load(urdf, *arguments, joints, locked)
    except ModelError as error:
        raise EpisodeError(f'{error} (motion {motion_source(spec)})') from error


def model_arm(spec: EpisodeSpec) -> Arm:
    """The controller's model: its URDF reduced to the motion's joints (P^nom, Ĝ, M̂ and the ω rules use it)."""
    return _reduced(load_arm, spec.model_urdf or spec.urdf, spec, None)


def plant_arm(spec: EpisodeSpec) -> Arm:
    """The plant: its URDF reduced to the motion's joints, its links scaled by `mass_scale`."""
    return _reduced(load_arm, spec.urdf, spec, spec.mass_scale)


def plant_chain(spec: EpisodeSpec) -> Chain:
    """The plant's model as the compiled loop reads it (unscaled: the loop scales each member's links)."""
    return _reduced(load_chain, spec.urdf, spec)


def model_chain(spec: EpisodeSpec) -> Chain:
    """The controller's model as the compiled law reads it."""
    return _reduced(load_chain, spec.model_urdf or spec.urdf, spec)


def plan_episode(spec: EpisodeSpec) -> EpisodePlan:
    """The episode's motion (its file's, or the paper's), sampled at j Δ for j = 0 … T/Δ."""
    return plan_motion(spec, episode_motion(spec), sample_times(spec.duration, spec.period))


def plan_motion(spec: EpisodeSpec, motion, times: np.ndarray) -> EpisodePlan:
    """The motion at the sample times, P^nom from the controller's model, limits and the τ-disturbed start."""
    model, plant = model_arm(spec), plant_arm(spec)
    if model.joint_names != plant.joint_names:
        raise EpisodeError(f'the model URDF {model.urdf_path} controls joints {model.joint_names}, the plant URDF '
                           f'{plant.urdf_path} {plant.joint_names}')
    for name, model_kind, plant_kind in zip(model.joint_names, model.prismatic, plant.prismatic):
        if model_kind != plant_kind:
            kinds = {True: 'prismatic', False: 'revolute'}
            raise EpisodeError(f'joint {name!r} is {kinds[bool(plant_kind)]} in the plant URDF {plant.urdf_path} and '
                               f'{kinds[bool(model_kind)]} in the model URDF {model.urdf_path}')
    if motion.dof != model.dof:
        raise EpisodeError(f'the programmed motion has {motion.dof} joints, the URDF {model.dof}')
    if times[-1] < motion.duration * (1 - 1e-9):
        raise EpisodeError(f'motion {spec.motion}: T = {spec.duration!r} s ends before its last point at '
                           f'{motion.duration!r} s: the arm would never be sent to the goal (give --duration of at '
                           'least that, or none)')
    warnings = motion_limit_warnings(plant, motion, spec)
    q_ref, v_ref, a_ref = sampled_motion(motion, times, motion_source(spec), model.joint_names)
    warnings += fast_friction_warnings(plant, motion.q0, v_ref, spec)
    try:
        for arm in (plant, model):
            arm.check_inertia(motion.q0, 'the start of the motion')
    except ModelError as error:
        raise EpisodeError(str(error)) from error
    with np.errstate(all='ignore'):  # a torque beyond floats is refused below, by joint
        nominal = nominal_torque(model, motion, times)
    source = motion_source(spec)
    beyond = ~np.isfinite(nominal)
    if beyond.any():
        at, joint = np.argwhere(beyond)[0]
        raise EpisodeError(f'motion {source}: joint {model.joint_names[joint]!r} needs a nominal torque of '
                           f'{nominal[at, joint]} at t = {times[at]:.6g} s (q̇^d = {v_ref[at, joint]:.6g}, q̈^d = '
                           f'{a_ref[at, joint]:.6g}), not a finite number: the motion asks more than any torque')
    for name, largest in zip(model.joint_names, np.max(np.abs(nominal), axis=0)):
        if not largest > 0:
            raise EpisodeError(f'motion {source}: joint {name!r} neither moves nor carries gravity along the motion '
                               f'(its nominal torque is 0 at every sample), so (3.2) has no torque scale R_i for it '
                               f'(spec §8): lock it (under locked) or move it')
    if spec.torque_limit == 'none':
        limit = None
    elif spec.torque_limit == 'paper':
        limit = paper_torque_limit(nominal)
    elif spec.torque_limit == 'urdf':
        limit = urdf_torque_limit(plant)
    else:
        limit = np.array(spec.torque_limit)
    q0, v0 = disturbed_start(motion, spec.tau)
    return EpisodePlan(times, q_ref, v_ref, a_ref, nominal, limit, q0, v0, motion, tuple(warnings),
                       tuple(model.joint_names), tuple(bool(x) for x in model.prismatic))


def urdf_torque_limit(arm: Arm) -> np.ndarray:
    """Each controlled joint's <limit effort>; refused if a joint has none (or 0, which URDF allows)."""
    for name, effort in zip(arm.joint_names, arm.effort_limit):
        if not (np.isfinite(effort) and effort > 0):
            raise EpisodeError(f'--urdf-limits: joint {name!r} of {arm.urdf_path} has no positive effort limit '
                               f'(effort = {effort}): give --torque-limit instead')
    return arm.effort_limit.copy()


# q^d between the samples: checked this densely over the motion, and at T/2 and T exactly (the bang-bang's peak
# velocity, a waypoint spline's overshoot fall between the samples the episode takes).
LIMIT_CHECK_POINTS = 4001


def sampled_motion(motion, times: np.ndarray, source: str, joint_names) -> tuple[np.ndarray, ...]:
    """(q^d, q̇^d, q̈^d) at `times`, refused naming the joint and the time where one is not a finite number (a
    waypoint's velocity or acceleration too large to spline)."""
    with np.errstate(all='ignore'):  # the refusal below says it, once and by name
        samples = motion.sample(times)
    for symbol, values in zip(('q^d', 'q̇^d', 'q̈^d'), samples):
        bad = ~np.isfinite(values)
        if bad.any():
            at, joint = np.argwhere(bad)[0]
            raise EpisodeError(f'motion {source}: joint {joint_names[joint]!r} has {symbol} = {values[at, joint]} '
                               f'at t = {times[at]:.6g} s, not a finite number: its points\' velocities or '
                               'accelerations are too large to spline')
    return samples


def motion_limit_warnings(arm: Arm, motion, spec: EpisodeSpec) -> list[str]:
    """Refuse a motion whose start, goal or waypoints lie outside the URDF's position limits, or whose q^d leaves
    the plant's divergence bound (spec §12); warn (naming the joint) where q^d between them leaves the position
    limits or q̇^d exceeds the velocity limits."""
    source = motion_source(spec)
    knots = [('start', motion.q0), ('goal', motion.qf)]
    knots += [(f'point {i}', positions) for i, positions in enumerate(getattr(motion, 'positions', ()))]
    for label, positions in knots:
        for name, value, lower, upper in zip(arm.joint_names, positions, arm.lower, arm.upper):
            if not lower <= value <= upper:
                raise EpisodeError(f'motion {source}: {label} of joint {name!r} is {float(value)!r}, outside its '
                                   f'URDF limits [{float(lower)}, {float(upper)}] ({arm.urdf_path})')
    times = np.linspace(0.0, motion.duration, LIMIT_CHECK_POINTS)
    q_ref, v_ref, a_ref = sampled_motion(motion, times, source, arm.joint_names)
    for i, name in enumerate(arm.joint_names):
        beyond = np.abs(q_ref[:, i]) > DEFAULT_MAX_POSITION
        if beyond.any():
            at = int(np.argmax(beyond))
            raise EpisodeError(f'motion {source}: joint {name!r} reaches q^d = {float(q_ref[at, i])!r} at t = '
                               f'{times[at]:.6g} s, beyond the plant\'s divergence bound ±{DEFAULT_MAX_POSITION:g} '
                               f'(spec §12): an episode there would end as diverged')
    warnings = []
    for i, name in enumerate(arm.joint_names):
        outside = (q_ref[:, i] < arm.lower[i]) | (q_ref[:, i] > arm.upper[i])
        if outside.any():
            at = int(np.argmax(outside))
            warnings.append(f'motion {source}: joint {name!r} leaves its position limits [{arm.lower[i]}, '
                            f'{arm.upper[i]}] at t = {times[at]:.6g} s (q^d = {q_ref[at, i]:.6g})')
        fastest = int(np.argmax(np.abs(v_ref[:, i])))
        if abs(v_ref[fastest, i]) > arm.velocity_limit[i]:
            warnings.append(f'motion {source}: joint {name!r} moves at {abs(v_ref[fastest, i]):.6g} at t = '
                            f'{times[fastest]:.6g} s, beyond its URDF velocity limit {arm.velocity_limit[i]:.6g}')
    return warnings


def fast_friction_warnings(plant: Arm, q0: np.ndarray, v_ref: np.ndarray, spec: EpisodeSpec) -> list[str]:
    """A warning per joint whose friction acts within one sampling period: its viscous damping B stops it in less
    than Δ (M_ii / B < Δ), or its Coulomb friction C stops its fastest programmed motion in less than Δ (M_ii
    max |q̇^d| / C < Δ), M_ii the plant's at the start. Such a joint follows its friction, not the sampled law: the
    law's friction model F̂, computed once per period from a delayed state, can drive it into a limit cycle, and the
    plant's RK4 steps resolve it coarsely, so that its indices change with --substeps."""
    try:  # checked here first: this runs before check_episode checks the plant's options
        given = PlantOptions(viscous_friction=spec.viscous_friction,
                             coulomb_friction=spec.coulomb_friction).checked(plant.dof)
    except PlantError as error:
        raise EpisodeError(str(error)) from error
    viscous, coulomb = plant_chain(spec).joint_friction(given.viscous_friction, given.coulomb_friction)
    inertia = np.diag(plant.mass_matrix(q0))
    fastest = np.max(np.abs(v_ref), axis=0)
    warnings = []
    for i, name in enumerate(plant.joint_names):
        fast = []
        if inertia[i] < viscous[i] * spec.period:
            fast.append(f'its damping {viscous[i]:.6g} in {inertia[i] / viscous[i]:.3g} s')
        if inertia[i] * fastest[i] < coulomb[i] * spec.period:
            fast.append(f'its Coulomb friction {coulomb[i]:.6g} from {fastest[i]:.3g} in '
                        f'{inertia[i] * fastest[i] / coulomb[i]:.3g} s')
        if fast:
            warnings.append(f"joint {name!r} (M_ii = {inertia[i]:.3g} at the start) is stopped by "
                            f"{' and by '.join(fast)}, within one sampling period Δ = {spec.period:g} s: it follows "
                            'its friction, not the sampled law, which may drive it into a limit cycle, and its '
                            'indices change with --substeps')
    return warnings


def gains_from_omega(spec: EpisodeSpec, omega: float) -> tuple[np.ndarray, np.ndarray]:
    """The ω rule of section 2 for the spec's controller; PD + gravity takes m_ii of the model at q_f."""
    if not (np.isfinite(omega) and omega > 0):
        raise EpisodeError(f'omega must be finite and positive, got {omega!r}')
    try:
        with np.errstate(over='ignore', under='ignore'):  # gains beyond floats are refused below, naming ω
            kp, kv = omega_rule_gains(spec.controller, model_arm(spec), omega, episode_motion(spec).qf)
    except GainError as error:
        raise EpisodeError(str(error)) from error
    if not (np.all(np.isfinite(kp) & (kp > 0)) and np.all(np.isfinite(kv) & (kv > 0))):
        raise EpisodeError(f'omega = {omega!r} gives the ω rule gains kp = {np.asarray(kp).tolist()}, '
                           f'kv = {np.asarray(kv).tolist()}: not all finite and positive')
    return kp, kv


# The step of the central differences of G(q): their error, ~h² times G's third derivative, is far below what
# moves the loop's roots.
GRAVITY_STEP = 1e-6
# A joint whose part in a growing mode is at least this share of the largest joint's is named in the warning.
NAMED_SHARE = 0.5


def gravity_stiffness(arm: Arm, q: np.ndarray) -> np.ndarray:
    """∂G/∂q at q, by central differences of G."""
    columns = []
    for i in range(arm.dof):
        step = np.zeros(arm.dof)
        step[i] = GRAVITY_STEP
        columns.append((arm.gravity(q + step) - arm.gravity(q - step)) / (2 * GRAVITY_STEP))
    return np.array(columns).T


def loop_feedback(spec: EpisodeSpec, model: Arm, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F_p, F_v) of the law linearised at rest at q: u = -(F_p x + F_v ẋ) at the measured sample, x = q - q^d.

    PD + gravity (2.1): K_p, K_v (its Ĝ(q^d) is a feedforward). Computed torque (2.6): M̂(q) K_p - ∂Ĝ/∂q and
    M̂(q) K_v - B̂, its model's gravity and viscous friction (its URDF's and the plant's beyond it, spec §5) taken at the
    measured state.
    """
    kp, kv = np.diag(spec.kp), np.diag(spec.kv)
    if spec.controller == 'pd_gravity':
        return kp, kv
    mass = model.mass_matrix(q)
    friction = np.diag(model_chain(spec).joint_friction(spec.viscous_friction)[0])
    return mass @ kp - gravity_stiffness(model, q), mass @ kv - friction


def loop_stability_warnings(spec: EpisodeSpec, subject: str = 'the gains') -> list[str]:
    """A warning, naming the joints, when the spec's gains lie beyond the stability boundary of its sampled loop
    linearised at rest at the motion's start q_0 or goal q_f: the plant's full M(q) (armature too), ∂G/∂q and viscous
    friction, the law's feedback (loop_feedback), Δ and the delay. The ω rules' boundary treats each joint alone; on
    a coupled arm this is where the loop the plant has stops being stable, whatever rule chose the gains."""
    plant, model = plant_arm(spec), model_arm(spec)
    motion = episode_motion(spec)
    damping = np.diag(plant_chain(spec).joint_friction(spec.viscous_friction)[0])
    growing, share = [], np.zeros(plant.dof)
    for label, q in (('start q_0', motion.q0), ('goal q_f', motion.qf)):
        try:
            # Gains beyond floating point overflow here; sampled_loop_transition refuses the loop they make.
            with np.errstate(over='ignore', invalid='ignore'):
                feedback = loop_feedback(spec, model, q)
            transition = sampled_loop_transition(plant.mass_matrix(q), gravity_stiffness(plant, q), damping,
                                                 *feedback, spec.period, spec.delay)
            radius, joints = growing_modes(transition, plant.dof)
        except StabilityError as error:
            return [f'the stability of {subject} was not checked: {error}']
        if joints.any():
            growing.append(f'{radius:.6g} at the {label}')
            share = np.maximum(share, joints)
    if not growing:
        return []
    named = [plant.joint_names[i] for i in np.argsort(-share, kind='stable') if share[i] >= NAMED_SHARE]
    return [f"{subject} lie beyond the stability boundary of the sampled loop (Δ = {spec.period:g} s, delay "
            f"{spec.delay}) linearised at rest with the arm's M(q) and ∂G/∂q: its spectral radius is "
            f"{' and '.join(growing)}, above 1; its growing modes move mostly {', '.join(named)}, whose errors "
            'grow while the arm is near there (lower the gains, Δ or the delay)']


def plant_options(spec: EpisodeSpec, plan: EpisodePlan, dof: int) -> PlantOptions:
    """The plant options `spec` runs with (its torque limit resolved by `plan`), checked for a `dof`-joint arm."""
    return PlantOptions(period=spec.period, substeps=spec.substeps, torque_limit=plan.torque_limit,
                        viscous_friction=spec.viscous_friction, coulomb_friction=spec.coulomb_friction,
                        external_torque=spec.external_torque).checked(dof)


def check_episode(spec: EpisodeSpec) -> EpisodePlan:
    """Plan `spec` and check everything a run would refuse (gains, per-joint options), before any work starts; a
    template's all but its gains."""
    plan = plan_episode(spec)
    dof = plan.q_ref.shape[1]
    try:
        if not spec.is_template:
            checked_gains(spec.kp, spec.kv, dof)
        plant_options(spec, plan, dof)
        if spec.mass_scale is not None:
            checked_mass_scale(spec.mass_scale, dof)
        if spec.mjcf is not None:
            episode_robot(spec, plan)
    except (GainError, PlantError, ModelError, RobotError) as error:
        raise EpisodeError(str(error)) from error
    return plan


def episode_robot(spec: EpisodeSpec, plan: EpisodePlan) -> Robot:
    """The MJCF robot `spec` runs on (load_robot, checked against the plan's joints and the period)."""
    if spec.mjcf_joints is not None and len(spec.mjcf_joints) != len(plan.joint_names):
        raise RobotError(f'mjcf_joints (--joint-map) names {len(spec.mjcf_joints)} joints; the motion controls '
                         f'{len(plan.joint_names)}: {list(plan.joint_names)}')
    joint_map = None if spec.mjcf_joints is None else dict(zip(plan.joint_names, spec.mjcf_joints))
    return load_robot(spec.mjcf, plan.joint_names, plan.prismatic, spec.period, joint_map)
