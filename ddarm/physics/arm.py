"""The arm's rigid-body model: a Pinocchio model built from the URDF, reduced to the controlled joints.

A URDF's movable joints are revolute, continuous or prismatic; its fixed joints are folded into
their parent link (Pinocchio's URDF parser makes them frames). The joints an episode controls
are named by its motion; every other movable joint is locked at a given position, which makes a
reduced model (pin.buildReducedModel) used alike by the plant and the controller. Joint
positions are angles (rad) or lengths (m) everywhere in ddarm: a continuous joint, which
Pinocchio represents by (cos θ, sin θ), is given to Pinocchio through `configuration`.
"""

from __future__ import annotations

import math
import os
import sys
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pinocchio as pin

from ddarm.errors import DdarmError

URDF_NAME = 'ddarm.urdf'
MOVABLE = ('revolute', 'continuous', 'prismatic')
# Pinocchio's joint models of URDF's movable joints: 1-DOF revolute (bounded or not) and prismatic.
PINOCCHIO_JOINTS = ('JointModelRX', 'JointModelRY', 'JointModelRZ', 'JointModelRevoluteUnaligned',
                    'JointModelRUBX', 'JointModelRUBY', 'JointModelRUBZ', 'JointModelRevoluteUnboundedUnaligned',
                    'JointModelPX', 'JointModelPY', 'JointModelPZ', 'JointModelPrismaticUnaligned')


def is_prismatic(joint_model: str) -> bool:
    """Whether a Pinocchio joint model (its shortname) is prismatic: its position a length, its effort a force."""
    return joint_model.startswith('JointModelP')


class ModelError(DdarmError, ValueError):
    """A URDF or model option that cannot describe the arm."""


def config_file(*parts: str) -> Path:
    """A file of ddarm's config/ folder (e.g. 'arms', 'panda', 'panda.urdf'): from the source tree, else from the
    share folder of the prefix this module is installed in."""
    package = Path(__file__).resolve().parents[1]
    candidates = [package.parent / 'config']
    if len(package.parents) > 3:  # <prefix>/lib/pythonX.Y/site-packages/ddarm (colcon or pip)
        candidates.append(package.parents[3] / 'share' / 'ddarm' / 'config')
    candidates.append(Path(sys.prefix) / 'share' / 'ddarm' / 'config')
    for candidate in candidates:
        if candidate.joinpath(*parts).is_file():
            return candidate.joinpath(*parts)
    raise ModelError(f'{"/".join(parts)} not found in {[str(c) for c in candidates]}')


def default_urdf_path() -> Path:
    """The arm's URDF (config/ddarm.urdf)."""
    return config_file(URDF_NAME)


def same_urdf(first: str | Path | None, second: str | Path | None) -> bool:
    """Whether two URDF arguments (None: the ddarm arm) name the same file."""
    def resolved(urdf):
        return (Path(urdf) if urdf else default_urdf_path()).resolve()
    return resolved(first) == resolved(second)


@dataclass(frozen=True)
class UrdfJoint:
    """A URDF joint as its <joint> element says: type, <limit> (inf where absent) and <mimic>."""

    name: str
    kind: str
    lower: float
    upper: float
    velocity: float
    effort: float
    mimic: tuple[str, float, float] | None  # (mimicked joint, multiplier, offset)


def _attribute(path: Path, joint: str, element, name: str, default: float) -> float:
    text = element.get(name) if element is not None else None
    if text is None:
        return default
    try:
        value = float(text)
    except ValueError:
        raise ModelError(f'URDF {path}: joint {joint!r}: {name}="{text}" is not a number') from None
    if math.isnan(value):
        raise ModelError(f'URDF {path}: joint {joint!r}: {name} is NaN')
    return value


