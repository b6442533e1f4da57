"""MuJoCo as the plant: a robot ddarm did not write, behind the same calls as ddarm's own plant.

MuJoCo (an independent engine: its own integrators, joint armature, damping, frictionloss, joint limits and force
ranges) integrates the robot from an MJCF file, or from a URDF it compiles. `MujocoPlant` holds a torque over one
sampling period (zero-order hold: the torque set once, then the period's whole number of MuJoCo timesteps) and
returns the sampled state, as `ddarm.physics.plant.Plant` does, so that the episode's loop, delay and indices are
the ones every other episode runs. `mujoco` is imported here only, when a robot file is given.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddarm.datafiles import MAX_FILE_BYTES, regular_file_problem
from ddarm.errors import DdarmError
from ddarm.interrupts import check_stop
from ddarm.physics.plant import DEFAULT_MAX_POSITION, DEFAULT_MAX_VELOCITY, beyond_bounds, saturate

INSTALL_HINT = "MuJoCo is not installed: pip install 'ddarm[mujoco]'"
# The actuator group (MuJoCo has 31) a servo is moved to and that group switched off (opt.disableactuator).
BYPASSED_GROUP = 30
# A period is a whole number of MuJoCo timesteps when it is within this fraction of one of that count.
WHOLE_STEPS_TOLERANCE = 1e-9
# The most MuJoCo timesteps one sampling period may take: beyond it the timestep is not meant for this period.
MAX_STEPS_PER_PERIOD = 100_000


class RobotError(DdarmError, ValueError):
    """A robot file (MJCF) ddarm cannot run as the plant, or an input it refuses."""


def import_mujoco():
    """The mujoco module, or RobotError saying how to install it."""
    try:
        import mujoco
    except ImportError:
        # A stop (Ctrl-C, SIGTERM) that lands in mujoco's C initialisation comes out of it as an ImportError
        # ('initialization failed'): that is the stop, not a missing MuJoCo (a node stopped as it configured said so).
        check_stop()
        raise RobotError(INSTALL_HINT) from None
    return mujoco


@dataclass(frozen=True)
class Actuation:
    """How a torque reaches each joint, as arrays over the joints: through a motor actuator (`actuator` >= 0;
    MuJoCo applies gear · gain · ctrl, ctrl within its ctrlrange, gain · ctrl within its forcerange) or, without one
    (`actuator` -1: gear and gain 1, no control or force range), as MuJoCo's applied joint force. Either way the
    joint's actuatorfrcrange bounds it, as MuJoCo bounds its actuators' force at the joint. Unbounded: ±inf."""

    actuator: np.ndarray
    gear: np.ndarray
    gain: np.ndarray
    ctrl_range: np.ndarray  # (n, 2)
    force_range: np.ndarray
    joint_range: np.ndarray

    def applied(self, torque: np.ndarray) -> np.ndarray:
        """The joint torques MuJoCo applies when asked for `torque`: each of its bounds, in MuJoCo's order."""
        control = np.clip(torque / (self.gear * self.gain), self.ctrl_range[:, 0], self.ctrl_range[:, 1])
        force = np.clip(self.gain * control, self.force_range[:, 0], self.force_range[:, 1])
        return np.clip(self.gear * force, self.joint_range[:, 0], self.joint_range[:, 1])

    def control(self, torque: np.ndarray) -> np.ndarray:
        """The actuators' ctrl that applies `torque` (one `applied` returned: within every bound)."""
        return torque / (self.gear * self.gain)


def _range(limited, bounds) -> tuple[float, float]:
    return (float(bounds[0]), float(bounds[1])) if bool(limited) else (-math.inf, math.inf)


