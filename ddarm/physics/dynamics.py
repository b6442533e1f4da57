"""The arm's dynamics as compiled code generated for its model: the one definition every path runs.

The model comes from Pinocchio (ddarm.physics.arm reads the URDF) as a Chain of arrays;
ddarm.physics.generated writes, for that chain, inverse dynamics (RNEA) and forward dynamics
(CRBA + Cholesky), each as Pinocchio's algorithm of that name, unrolled with the model's
constants. `compiled_dynamics` compiles them (numba, cached on disk by the code's hash) and hands
them to the compiled loops as first-class functions, so that the plant step, the laws and the
batch engine are compiled once for every arm. Why not Pinocchio at run time: on this project's
2-core machine its abaInParallel takes 0.48 ms for one RK4 stage of 1,000 states, which caps the
batch engine near 650 episodes/s before any other work (bench/batch_throughput.py). The tests
check the generated code against pin.rnea and pin.aba (random states, armature, revolute and
prismatic joints, every arm in config/arms).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import stat
import sys
import tempfile
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numba
import numpy as np
import pinocchio as pin
from numba import types
from numba.core.types.function_type import CompileResultWAP

from ddarm.physics.arm import PINOCCHIO_JOINTS, ModelError, is_prismatic, load_arm, urdf_stamp

REVOLUTE, PRISMATIC = 0, 1


@dataclass(frozen=True)
class Chain:
    """A Pinocchio model as plain arrays: per joint its parent, kind, axis, placement and link inertia.

    Joint i (0-based) is Pinocchio's joint i + 1; parent -1 is the fixed base. Placements are
    Pinocchio's jointPlacements (child-to-parent rotation and translation at q = 0), inertias
    are expressed in the joint's frame: mass, centre of mass (lever) and inertia about it.
    """

    parent: np.ndarray
    kind: np.ndarray
    axis: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    mass: np.ndarray
    lever: np.ndarray
    inertia: np.ndarray
    armature: np.ndarray
    gravity: np.ndarray

    @property
    def dof(self) -> int:
        return len(self.parent)

    def arrays(self) -> tuple:
        """Every field, in one fixed order."""
        return (self.parent, self.kind, self.axis, self.rotation, self.translation, self.armature, self.gravity,
                self.mass, self.lever, self.inertia)


def chain_from_model(model: pin.Model) -> Chain:
    """The arrays the compiled dynamics read, from a model of 1-DOF revolute (bounded or continuous) or prismatic
    joints; positions are angles and lengths."""
    parent, kind, axis, rotation, translation = [], [], [], [], []
    # Each joint's axis from its motion subspace S (linear part for prismatic, angular for revolute joints): the
    # Python bindings expose no axis for every joint model (RevoluteUnboundedUnaligned has none).
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    for joint_id in range(1, model.njoints):
        joint = model.joints[joint_id]
        name = joint.shortname()
        if name not in PINOCCHIO_JOINTS or joint.nv != 1 or joint.idx_v != joint_id - 1:
            raise ModelError(f'joint {model.names[joint_id]!r} is a {name}: the batch engine supports '
                             f'revolute, continuous and prismatic joints only')
        # Continuous joints (RUB*, Pinocchio's (cos θ, sin θ)) are revolute: their position is the angle θ.
        joint_kind = PRISMATIC if is_prismatic(name) else REVOLUTE
        subspace = np.array(data.joints[joint_id].S).ravel()
        parent.append(model.parents[joint_id] - 1)
        kind.append(joint_kind)
        axis.append(subspace[:3] if joint_kind == PRISMATIC else subspace[3:])
        rotation.append(model.jointPlacements[joint_id].rotation)
        translation.append(model.jointPlacements[joint_id].translation)
    inertias = [model.inertias[joint_id] for joint_id in range(1, model.njoints)]
    return Chain(
        parent=np.array(parent, dtype=np.int64), kind=np.array(kind, dtype=np.int64),
        axis=np.array(axis, dtype=float), rotation=np.array(rotation, dtype=float),
        translation=np.array(translation, dtype=float),
        mass=np.array([inertia.mass for inertia in inertias]),
        lever=np.array([inertia.lever for inertia in inertias]),
        inertia=np.array([inertia.inertia for inertia in inertias]),
        armature=np.array(model.armature, dtype=float), gravity=np.array(model.gravity.linear, dtype=float))


def load_chain(urdf: str | None, joints: tuple[str, ...] | None = None,
               locked: tuple[tuple[str, float], ...] = ()) -> Chain:
    """The chain of the URDF's model reduced to `joints` (the others `locked`), built once per process and version
    of the file."""
    return _load_chain(urdf, urdf_stamp(urdf), joints, locked)


@lru_cache(maxsize=16)
def _load_chain(urdf, stamp, joints, locked) -> Chain:
    return chain_from_model(load_arm(urdf, None, joints, locked).model)



# The compiled functions keep the members of a chunk on the last axis ("lanes") and loop over
# them innermost: every call of a compiled function costs an atomic reference count per array
# argument, which per member would cost as much as the dynamics themselves.
# error_model='numpy': a division by zero gives inf or NaN, as in the scalar path, and the
# divergence check sees it; fastmath 'contract' only fuses multiply-adds, and no flag that
# assumes finite numbers is set.
COMPILED = dict(cache=True, error_model='numpy', fastmath={'contract'})
LANE_ARRAY = types.float64[:, ::1]
# Both generated functions: (mass scale, q, q̇, torque or q̈, out, lanes), arrays of shape (n, lanes).
KERNEL_SIGNATURE = types.void(LANE_ARRAY, LANE_ARRAY, LANE_ARRAY, LANE_ARRAY, LANE_ARRAY, types.int64)
CACHE_ENVIRONMENT = 'DDARM_CACHE_DIR'


def typed_entry(dispatcher, *arguments):
    """`dispatcher`'s compiled code for the types of `arguments` (compiled, or loaded from numba's cache, now).

    Call it only with arguments of exactly those types, arrays C-contiguous: it converts them without
    checking their layout. numba's dispatcher types every argument at every call, and a first-class
    function (the generated dynamics) costs it about 15 µs, more than a plant step or a law's command
    takes; a node makes one such call per sample, with arrays it makes itself, so it types them once.
    """
    return dispatcher.compile(tuple(numba.typeof(argument) for argument in arguments))


@dataclass(frozen=True)
class Dynamics:
    """A chain's compiled forward and inverse dynamics, as first-class functions of KERNEL_SIGNATURE.

    The compiled loops take them as arguments (typed by their signature, not by which model they
    are), so each loop is compiled once and serves every arm. `chain` is the model they were made from.
    """

    chain: Chain
    forward_dynamics: CompileResultWAP
    inverse_dynamics: CompileResultWAP


_process_folder: Path | None = None


def _private_folder(folder: Path) -> Path | None:
    """`folder`, made if missing, if it is a real folder of this user that no one else may write (numba
    unpickles what it finds there); else None."""
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        status = os.lstat(folder)
    except OSError:
        return None
    if (not stat.S_ISDIR(status.st_mode) or status.st_uid != os.getuid() or status.st_mode & 0o022
            or not os.access(folder, os.W_OK)):
        return None
    return folder


def cache_folder() -> Path:
    """Where generated dynamics and their compiled code are kept: $DDARM_CACHE_DIR, else the user's
    cache folder ($XDG_CACHE_HOME or ~/.cache)/ddarm, else (a home that cannot be written) a private
    folder of this user in the temporary folder."""
    given = os.environ.get(CACHE_ENVIRONMENT)
    if given:
        return Path(given)
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    for folder in (Path(base) / 'ddarm', Path(tempfile.gettempdir()) / f'ddarm-{os.getuid()}'):
        if _private_folder(folder) is not None:
            return folder
    global _process_folder
    if _process_folder is None:  # this process's own: its compiled code is not kept beyond it
        _process_folder = Path(tempfile.mkdtemp(prefix='ddarm-'))
    return _process_folder


def _module_file(source: str) -> tuple[str, Path]:
    """The generated module's name and file, written once: a file already there is never rewritten, since
    numba's cache of it is stamped with its modification time (many processes may ask at once)."""
    content = source.encode('utf-8')
    name = f'ddarm_dynamics_{hashlib.sha256(content).hexdigest()[:24]}'
    folder = cache_folder() / 'dynamics'
    path = folder / f'{name}.py'
    draft = None
    try:
        if path.is_file() and path.read_bytes() == content:
            return name, path
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile('wb', dir=folder, suffix='.tmp', delete=False) as file:
            draft = file.name
            file.write(content)
        try:
            os.link(draft, path)  # fails if another process wrote it first: its file stands
        except FileExistsError:
            if path.read_bytes() != content:
                os.replace(draft, path)
        except OSError:  # a file system without hard links
            os.replace(draft, path)
    except OSError as error:
        raise ModelError(f'cannot write the arm\'s generated dynamics to {folder}: {error.strerror or error}; '
                         f'set {CACHE_ENVIRONMENT} to a folder this user can write') from error
    finally:
        if draft is not None and os.path.exists(draft):
            os.unlink(draft)
    return name, path


