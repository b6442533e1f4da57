"""The arm's dynamics as compiled code generated for its model: the one definition every path runs.

The model comes from Pinocchio (ddarm.physics.arm reads the URDF) as a Chain of arrays;
ddarm.physics.generated writes, for that chain, inverse dynamics (RNEA) and forward dynamics
(CRBA + Cholesky), each as Pinocchio's algorithm of that name, unrolled with the model's
constants (looped for a long chain; at most MAX_JOINTS joints). `compiled_dynamics` compiles them (numba, cached
by the code's hash in a folder only this user can write, each cached file checksummed) and hands
them to the compiled loops as first-class functions, so that the plant step, the laws and the
batch engine are compiled once for every arm. Why not Pinocchio at run time: on this project's
2-core machine its abaInParallel takes 0.48 ms for one RK4 stage of 1,000 states, which caps the
batch engine near 650 episodes/s before any other work (bench/batch_throughput.py). The tests
check the generated code against pin.rnea and pin.aba (random states, armature, revolute and
prismatic joints, every arm in config/arms).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import importlib.machinery
import importlib.util
import inspect
import io
import os
import pickle
import shutil
import stat
import sys
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numba
import numpy as np
import pinocchio as pin
from numba import types
from numba.core import cgutils
from numba.core.caching import CompileResultCacheImpl, FunctionCache, IndexDataCacheFile, InTreeCacheLocator
from numba.core.types.function_type import CompileResultWAP
from numba.extending import intrinsic

from ddarm.physics.arm import PINOCCHIO_JOINTS, ModelError, is_prismatic, load_arm, urdf_stamp
# The most joints a chain may have (ddarm's one bound on joints), refused before anything is generated beyond
# it. The generated code and its compile time grow linearly with the joint count (generated.py loops over the
# joints beyond UNROLLED_JOINTS), the forward dynamics' work per state as n·depth + n³/6 (CRBA and Cholesky): a few
# times 10⁵ operations per state at 64 joints.
from ddarm.samples import MAX_JOINTS

REVOLUTE, PRISMATIC = 0, 1


@dataclass(frozen=True)
class Chain:
    """A Pinocchio model as plain arrays: per joint its parent, kind, axis, placement and link inertia.

    Joint i (0-based) is Pinocchio's joint i + 1; parent -1 is the fixed base. Placements are
    Pinocchio's jointPlacements (child-to-parent rotation and translation at q = 0), inertias
    are expressed in the joint's frame: mass, centre of mass (lever) and inertia about it. `damping` and
    `friction` are each joint's viscous and Coulomb friction (the URDF's <dynamics>), which the dynamics
    leave to the plant and the law (`joint_friction`).
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
    damping: np.ndarray
    friction: np.ndarray

    @property
    def dof(self) -> int:
        return len(self.parent)

    def joint_friction(self, viscous=None, coulomb=None) -> tuple[np.ndarray, np.ndarray]:
        """The joints' viscous and Coulomb friction: the URDF's <dynamics damping friction> plus `viscous` and
        `coulomb` beyond them (None: none), each a checked array of `dof` numbers."""
        return (self.damping + (0.0 if viscous is None else np.asarray(viscous, dtype=float)),
                self.friction + (0.0 if coulomb is None else np.asarray(coulomb, dtype=float)))

    def arrays(self) -> tuple:
        """Every field, in one fixed order."""
        return (self.parent, self.kind, self.axis, self.rotation, self.translation, self.armature, self.gravity,
                self.mass, self.lever, self.inertia)


def check_joint_count(count: int) -> None:
    if count > MAX_JOINTS:
        raise ModelError(f'the arm has {count} joints to control; ddarm\'s compiled dynamics take at most {MAX_JOINTS} '
                         f'(lock the others in the motion file)')


def chain_from_model(model: pin.Model) -> Chain:
    """The arrays the compiled dynamics read, from a model of 1-DOF revolute (bounded or continuous) or prismatic
    joints; positions are angles and lengths."""
    check_joint_count(model.njoints - 1)
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
        armature=np.array(model.armature, dtype=float), gravity=np.array(model.gravity.linear, dtype=float),
        damping=np.array(model.damping, dtype=float), friction=np.array(model.friction, dtype=float))


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