def urdf_joints(path: Path) -> dict[str, UrdfJoint]:
    """The URDF's joints by name, in file order; refuses joint types no fixed-base arm model takes.

    Read from the XML: Pinocchio's parser turns a floating or planar joint into a base of 6 or 3
    DOF and a mimic joint into an independent one without a word.
    """
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError) as error:
        raise ModelError(f'URDF {path} is not readable XML: {error}') from error
    if root.tag != 'robot':
        raise ModelError(f'URDF {path}: the root element is <{root.tag}>, not <robot>')
    joints = {}
    for element in root.iter('joint'):
        if element.get('type') is None:  # <joint> inside <transmission> names a joint; it does not define one
            continue
        name, kind = element.get('name', ''), element.get('type')
        if kind in ('floating', 'planar'):
            raise ModelError(f'URDF {path}: joint {name!r} is {kind}: ddarm models fixed-base arms '
                             f'(revolute, continuous, prismatic and fixed joints)')
        if kind not in (*MOVABLE, 'fixed'):
            raise ModelError(f'URDF {path}: joint {name!r} has type {kind!r}, which URDF does not define')
        limit, mimic = element.find('limit'), element.find('mimic')
        unbounded = kind == 'continuous'
        joints[name] = UrdfJoint(
            name, kind,
            -math.inf if unbounded else _attribute(path, name, limit, 'lower', -math.inf),
            math.inf if unbounded else _attribute(path, name, limit, 'upper', math.inf),
            _attribute(path, name, limit, 'velocity', math.inf), _attribute(path, name, limit, 'effort', math.inf),
            None if mimic is None else (mimic.get('joint', ''), _attribute(path, name, mimic, 'multiplier', 1.0),
                                        _attribute(path, name, mimic, 'offset', 0.0)))
    return joints


def _locked_positions(path: Path, joints: dict[str, UrdfJoint], movable: list[str], controlled: tuple[str, ...],
                      locked: tuple[tuple[str, float], ...]) -> dict[str, float]:
    """The position of every movable joint not controlled: given, a mimic's from its joint, else 0."""
    given = dict(locked)
    for name in given:
        if name not in joints:
            raise ModelError(f'URDF {path}: locked joint {name!r} is not a joint of the URDF')
        if joints[name].kind == 'fixed':
            raise ModelError(f'URDF {path}: locked joint {name!r} is fixed: only movable joints are locked')
        if name in controlled:
            raise ModelError(f'URDF {path}: joint {name!r} is both controlled and locked')
    for name in controlled:
        joint = joints[name]
        if joint.mimic is not None:
            raise ModelError(f'URDF {path}: joint {name!r} mimics {joint.mimic[0]!r}: a mimic joint cannot be '
                             f'controlled (lock it and the joint it mimics, or remove its <mimic>)')
    positions = {}
    for name in movable:
        if name in controlled:
            continue
        joint = joints[name]
        if joint.mimic is None:
            positions[name] = float(given.get(name, 0.0))
    for name in movable:
        joint = joints[name]
        if name in controlled or joint.mimic is None:
            continue
        source, multiplier, offset = joint.mimic
        if name in given:
            raise ModelError(f'URDF {path}: joint {name!r} mimics {source!r}: give the position of {source!r} '
                             f'under locked, not its own')
        if source not in positions:
            raise ModelError(f'URDF {path}: joint {name!r} mimics {source!r}, which is '
                             f'{"controlled" if source in controlled else "no locked joint"}: mimic joints are '
                             f'supported only locked, with the joint they follow')
        positions[name] = multiplier * positions[source] + offset
    for name, value in positions.items():
        joint = joints[name]
        if not (math.isfinite(value) and joint.lower <= value <= joint.upper):
            raise ModelError(f'URDF {path}: locked joint {name!r} at {value!r} is outside its limits '
                             f'[{joint.lower}, {joint.upper}]')
    return positions


def _check_readable(path: Path) -> None:
    if path.is_dir():
        raise ModelError(f'URDF {path} is a directory, not a URDF file')
    if not path.exists():
        raise ModelError(f'URDF {path} does not exist')
    try:
        # Pinocchio reports a file it cannot open as one without a valid model: ask the OS first.
        with path.open('rb'):
            pass
    except OSError as error:
        raise ModelError(f'URDF {path} cannot be read: {error.strerror}') from error


def _read_model(path: Path) -> pin.Model:
    try:
        return pin.buildModelFromUrdf(str(path))
    except (RuntimeError, ValueError) as error:
        raise ModelError(f'URDF {path} is not a URDF the arm can be built from: {error}') from error