def _chain_key(chain: Chain) -> bytes:
    return b''.join(np.ascontiguousarray(array).tobytes() + str(array.shape).encode() for array in chain.arrays())


_loaded: dict[bytes, Dynamics] = {}
# A module numba is compiling must not be seen by another thread (the searches' and the nodes' threads
# ask for the same chain): one thread loads at a time.
_loading = threading.Lock()


def compiled_dynamics(chain: Chain) -> Dynamics:
    """The chain's generated dynamics, compiled (or loaded from numba's cache), once per process and chain."""
    key = _chain_key(chain)
    with _loading:
        if key not in _loaded:
            from ddarm.physics.generated import dynamics_source
            name, path = _module_file(dynamics_source(chain))
            module = sys.modules.get(name)
            if module is None:
                spec = importlib.util.spec_from_file_location(name, path)
                module = importlib.util.module_from_spec(spec)
                # numba finds the module of compiled code by name, also when it loads it from its cache.
                sys.modules[name] = module
                try:
                    spec.loader.exec_module(module)
                except BaseException:
                    del sys.modules[name]
                    raise
            _loaded[key] = Dynamics(chain, *(CompileResultWAP(kernel.overloads[KERNEL_SIGNATURE.args])
                                             for kernel in (module.forward_dynamics, module.inverse_dynamics)))
        return _loaded[key]