@intrinsic
def stack_buffer(typingctx, count):
    """A pointer to `count` (a constant) float64 on the calling function's stack, uninitialised; wrap it in
    numba.carray. numba has no stack arrays, and the generated kernels' scratch taken from the heap (np.empty) cost a
    member alone as much again as its copies (Panda, forward dynamics: 0.51 µs against 0.39 µs); LLVM also knows
    that the stack does not overlap the kernels' arguments."""
    if not isinstance(count, types.IntegerLiteral) or count.literal_value < 1:
        return None
    size = count.literal_value

    def codegen(context, builder, signature, arguments):
        return cgutils.alloca_once(builder, context.get_value_type(types.float64), size=size)
    return types.CPointer(types.float64)(count), codegen


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
_said: set[str] = set()


def _say(line: str) -> None:
    print(f'ddarm: {line}', file=sys.stderr, flush=True)


def _say_once(line: str) -> None:
    if line not in _said:
        _said.add(line)
        _say(line)


def _why_not_private(folder: Path) -> str | None:
    """Why numba may not load code from `folder` (made if missing), or None: it unpickles what it finds there, so
    the folder must be this user's, writable by no one else, and so must every folder above it be (root's or this
    user's, and writable by others only with the sticky bit, as /tmp), or someone else could replace it."""
    why = _why_parents_unsafe(folder)  # before anything is made inside a folder others may write
    if why is not None:
        return why
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        status = os.lstat(folder)
    except FileExistsError:
        return 'is not a folder'
    except NotADirectoryError:
        return 'cannot be made a folder: a folder above it is not a folder'
    except OSError as error:
        return f'cannot be made a folder ({error.strerror or error})'
    if not stat.S_ISDIR(status.st_mode):
        return 'is not a folder'
    if status.st_uid != os.getuid():
        return f'is owned by user {status.st_uid}, not by this user ({os.getuid()})'
    if status.st_mode & 0o022:
        return f'is writable by {"others" if status.st_mode & 0o002 else "its group"} (mode {status.st_mode & 0o777:o})'
    if not os.access(folder, os.W_OK | os.X_OK):
        return 'cannot be written by this user'
    return _why_parents_unsafe(folder)


def _why_parents_unsafe(folder: Path) -> str | None:
    """Why someone else could replace `folder` through a folder above it (one not made yet is skipped), or None."""
    for parent in folder.parents:
        try:
            status = os.stat(parent)
        except FileNotFoundError:
            continue
        if status.st_uid not in (0, os.getuid()):
            return f'is inside {parent}, owned by user {status.st_uid}, who could replace it'
        if status.st_mode & 0o022 and not status.st_mode & stat.S_ISVTX:
            return f'is inside {parent}, which others may write (mode {status.st_mode & 0o777:o}), so could replace it'
    return None


def cache_folder() -> Path:
    """Where generated dynamics and their compiled code are kept: $DDARM_CACHE_DIR (refused unless private), else
    the user's cache folder ($XDG_CACHE_HOME or ~/.cache)/ddarm, else a private folder of this user in the temporary
    folder, else one of this process; a folder passed over is named on stderr with the reason."""
    given = os.environ.get(CACHE_ENVIRONMENT)
    if given:
        folder = Path(given).resolve()
        why = _why_not_private(folder)
        if why is not None:
            raise ModelError(f'the dynamics cache {folder} (${CACHE_ENVIRONMENT}) {why}: numba runs the pickled code '
                             f'it finds there; set {CACHE_ENVIRONMENT} to a folder only this user can write')
        return folder
    base = os.environ.get('XDG_CACHE_HOME')
    if base and not os.path.isabs(base):  # the XDG specification: a relative path is invalid, to be ignored
        _say_once(f'ignoring XDG_CACHE_HOME={base}: not an absolute path')
        base = None
    base = base or os.path.join(os.path.expanduser('~'), '.cache')
    for folder in (Path(base) / 'ddarm', Path(tempfile.gettempdir()) / f'ddarm-{os.getuid()}'):
        folder = folder.resolve()
        why = _why_not_private(folder)
        if why is None:
            return folder
        _say_once(f'not keeping compiled dynamics in {folder}: it {why}')
    global _process_folder
    if _process_folder is None:  # this process's own: its compiled code is not kept beyond it
        _process_folder = Path(tempfile.mkdtemp(prefix='ddarm-')).resolve()
        why = _why_not_private(_process_folder)
        if why is not None:
            raise ModelError(f'no private folder for the compiled dynamics: {_process_folder} {why}; set '
                             f'{CACHE_ENVIRONMENT} to a folder only this user can write')
    return _process_folder