@dataclass(frozen=True)
class Arm:
    """A fixed-base arm of revolute, continuous and prismatic joints (the controlled ones), and a Pinocchio
    workspace for its dynamics.

    Like Pinocchio's own Model/Data pair, `model` is what the robot is and
    `data` is scratch space: an Arm is not to be shared between threads.
    """

    model: pin.Model
    data: pin.Data
    urdf_path: Path
    lower: np.ndarray  # the URDF's <limit> per controlled joint (inf where it has none)
    upper: np.ndarray
    velocity_limit: np.ndarray
    effort_limit: np.ndarray
    unbounded: np.ndarray  # continuous joints: (cos θ, sin θ) to Pinocchio
    locked: tuple[tuple[str, float], ...] = ()  # every movable joint not controlled, at its position

    @classmethod
    def from_urdf(cls, urdf_path: Path | str | None = None, mass_scale: np.ndarray | list[float] | None = None,
                  joints: tuple[str, ...] | list[str] | None = None,
                  locked: tuple[tuple[str, float], ...] | dict = ()) -> Arm:
        """Load the URDF reduced to `joints` (default: every movable joint), the others at `locked` (default 0).

        `mass_scale` multiplies each controlled joint's link inertia (mass and moments, locked
        links folded in): a heavier link of the same shape and uniform density scales its whole
        spatial inertia, which is how the plant is made to differ from the model.
        """
        path = Path(urdf_path) if urdf_path is not None else default_urdf_path()
        _check_readable(path)
        described = urdf_joints(path)  # first: Pinocchio's parser prints its own lines for a joint type it refuses
        full = _read_model(path)
        movable = list(full.names)[1:]
        controlled = tuple(movable if joints is None else joints)
        if not controlled:
            raise ModelError(f'URDF {path}: no joint to control (its movable joints: {movable})')
        for name in controlled:
            if name not in movable:
                kind = described[name].kind if name in described else None
                raise ModelError(f'URDF {path}: joint {name!r} is '
                                 f'{"a " + kind + " joint" if kind else "not a joint of the URDF"}; its movable '
                                 f'joints: {movable}')
        repeated = sorted({name for name in controlled if controlled.count(name) > 1})
        if repeated:
            raise ModelError(f'URDF {path}: joints {repeated} named more than once')
        in_model_order = [name for name in movable if name in controlled]
        if list(controlled) != in_model_order:
            raise ModelError(f'URDF {path}: list the controlled joints in the URDF\'s order (parent before child, '
                             f'as Pinocchio numbers them): {in_model_order}, not {list(controlled)}')
        locked = tuple(locked.items()) if isinstance(locked, dict) else tuple(locked)
        positions = _locked_positions(path, described, movable, controlled, locked)
        model = full
        if positions:
            reference = pin.neutral(full)
            for name, value in positions.items():
                joint = full.joints[full.getJointId(name)]
                if joint.nq == 2:
                    reference[joint.idx_q:joint.idx_q + 2] = (math.cos(value), math.sin(value))
                else:
                    reference[joint.idx_q] = value
            model = pin.buildReducedModel(full, [full.getJointId(name) for name in positions], reference)
        for joint_id in range(1, model.njoints):
            kind = model.joints[joint_id].shortname()
            if kind not in PINOCCHIO_JOINTS:
                raise ModelError(f'URDF {path}: joint {model.names[joint_id]!r} is a {kind}; ddarm supports '
                                 f'revolute, continuous and prismatic joints')
        if mass_scale is not None:
            scale = np.asarray(mass_scale, dtype=float)
            if scale.shape != (model.nv,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
                raise ModelError(f'mass_scale must be {model.nv} finite positive numbers, got {mass_scale!r}')
            for joint_id, factor in enumerate(scale, start=1):
                inertia = model.inertias[joint_id]
                model.inertias[joint_id] = pin.Inertia(
                    factor * inertia.mass, inertia.lever, factor * inertia.inertia)
        limits = [described[name] for name in controlled]
        arm = cls(model=model, data=model.createData(), urdf_path=path,
                  lower=np.array([joint.lower for joint in limits]), upper=np.array([joint.upper for joint in limits]),
                  velocity_limit=np.array([joint.velocity for joint in limits]),
                  effort_limit=np.array([joint.effort for joint in limits]),
                  unbounded=np.array([model.joints[i].nq == 2 for i in range(1, model.njoints)]),
                  locked=tuple(positions.items()))
        arm.check_inertia(np.zeros(arm.dof), 'q = 0')
        return arm

    def check_inertia(self, q: np.ndarray, where: str) -> None:
        """Refuse an M(q) that is not positive definite: the plant could not be integrated, nor M̂ inverted."""
        mass = self.mass_matrix(q)
        for name, value in zip(self.joint_names, np.diag(mass)):
            if not value > 0:
                raise ModelError(f'URDF {self.urdf_path}: joint {name!r} moves no mass or inertia (M_ii = '
                                 f'{float(value)!r}): lock it, or give its link an <inertial>')
        values, vectors = np.linalg.eigh(mass)
        if not values[0] > 1e-12 * values[-1]:
            involved = [name for name, part in zip(self.joint_names, vectors[:, 0]) if abs(part) > 0.1]
            raise ModelError(f'URDF {self.urdf_path}: M(q) is singular at {where} (joints {involved} move the same '
                             f'inertia, e.g. two coaxial joints with no mass between them): lock one of them')

    @property
    def dof(self) -> int:
        return self.model.nv

    @property
    def joint_names(self) -> list[str]:
        return list(self.model.names)[1:]

    @property
    def prismatic(self) -> np.ndarray:
        """Which controlled joints are prismatic (positions in m, efforts in N); the others are angles."""
        return np.array([is_prismatic(self.model.joints[i].shortname()) for i in range(1, self.model.njoints)])

    def configuration(self, q: np.ndarray) -> np.ndarray:
        """Pinocchio's configuration of joint positions q: (cos θ, sin θ) for each continuous joint."""
        if not self.unbounded.any():
            return q
        q = np.asarray(q, dtype=float)
        parts = [(math.cos(value), math.sin(value)) if unbounded else (value,)
                 for value, unbounded in zip(q, self.unbounded)]
        return np.array([x for part in parts for x in part])

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M(q) of (1.1), symmetric."""
        upper = pin.crba(self.model, self.data, self.configuration(q))
        return np.triu(upper) + np.triu(upper, 1).T

    def bias(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """V(q, q̇) + G(q) of (1.1)."""
        return pin.nonLinearEffects(self.model, self.data, self.configuration(q), v).copy()

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G(q) of (1.1)."""
        return pin.computeGeneralizedGravity(self.model, self.data, self.configuration(q)).copy()

    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, torque: np.ndarray) -> np.ndarray:
        """q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque (articulated-body algorithm)."""
        return pin.aba(self.model, self.data, self.configuration(q), v, torque).copy()

    def inverse_dynamics(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """M(q) a + V(q, q̇) + G(q) (recursive Newton-Euler)."""
        return pin.rnea(self.model, self.data, self.configuration(q), v, a).copy()

    def energy(self, q: np.ndarray, v: np.ndarray) -> float:
        """Kinetic plus potential energy, for conservation checks."""
        configuration = self.configuration(q)
        kinetic = pin.computeKineticEnergy(self.model, self.data, configuration, v)
        potential = pin.computePotentialEnergy(self.model, self.data, configuration)
        return float(kinetic + potential)

    def frame_position(self, q: np.ndarray, frame: str) -> np.ndarray:
        """Position of a URDF link frame in the fixed frame."""
        if not self.model.existFrame(frame):
            raise ModelError(f'no frame {frame!r} in {self.urdf_path}')
        pin.framesForwardKinematics(self.model, self.data, self.configuration(q))
        return self.data.oMf[self.model.getFrameId(frame)].translation.copy()


def urdf_stamp(urdf: str | None) -> tuple:
    """What a cached model of `urdf` is valid for: the file's modification time and size (a file edited between
    two commands of one process is read again)."""
    try:
        status = os.stat(urdf if urdf is not None else default_urdf_path())
    except OSError:
        return ()  # from_urdf refuses it, naming why
    return status.st_mtime_ns, status.st_size


def movable_joints(urdf: str) -> tuple[str, ...]:
    """The URDF's movable joints, in file order, read once per version of the file."""
    return _movable_joints(urdf, urdf_stamp(urdf))


@lru_cache(maxsize=16)
def _movable_joints(urdf, stamp) -> tuple[str, ...]:
    _check_readable(Path(urdf))
    return tuple(joint.name for joint in urdf_joints(Path(urdf)).values() if joint.kind in MOVABLE)


def load_arm(urdf: str | None, mass_scale: tuple[float, ...] | None = None, joints: tuple[str, ...] | None = None,
             locked: tuple[tuple[str, float], ...] = ()) -> Arm:
    """The arm from a URDF, loaded once per process and version of the file (Arm holds scratch space: one thread
    only)."""
    return _load_arm(urdf, urdf_stamp(urdf), mass_scale, joints, locked)


@lru_cache(maxsize=16)
def _load_arm(urdf, stamp, mass_scale, joints, locked) -> Arm:
    return Arm.from_urdf(urdf, mass_scale, joints, locked)