@dataclass(frozen=True)
class Robot:
    """A MuJoCo model checked to be the episode's arm: its joints, by name, are exactly the controlled joints."""

    path: Path
    model: object  # mujoco.MjModel
    joint_names: tuple[str, ...]  # ddarm's order; MuJoCo's joint of each given by its own name through `joint_map`
    qpos_address: np.ndarray
    dof_address: np.ndarray
    actuation: Actuation
    steps_per_period: int
    period: float
    bypassed: tuple[str, ...] = ()  # the servos switched off (torques are applied as joint forces instead)

    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def integrator(self) -> str:
        mujoco = import_mujoco()
        return mujoco.mjtIntegrator(self.model.opt.integrator).name.removeprefix('mjINT_').lower()

    def description(self) -> dict:
        """What the JSON says of the robot: its file, engine, timestep, integrator and how torques reach it."""
        mujoco = import_mujoco()
        return {'mjcf': str(self.path), 'engine': f'MuJoCo {mujoco.mj_versionString()}', 'timestep': self.timestep,
                'integrator': self.integrator, 'steps_per_period': self.steps_per_period,
                'torque_through': self._torque_through(), 'bypassed_actuators': list(self.bypassed),
                'joint_map': {name: self.model.joint(int(index)).name for name, index in
                              zip(self.joint_names, self._joint_ids())}}

    def warnings(self) -> list[str]:
        """What the robot was changed in to run the episode: its servos switched off, said once."""
        if not self.bypassed:
            return []
        return [f'the MJCF {self.path} has servo actuators {list(self.bypassed)} (not torque motors): they are '
                'switched off and the torques applied as joint forces, bounded by their force ranges']

    def _torque_through(self) -> str:
        motors = self.actuation.actuator >= 0
        if motors.all() or not motors.any():
            return 'motor actuators' if motors.all() else 'applied joint forces'
        return (f'motor actuators on {[n for n, m in zip(self.joint_names, motors) if m]}, applied joint forces on '
                f'{[n for n, m in zip(self.joint_names, motors) if not m]}')

    def _joint_ids(self) -> list[int]:
        return [int(np.flatnonzero(self.model.jnt_dofadr == address)[0]) for address in self.dof_address]


def _read_model(path: Path):
    mujoco = import_mujoco()
    try:
        status = os.stat(path)
    except OSError as error:
        raise RobotError(f'MJCF {path} cannot be read: {error.strerror}') from None
    problem = regular_file_problem(status)
    if problem is not None:
        raise RobotError(f'MJCF {path} {problem}')
    if status.st_size > MAX_FILE_BYTES:
        raise RobotError(f'MJCF {path} holds {status.st_size} bytes, more than the {MAX_FILE_BYTES} ddarm reads')
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as error:  # MuJoCo's parser and compiler say what they refuse
        message = ' '.join(str(error).split())
        raise RobotError(f'MJCF {path} is not a model MuJoCo compiles: {message}') from None


def robot_joints(path: str | Path) -> dict[str, bool]:
    """The hinge and slide joints of the MJCF at `path`, in MuJoCo's order: name -> prismatic (a slide)."""
    mujoco = import_mujoco()
    model = _read_model(Path(path))
    kinds = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    return {model.joint(j).name: int(model.jnt_type[j]) == kinds[1] for j in range(model.njnt)
            if int(model.jnt_type[j]) in kinds}