def _lanes(values, n: int, lanes: int) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(np.transpose(np.atleast_2d(np.asarray(values, dtype=float))),
                                                (n, lanes)))


def _evaluate(kernel, chain: Chain, q, v, third, mass_scale) -> np.ndarray:
    q = np.ascontiguousarray(np.transpose(np.atleast_2d(np.asarray(q, dtype=float))))
    n, lanes = q.shape
    if n != chain.dof:  # the compiled code reads and writes `dof` rows without bounds checks
        raise ValueError(f'states must have {chain.dof} joint values each, got {n}')
    scale = np.ones((n, lanes)) if mass_scale is None else _lanes(mass_scale, n, lanes)
    out = np.empty((n, lanes))
    kernel(scale, q, _lanes(v, n, lanes), _lanes(third, n, lanes), out, lanes)
    return np.ascontiguousarray(out.T)


def inverse_dynamics_at(chain: Chain, q: np.ndarray, v: np.ndarray, a: np.ndarray,
                        mass_scale: np.ndarray | None = None) -> np.ndarray:
    """τ = M(q) a + V(q, q̇) + G(q) at m states (arrays of shape (m, n)), by the compiled code the loops run;
    `mass_scale` (n,) or (m, n) scales each link's mass and inertia."""
    return _evaluate(compiled_dynamics(chain).inverse_dynamics, chain, q, v, a, mass_scale)


def forward_dynamics_at(chain: Chain, q: np.ndarray, v: np.ndarray, torque: np.ndarray,
                        mass_scale: np.ndarray | None = None) -> np.ndarray:
    """q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque at m states (arrays of shape (m, n)), as inverse_dynamics_at."""
    return _evaluate(compiled_dynamics(chain).forward_dynamics, chain, q, v, torque, mass_scale)