def _private_subfolder(folder: Path) -> Path:
    why = _why_not_private(folder)
    if why is not None:
        raise ModelError(f'the dynamics cache\'s folder {folder} {why}: numba runs the pickled code it finds there; '
                         f'remove it, or set {CACHE_ENVIRONMENT} to a folder only this user can write')
    return folder


def _module_file(source: str) -> tuple[str, Path]:
    """The generated module's name and file, in a private folder: a file already there is kept if it holds
    `source`, else replaced, saying so (many processes may ask at once)."""
    content = source.encode('utf-8')
    name = f'ddarm_dynamics_{hashlib.sha256(content).hexdigest()[:24]}'
    folder = cache_folder() / 'dynamics'
    path = folder / f'{name}.py'
    draft = None
    try:
        _private_subfolder(folder)
        # numba keeps the kernels' compiled code here (see _CheckedLocator): checked before anything is read.
        _private_subfolder(folder / '__pycache__')
        try:
            current = _read_cache_file(path)
        except FileNotFoundError:
            current = None
        except _DamagedFile as damaged:  # a FIFO here would hang the read (and the import), a link read /dev/zero
            _discard(damaged.path, folder)
            _say(f'{damaged}: deleted it, writing it again')
            current = None
        if current == content:
            return name, path
        if current is not None:
            _say(f'{path} is not the code generated for it (truncated or changed): writing it again')
        with tempfile.NamedTemporaryFile('wb', dir=folder, suffix='.tmp', delete=False) as file:
            draft = file.name
            file.write(content)
        try:
            os.link(draft, path)  # fails if another process wrote it first: its file stands
        except FileExistsError:
            try:
                written = _read_cache_file(path)
            except (FileNotFoundError, _DamagedFile):
                written = None
            if written != content:
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


class _DamagedFile(Exception):
    def __init__(self, path: str, why: str) -> None:
        super().__init__(f'{path} {why}')
        self.path = path


# The most a file of the cache may weigh. The largest ddarm writes are numba's compiled code of the batch engine's
# chunk loop and of an 8-joint arm's unrolled forward dynamics, about 0.6 MB each (a generated module is at most
# about 125 kB, an index 2 kB): 64 MiB is a hundred times that, and a bound on what a file swapped in (a link to
# /dev/zero, a huge file) costs to read before it is found damaged.
CACHE_FILE_LIMIT = 64 << 20