def load_robot(path: str | Path, joint_names: tuple[str, ...], prismatic: tuple[bool, ...], period: float,
               joint_map: dict[str, str] | None = None) -> Robot:
    """The MuJoCo model at `path` as the plant of an arm whose controlled joints are `joint_names` (ddarm's order).

    `joint_map` names, for a ddarm joint, the MJCF joint that is it, where their names differ. Refused, naming
    what: an MJCF that MuJoCo does not compile; joints that are not exactly the controlled ones (by name and count;
    a free or ball joint; a hinge for a prismatic joint or a slide for a revolute one); an actuator that does not
    drive one of them directly, or two motors on one; a period that is not a whole number of its timesteps. A
    servo (any actuator but a torque motor) would fight the torques ddarm applies: it is switched off
    (Robot.bypassed, said by Robot.warnings) and its joint's torque applied as a joint force within its force range.
    """
    path = Path(path)
    joint_map = dict(joint_map or {})
    unknown = sorted(set(joint_map) - set(joint_names))
    if unknown:
        raise RobotError(f'--joint-map names {unknown}, which are not joints the motion controls {list(joint_names)}')
    mujoco = import_mujoco()
    model = _read_model(path)
    kinds = {int(mujoco.mjtJoint.mjJNT_HINGE): 'hinge', int(mujoco.mjtJoint.mjJNT_SLIDE): 'slide',
             int(mujoco.mjtJoint.mjJNT_BALL): 'ball', int(mujoco.mjtJoint.mjJNT_FREE): 'free'}
    theirs = {model.joint(j).name: j for j in range(model.njnt)}
    unnamed = [j for j in range(model.njnt) if not model.joint(j).name]
    if unnamed:
        raise RobotError(f'MJCF {path}: joints {unnamed} (in MuJoCo\'s order) have no name: ddarm matches joints '
                         f'by name')
    free = sorted(name for name, j in theirs.items() if kinds[int(model.jnt_type[j])] in ('free', 'ball'))
    if free:
        raise RobotError(f'MJCF {path}: joints {free} are free or ball joints: ddarm controls a fixed-base arm of '
                         f'hinge and slide joints')
    wanted = [joint_map.get(name, name) for name in joint_names]
    missing = [name for name in wanted if name not in theirs]
    extra = sorted(set(theirs) - set(wanted))
    if missing or extra:
        said = []
        if missing:
            said.append(f'has no joint {missing}')
        if extra:
            said.append(f'has joints {extra} the motion does not control')
        raise RobotError(f'MJCF {path} {" and ".join(said)}: its joints must be the controlled joints '
                         f'{list(joint_names)} (map names that differ with --joint-map URDF_JOINT=MJCF_JOINT; remove '
                         'or fix the joints ddarm would lock)')
    ids = [theirs[name] for name in wanted]
    for name, ours, prismatic_joint, j in zip(joint_names, wanted, prismatic, ids):
        kind = kinds[int(model.jnt_type[j])]
        if kind != ('slide' if prismatic_joint else 'hinge'):
            raise RobotError(f'MJCF {path}: joint {ours!r} is a {kind} joint and {name!r} is '
                             f'{"prismatic" if prismatic_joint else "revolute"} in the URDF')
    motor, bypassed, servo_range = {}, [], {}
    for a in range(model.nu):
        actuator = model.actuator(a)
        name = actuator.name or f'#{a}'
        joint = int(model.actuator_trnid[a, 0])
        if int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT) or joint not in ids:
            raise RobotError(f'MJCF {path}: actuator {name!r} does not drive one of the controlled joints directly '
                             '(a tendon, site or slider-crank transmission): ddarm applies one torque per joint')
        is_motor = (int(model.actuator_dyntype[a]) == int(mujoco.mjtDyn.mjDYN_NONE)
                    and int(model.actuator_gaintype[a]) == int(mujoco.mjtGain.mjGAIN_FIXED)
                    and int(model.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_NONE)
                    and model.actuator_gainprm[a, 0] != 0 and model.actuator_gear[a, 0] != 0)
        if not is_motor:
            # A servo (position, velocity; a muscle, a bias) held at its control would fight the torques ddarm
            # applies: it is switched off, and its force range, the drive's limit, bounds the applied joint force.
            bypassed.append(name)
            model.actuator_group[a] = BYPASSED_GROUP
            if model.actuator_forcelimited[a]:
                ends = sorted(model.actuator_gear[a, 0] * model.actuator_forcerange[a])
                servo_range[joint] = (float(ends[0]), float(ends[1]))
            continue
        if joint in motor:
            raise RobotError(f'MJCF {path}: joint {model.joint(joint).name!r} has two motors; ddarm drives one '
                             'torque per joint')
        motor[joint] = a
    if bypassed:
        model.opt.disableactuator |= 1 << BYPASSED_GROUP
    actuators = [motor.get(j, -1) for j in ids]
    unbounded = (-math.inf, math.inf)

    def joint_range(j: int) -> tuple[float, float]:
        low, high = _range(model.jnt_actfrclimited[j], model.jnt_actfrcrange[j])
        if motor.get(j, -1) < 0 and j in servo_range:
            low, high = max(low, servo_range[j][0]), min(high, servo_range[j][1])
        return low, high

    actuation = Actuation(
        actuator=np.array(actuators),
        gear=np.array([model.actuator_gear[a, 0] if a >= 0 else 1.0 for a in actuators], dtype=float),
        gain=np.array([model.actuator_gainprm[a, 0] if a >= 0 else 1.0 for a in actuators], dtype=float),
        ctrl_range=np.array([_range(model.actuator_ctrllimited[a], model.actuator_ctrlrange[a]) if a >= 0
                             else unbounded for a in actuators]),
        force_range=np.array([_range(model.actuator_forcelimited[a], model.actuator_forcerange[a]) if a >= 0
                              else unbounded for a in actuators]),
        joint_range=np.array([joint_range(j) for j in ids]))
    return Robot(path=path, model=model, joint_names=tuple(joint_names),
                 qpos_address=np.array([model.jnt_qposadr[j] for j in ids]),
                 dof_address=np.array([model.jnt_dofadr[j] for j in ids]),
                 actuation=actuation, steps_per_period=_steps(path, model, period),
                 period=period, bypassed=tuple(bypassed))


def _steps(path: Path, model, period: float) -> int:
    """The MuJoCo timesteps of one sampling period; RobotError unless it is a whole number of them."""
    timestep = float(model.opt.timestep)
    steps = period / timestep
    whole = round(steps)
    if not (1 <= whole <= MAX_STEPS_PER_PERIOD and abs(steps - whole) <= WHOLE_STEPS_TOLERANCE * whole):
        raise RobotError(f'MJCF {path}: the period {period:g} s is not a whole number of its timestep {timestep:g} s '
                         f'(<option timestep>; {steps:.6g} steps): the held torque would change inside a timestep')
    return int(whole)


def at_period(robot: Robot, period: float) -> Robot:
    """The robot sampled at another period (RobotError unless a whole number of its timesteps)."""
    if period == robot.period:
        return robot
    return dataclasses.replace(robot, steps_per_period=_steps(robot.path, robot.model, period), period=period)


def warm_up() -> None:
    """Load the compiled saturation that MujocoPlant.saturate calls (from numba's cache, or compile it) now: loaded at
    a realtime robot's first period, it took 0.3 s (numba's linear algebra imports scipy.linalg with it) and made
    that episode's first periods late."""
    saturate(np.zeros((1, 1)), np.full((1, 1), np.inf), np.empty((1, 1)), 1)


class MujocoPlant:
    """One episode's robot in MuJoCo: the state (q, q̇) at sample n, advanced one sampling period at a time.

    The same calls as ddarm's Plant: `saturate` gives the torque the actuators apply (ddarm's limit, then the
    robot's own ranges), `advance` holds it over one period. Once the state leaves the plant's bounds, stops being
    finite or MuJoCo finds its accelerations unstable (and would reset the robot), the plant is `diverged`, its
    state frozen at the last sample within bounds.
    """

    def __init__(self, robot: Robot, q, v, torque_limit=None) -> None:
        mujoco = import_mujoco()
        self._mujoco = mujoco
        self.robot = robot
        self.dof = len(robot.joint_names)
        self._data = mujoco.MjData(robot.model)
        self._limit = (np.full((self.dof, 1), np.inf) if torque_limit is None
                       else np.ascontiguousarray(np.asarray(torque_limit, dtype=float)[:, None]))
        self._q = np.array(q, dtype=float)
        self._v = np.array(v, dtype=float)
        self._data.qpos[robot.qpos_address] = self._q
        self._data.qvel[robot.dof_address] = self._v
        mujoco.mj_forward(robot.model, self._data)
        self._unstable = [int(w) for w in (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQPOS,
                                           mujoco.mjtWarning.mjWARN_BADQVEL)]
        self.sample = 0
        self.diverged = False

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    @property
    def v(self) -> np.ndarray:
        return self._v.copy()

    @property
    def time(self) -> float:
        return self.sample * self.robot.period

    def saturate(self, command: np.ndarray) -> np.ndarray:
        """The torque applied for a command: ddarm's actuator limit (`saturate`, as for ddarm's plant), then what
        the robot's actuators can apply (Actuation.applied)."""
        values = np.asarray(command, dtype=float)
        if values.shape != (self.dof,):
            raise RobotError(f'sample {self.sample}: command must be {self.dof} numbers, got {command!r}')
        limited = np.empty((self.dof, 1))
        saturate(np.ascontiguousarray(values[:, None]), self._limit, limited, 1)
        return self.robot.actuation.applied(limited[:, 0])

    def advance(self, applied_torque: np.ndarray) -> bool:
        """Hold a torque `saturate` returned over [t_n, t_{n+1}): the period's MuJoCo timesteps.

        Returns False, and freezes the plant as diverged, when the state leaves its bounds or MuJoCo's
        accelerations do. Raises RobotError for a torque that is not `dof` finite numbers: nothing is integrated.
        """
        torque = np.asarray(applied_torque, dtype=float)
        if torque.shape != (self.dof,) or not all(map(math.isfinite, torque.tolist())):
            raise RobotError(f'sample {self.sample}: torque must be {self.dof} finite numbers, got {applied_torque!r}')
        if self.diverged:
            return False
        robot, data, mujoco = self.robot, self._data, self._mujoco
        actuation = robot.actuation
        motors = actuation.actuator >= 0
        data.ctrl[actuation.actuator[motors]] = actuation.control(torque)[motors]
        data.qfrc_applied[robot.dof_address[~motors]] = torque[~motors]
        warned = [data.warning[w].number for w in self._unstable]
        for _ in range(robot.steps_per_period):
            mujoco.mj_step(robot.model, data)
        q, v = data.qpos[robot.qpos_address].copy(), data.qvel[robot.dof_address].copy()
        unstable = any(data.warning[w].number > count for w, count in zip(self._unstable, warned))
        if unstable or beyond_bounds(q, v, DEFAULT_MAX_POSITION, DEFAULT_MAX_VELOCITY):
            self.diverged = True
            return False
        applied = data.qfrc_actuator[robot.dof_address] + data.qfrc_applied[robot.dof_address]
        if not float(np.max(np.abs(applied - torque))) <= 1e-12 * max(1.0, float(np.max(np.abs(torque)))):
            raise RobotError(f'MJCF {robot.path}: MuJoCo applied the joint torques {applied.tolist()} where ddarm held '
                             f'{torque.tolist()} (sample {self.sample}): its actuators are not what ddarm read')
        self._q, self._v = q, v
        self.sample += 1
        return True