_NOT_FILES = ((stat.S_ISLNK, 'a symbolic link'), (stat.S_ISDIR, 'a folder'), (stat.S_ISFIFO, 'a FIFO'),
              (stat.S_ISSOCK, 'a socket'), (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'))


def _why_damaged(status: os.stat_result) -> str | None:
    """Why a cache file of this status (lstat or fstat) is not to be read, or None."""
    if not stat.S_ISREG(status.st_mode):
        kind = next((name for test, name in _NOT_FILES if test(status.st_mode)), 'of an unknown kind')
        return f'is damaged ({kind}, not a regular file)'
    if status.st_size > CACHE_FILE_LIMIT:
        return f'is damaged ({status.st_size} bytes, more than any cache file ddarm writes, {CACHE_FILE_LIMIT})'
    return None


def _read_cache_file(path) -> bytes:
    """The content of the cache file `path`, read only if it is a regular file (not a symbolic link, a FIFO, a
    device or a folder) of at most CACHE_FILE_LIMIT bytes, else _DamagedFile; FileNotFoundError if there is none.
    Checked with lstat before it is opened, and opened neither following a link nor waiting for a FIFO's writer,
    so that what is swapped in between is found by fstat, not hung on."""
    path = str(path)
    why = _why_damaged(os.lstat(path))
    if why is not None:
        raise _DamagedFile(path, why)
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as error:
        if error.errno in (errno.ELOOP, errno.ENXIO):  # a link, a socket
            raise _DamagedFile(path, 'is damaged (not a regular file)') from None
        raise
    try:
        why = _why_damaged(os.fstat(descriptor))
        if why is not None:
            raise _DamagedFile(path, why)
        chunks, size = [], 0
        while chunk := os.read(descriptor, min(1 << 20, CACHE_FILE_LIMIT + 1 - size)):
            chunks.append(chunk)
            size += len(chunk)
            if size > CACHE_FILE_LIMIT:
                raise _DamagedFile(path, f'is damaged (more than any cache file ddarm writes, {CACHE_FILE_LIMIT} '
                                         f'bytes)')
        return b''.join(chunks)
    finally:
        os.close(descriptor)


def _discard(path: str, folder) -> None:
    """Removes the damaged file `path` of the checked cache folder `folder`: a file, FIFO or symbolic link is
    unlinked (a link's target is never touched); a folder is removed with all it holds only if it is one directly
    in `folder`, inside cache_folder() (shutil.rmtree follows no link)."""
    try:
        status = os.lstat(path)
        if not stat.S_ISDIR(status.st_mode):
            os.unlink(path)
            return
        parent = Path(path).parent.resolve()
        if parent != Path(folder).resolve() or not parent.is_relative_to(cache_folder()):
            raise ModelError(f'{path} is a folder where a file of the dynamics cache belongs, outside the cache '
                             f'{cache_folder()}: not removing it; remove it')
        shutil.rmtree(path)
    except FileNotFoundError:  # another process removed it first
        pass
    except OSError as error:
        raise ModelError(f'{path} is damaged, and cannot be removed ({error.strerror or error}); remove it, or set '
                         f'{CACHE_ENVIRONMENT} to another folder') from error


class _ChecksummedFiles(IndexDataCacheFile):
    """numba's index and data files of a kernel, each written with the SHA-256 of its content in front and read
    only if it matches: a truncated or overwritten file is found before pickle or LLVM sees it (one wrong byte
    of compiled code could crash the process or change a number)."""

    def _verified(self, path: str) -> bytes:
        content = _read_cache_file(path)
        digest, payload = content[:_DIGEST], content[_DIGEST:]
        if len(content) < _DIGEST or hashlib.sha256(payload).digest() != digest:
            raise _DamagedFile(path, 'is damaged (its checksum does not match)')
        return payload

    def _load_index(self):
        try:
            payload = self._verified(self._index_path)
        except FileNotFoundError:
            return {}
        stream = io.BytesIO(payload)
        if pickle.load(stream) != self._version:
            return {}
        stamp, overloads = pickle.loads(stream.read())
        return overloads if stamp == self._source_stamp else {}

    def _load_data(self, name):
        return pickle.loads(self._verified(self._data_path(name)))

    @contextlib.contextmanager
    def _open_for_write(self, filepath):
        buffer = io.BytesIO()
        yield buffer
        with super()._open_for_write(filepath) as file:
            file.write(hashlib.sha256(buffer.getvalue()).digest() + buffer.getvalue())


_DIGEST = hashlib.sha256().digest_size


class _CheckedLocator(InTreeCacheLocator):
    """Where _CheckedCache keeps a function's compiled code: folder(), checked private (_private_subfolder) before
    anything is read or written there; stamped, as numba's own, with the hash of the function's source file."""

    def __init__(self, py_func, py_file: str, folder: Callable[[], Path]) -> None:
        super().__init__(py_func, py_file)
        self._folder = folder

    def get_cache_path(self):
        return str(self._folder())

    def ensure_cache_path(self):
        _private_subfolder(Path(self.get_cache_path()))


class _CheckedCacheImpl(CompileResultCacheImpl):
    def __init__(self, py_func, folder: Callable[[], Path]):  # numba's own lets NUMBA_CACHE_DIR and others move it
        self._lineno = py_func.__code__.co_firstlineno
        path = inspect.getfile(py_func)
        self._locator = _CheckedLocator(py_func, path, folder)
        self._filename_base = self.get_filename_base(f'{Path(path).stem}.{py_func.__qualname__}',
                                                     getattr(sys, 'abiflags', ''))


class _CheckedCache(FunctionCache):
    """numba's cache of one function (`what`), only in the checked folder folder(), every file checksummed; a
    damaged file is deleted, said on stderr, and the function compiled (and cached) again. The folder is found at
    each load and save, not when the function is defined: a module of compiled loops is imported before the
    command has read its options, and $DDARM_CACHE_DIR may be refused."""

    def __init__(self, py_func, folder: Callable[[], Path], what: str) -> None:  # numba's own finds its folder now
        self._name = repr(py_func)
        self._py_func = py_func
        self._impl = _CheckedCacheImpl(py_func, folder)
        self._what = what
        self.enable()

    @property
    def cache_path(self):
        return self._impl.locator.get_cache_path()

    @property
    def _cache_file(self):
        return _ChecksummedFiles(self.cache_path, self._impl.filename_base, self._impl.locator.get_source_stamp())

    def load_overload(self, sig, target_context):
        self._impl.locator.ensure_cache_path()
        try:
            return super().load_overload(sig, target_context)
        except _DamagedFile as damaged:
            _discard(damaged.path, self.cache_path)
            _say(f'{damaged}: deleted it, compiling {self._what} again')
            return None

    def save_overload(self, sig, data):
        try:
            super().save_overload(sig, data)
        except _DamagedFile as damaged:  # the index, damaged since load_overload read it
            _discard(damaged.path, self.cache_path)
            _say(f'{damaged}: deleted it, caching {self._what} again')
            super().save_overload(sig, data)


def generated_kernel(options: dict):
    """numba.njit(KERNEL_SIGNATURE, **options) for a generated module's kernel, compiled now, its compiled code
    cached (options['cache']) by _CheckedCache in the __pycache__ beside the module (checked by _module_file)."""
    def compile_kernel(function):
        dispatcher = numba.njit(**{**options, 'cache': False})(function)
        if options.get('cache'):
            folder = Path(inspect.getfile(function)).parent / '__pycache__'
            # What Dispatcher.enable_caching does, with this cache.
            dispatcher._cache = _CheckedCache(function, lambda: folder, 'the arm\'s dynamics')
        dispatcher.compile(KERNEL_SIGNATURE.args)
        dispatcher.disable_compile()
        return dispatcher
    return compile_kernel


def _loops_folder(source: str) -> Path:
    """The private folder of the compiled code of ddarm's loops in the module file `source`: cache_folder()/loops/
    <module>-<hash of the file's path>, one per copy of ddarm (two checkouts' loops may differ; sharing a folder,
    each would find the other's cache stale and overwrite it)."""
    path = Path(source).resolve()
    loops = _private_subfolder(cache_folder() / 'loops')
    return loops / f'{path.stem}-{hashlib.sha256(str(path).encode()).hexdigest()[:16]}'


def cached_njit(**options):
    """numba.njit(**COMPILED, **options) for ddarm's own compiled loops: compiled at the first call (for its
    argument types), the compiled code cached by _CheckedCache in _loops_folder, not numba's __pycache__ or
    $NUMBA_CACHE_DIR."""
    def lazily_compiled(function):
        dispatcher = numba.njit(**{**COMPILED, **options, 'cache': False})(function)
        source = inspect.getfile(function)
        dispatcher._cache = _CheckedCache(function, lambda: _loops_folder(source),
                                          f'{function.__module__}.{function.__qualname__}')
        return dispatcher
    return lazily_compiled


class _GeneratedLoader(importlib.machinery.SourceFileLoader):
    """Runs a generated module from the source _module_file checked: no bytecode of it is read or written (a .pyc in
    the cache would be one more file to damage, and Python runs one with a valid header unchecked)."""

    def __init__(self, name: str, path: Path, source: str) -> None:
        super().__init__(name, str(path))
        self.source = source

    def get_code(self, fullname):
        return compile(self.source, self.path, 'exec', dont_inherit=True)


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
            source = dynamics_source(chain)
            name, path = _module_file(source)
            module = sys.modules.get(name)
            if module is None:
                spec = importlib.util.spec_from_file_location(name, path, loader=_GeneratedLoader(name, path, source))
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
