"""The dynamics cache against someone else's files: a cache folder another user may write is never read (numba
unpickles what it finds there), and a truncated or garbage file of any kind the cache holds is discarded, said
so in one line, and rebuilt."""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import json
import os
import pickle
import shutil
import stat
import struct
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pinocchio as pin
import pytest

from ddarm.physics import dynamics
from ddarm.physics.arm import ModelError
from ddarm.physics.dynamics import chain_from_model, compiled_dynamics, inverse_dynamics_at
from ddarm.physics.generated import dynamics_source

NOBODY = 65534
as_root = pytest.mark.skipif(os.getuid() != 0, reason='giving a folder to another user needs root')


def small_chain(mass: float) -> dynamics.Chain:
    """A 1-joint chain (compiled in about a second), its link of `mass`: a chain no other test compiles."""
    model = pin.Model()
    joint = model.addJoint(0, pin.JointModelRY(), pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.1])), 'j1')
    model.appendBodyToJoint(joint, pin.Inertia(mass, np.array([0.2, 0.0, 0.0]), np.diag([0.01, 0.02, 0.03])),
                            pin.SE3.Identity())
    return chain_from_model(model)


def module_name(chain) -> str:
    return f'ddarm_dynamics_{hashlib.sha256(dynamics_source(chain).encode()).hexdigest()[:24]}'


def index_names(chain) -> list[str]:
    """numba's index file names for the chain's two kernels: <module>.<function>-<first line>.pyXY.nbi."""
    lines = dynamics_source(chain).splitlines()
    names = []
    for function in ('forward_dynamics', 'inverse_dynamics'):
        line = next(number for number, text in enumerate(lines) if text.startswith(f'def {function}('))
        while line > 0 and lines[line - 1].startswith('@'):
            line -= 1
        names.append(f'{module_name(chain)}.{function}-{line + 1}.py{sys.version_info[0]}{sys.version_info[1]}'
                     f'{getattr(sys, "abiflags", "")}.nbi')
    return names


class _Planted:
    """A pickle that, when loaded, creates `marker`: code someone else planted, run by whoever unpickles it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), 'w')


def plant(folder: Path, chain, marker: Path) -> None:
    """A planted index for each of the chain's kernels in `folder`, as numba would find it."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in index_names(chain):
        (folder / name).write_bytes(pickle.dumps(_Planted(marker)))


@pytest.fixture
def no_chain_loaded(monkeypatch):
    monkeypatch.setattr(dynamics, '_loaded', {})
    monkeypatch.setattr(dynamics, '_process_folder', None)


def shared(folder: Path, mode: int = 0o777, owner: int | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(mode)
    if owner is not None:
        os.chown(folder, owner, owner)
    return folder


@pytest.mark.parametrize('case', [
    pytest.param('world-writable, another user\'s', marks=as_root),
    'world-writable, this user\'s',
    'group-writable',
    'private, in a folder anyone may write',
    'private, its dynamics folder world-writable',
    pytest.param('private, its numba folder another user\'s', marks=as_root),
])
def test_a_cache_dir_others_may_write_is_refused_naming_it_and_nothing_in_it_is_loaded(tmp_path, monkeypatch,
                                                                                      no_chain_loaded, case):
    chain = small_chain(1.0 + len(case) / 100)
    marker = tmp_path / 'planted-code-ran'
    if case.startswith('private, in'):
        cache = shared(tmp_path / 'open') / 'cache'
        cache.mkdir(mode=0o700)
        unsafe = tmp_path / 'open'
    else:
        cache = tmp_path / 'cache'
        unsafe = cache
        if case == 'world-writable, another user\'s':
            shared(cache, owner=NOBODY)
        elif case == 'world-writable, this user\'s':
            shared(cache)
        elif case == 'group-writable':
            shared(cache, 0o770)
        else:
            shared(cache, 0o700)
    if case.endswith('dynamics folder world-writable'):
        unsafe = shared(cache / 'dynamics')
    if case.endswith('another user\'s') and case.startswith('private'):
        unsafe = shared(cache / 'dynamics' / '__pycache__', 0o755, owner=NOBODY)
    plant(cache / 'dynamics' / '__pycache__', chain, marker)
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(cache))
    with pytest.raises(ModelError, match=f'{unsafe}.*(writ|own)'):
        compiled_dynamics(chain)
    assert not marker.exists()


def test_numba_cache_dir_does_not_move_the_compiled_dynamics_out_of_the_checked_folder(tmp_path, monkeypatch,
                                                                                       no_chain_loaded):
    chain = small_chain(1.71)
    marker = tmp_path / 'planted-code-ran'
    cache = tmp_path / 'cache'
    cache.mkdir(mode=0o700)
    hostile = shared(tmp_path / 'numba-cache')
    # Where numba's own locator puts a module's cache under NUMBA_CACHE_DIR: <folder>_<sha1 of its path>.
    folder = str((cache / 'dynamics').resolve())
    plant(hostile / f'dynamics_{hashlib.sha1(folder.encode()).hexdigest()}', chain, marker)
    monkeypatch.setattr(numba.config, 'CACHE_DIR', str(hostile))
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(cache))
    compiled_dynamics(chain)
    assert not marker.exists()
    assert {path.name for path in (cache / 'dynamics' / '__pycache__').glob('*.nbi')} == set(index_names(chain))


def test_a_user_cache_folder_others_may_write_is_left_for_a_private_one_saying_why(tmp_path, monkeypatch, capsys,
                                                                                   no_chain_loaded):
    chain = small_chain(1.83)
    marker = tmp_path / 'planted-code-ran'
    monkeypatch.delenv(dynamics.CACHE_ENVIRONMENT, raising=False)
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'xdg'))
    hostile = shared(tmp_path / 'xdg' / 'ddarm')
    plant(hostile / 'dynamics' / '__pycache__', chain, marker)
    (tmp_path / 'tmp').mkdir()
    monkeypatch.setenv('TMPDIR', str(tmp_path / 'tmp'))
    monkeypatch.setattr(dynamics.tempfile, 'tempdir', None)
    compiled_dynamics(chain)
    assert not marker.exists()
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 1 and str(hostile) in said[0] and 'writ' in said[0]
    assert dynamics.cache_folder() == tmp_path / 'tmp' / f'ddarm-{os.getuid()}'


def test_a_user_cache_folder_inside_a_folder_others_may_write_is_left_without_making_anything_there(
        tmp_path, monkeypatch, capsys, no_chain_loaded):
    monkeypatch.setattr(dynamics, '_said', set())
    monkeypatch.delenv(dynamics.CACHE_ENVIRONMENT, raising=False)
    hostile = shared(tmp_path / 'shared')
    monkeypatch.setenv('XDG_CACHE_HOME', str(hostile))
    (tmp_path / 'tmp').mkdir()
    monkeypatch.setenv('TMPDIR', str(tmp_path / 'tmp'))
    monkeypatch.setattr(dynamics.tempfile, 'tempdir', None)
    assert dynamics.cache_folder() == tmp_path / 'tmp' / f'ddarm-{os.getuid()}'
    assert list(hostile.iterdir()) == []  # a ddarm/ made there would be a folder others could swap
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 1 and str(hostile / 'ddarm') in said[0] and 'others may write' in said[0]


def test_a_relative_xdg_cache_home_is_ignored_as_the_xdg_specification_says(tmp_path, monkeypatch, capsys,
                                                                             no_chain_loaded):
    monkeypatch.setattr(dynamics, '_said', set())
    monkeypatch.delenv(dynamics.CACHE_ENVIRONMENT, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv('XDG_CACHE_HOME', 'relative-cache')
    monkeypatch.setenv('HOME', str(tmp_path / 'home'))
    assert dynamics.cache_folder() == tmp_path / 'home' / '.cache' / 'ddarm'
    assert not (tmp_path / 'relative-cache').exists()
    assert 'ignoring XDG_CACHE_HOME=relative-cache: not an absolute path' in capsys.readouterr().err


def load_from_disk(chain) -> dynamics.Dynamics:
    """The chain's dynamics as a new process gets them: its module run again, numba's cache read."""
    sys.modules.pop(module_name(chain), None)
    dynamics._loaded.clear()
    return compiled_dynamics(chain)


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])


def _garbage(path: Path) -> None:
    path.write_bytes(b'\x80\x05garbage' * 40)


def _flip(path: Path) -> None:
    content = bytearray(path.read_bytes())
    content[len(content) * 2 // 3] ^= 0x10  # still a pickle, perhaps, with one wrong byte of code or data
    path.write_bytes(bytes(content))


def _bytecode(module: Path) -> None:
    # A .pyc with a valid header for the module (its mtime and size) and garbage after it: Python would trust it.
    status = module.stat()
    header = importlib.util.MAGIC_NUMBER + struct.pack('<III', 0, int(status.st_mtime) & 0xFFFFFFFF,
                                                       status.st_size & 0xFFFFFFFF)
    (module.parent / '__pycache__' / f'{module.stem}.{sys.implementation.cache_tag}.pyc').write_bytes(
        header + b'garbage' * 10)


@pytest.mark.parametrize('kind, spoil', [
    ('index', _truncate), ('index', _garbage), ('index', _flip),
    ('data', _truncate), ('data', _garbage), ('data', _flip),
    ('module', _truncate), ('module', _garbage), ('bytecode', None),
])
def test_a_spoiled_cache_file_is_discarded_saying_so_and_rebuilt(tmp_path, monkeypatch, capsys, no_chain_loaded,
                                                                 kind, spoil):
    chain = small_chain(2.5)
    cache = tmp_path / 'cache'
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(cache))
    state = (np.array([[0.3]]), np.array([[-1.2]]), np.array([[0.7]]))
    expected = inverse_dynamics_at(chain, *state)
    load_from_disk(chain)
    folder = cache / 'dynamics'
    module = folder / f'{module_name(chain)}.py'
    files = {'index': sorted((folder / '__pycache__').glob('*.nbi')),
             'data': sorted((folder / '__pycache__').glob('*.nbc')), 'module': [module], 'bytecode': [module]}[kind]
    assert len(files) == (2 if kind in ('index', 'data') else 1)
    capsys.readouterr()
    if kind == 'bytecode':
        _bytecode(module)
    else:
        for path in files:
            spoil(path)
    load_from_disk(chain)
    np.testing.assert_array_equal(inverse_dynamics_at(chain, *state), expected)
    said = capsys.readouterr().err.splitlines()
    if kind != 'bytecode':  # never read, so nothing to say
        assert len(said) == len(files) and all(str(path) in line for path, line in zip(files, said)), said
    # Rebuilt: the next process loads the compiled code from the cache, and has nothing to say.
    load_from_disk(chain)
    assert capsys.readouterr().err == ''
    kernels = [sys.modules[module_name(chain)].forward_dynamics, sys.modules[module_name(chain)].inverse_dynamics]
    assert all(sum(kernel.stats.cache_hits.values()) == 1 for kernel in kernels)


# ddarm's own compiled loops (the plant step, the laws, the batch engine, the indices' sums): their cache too is kept
# only in the checked folder, checksummed, and rebuilt when damaged. Each run below is a new process, as a later
# command is; it starts from a copy of the cache the session's `compiled_loop` fixture filled, so that it compiles
# only what the test spoils.
LOOP_MODULES = ('ddarm.physics.plant', 'ddarm.control.laws', 'ddarm.episodes.engine', 'ddarm.episodes.indices')


def loop_dispatchers() -> dict[str, numba.core.registry.CPUDispatcher]:
    """Every compiled function of ddarm's loops, by module.name."""
    found = {}
    for name in LOOP_MODULES:
        module = importlib.import_module(name)
        for attribute, value in vars(module).items():
            if isinstance(value, numba.core.registry.CPUDispatcher) and value.py_func.__module__ == name:
                found[f'{name}.{attribute}'] = value
    return found


def loop_numbers() -> list[str]:
    """What ddarm's compiled loops compute, to the bit: a plant step, each law's command, a batch's indices and the
    indices of an episode's series (loaded from the cache, or compiled)."""
    from ddarm.control.laws import LAWS, Measurement, ReferencePoint
    from ddarm.episodes.engine import run_episode, simulate_batch, warm_up
    from ddarm.episodes.indices import score_series
    from ddarm.episodes.spec import EpisodeSpec
    from ddarm.physics.dynamics import load_chain
    from ddarm.physics.plant import Plant, PlantOptions

    warm_up()
    chain = load_chain(None)
    dof = chain.dof
    plant = Plant(chain, PlantOptions(), np.full(dof, 0.3), np.full(dof, -0.2))
    plant.advance(plant.saturate(np.full(dof, 1.5)))
    numbers = [*plant.q, *plant.v]
    state = Measurement(np.full(dof, 0.1), np.full(dof, 0.2), np.full(dof, 0.4), np.full(dof, -0.3))
    for law in LAWS.values():
        numbers += list(law(chain, np.full(dof, 30.0), np.full(dof, 7.0)).torque(
            state, ReferencePoint(np.zeros(dof), np.zeros(dof), np.full(dof, 0.5)), np.full(dof, 2.0)))
    spec = EpisodeSpec(controller='computed_torque', kp=(40.0,) * dof, kv=(9.0,) * dof)
    batch = simulate_batch(spec, [[40.0] * dof, [25.0] * dof], [[9.0] * dof, [6.0] * dof])
    numbers += [*batch.I1, *batch.I2]
    episode = run_episode(spec)
    numbers += score_series(episode.plan.q_ref, episode.scored('q'), episode.scored('torque'), episode.plan.nominal,
                            episode.plan.k_max).values()
    return [float(number).hex() for number in numbers]


def report_loops() -> None:
    """loop_numbers() and how many compilations each of the loops' functions needed, as JSON on stdout."""
    numbers = loop_numbers()
    compiled = {name: sum(dispatcher.stats.cache_misses.values()) for name, dispatcher in loop_dispatchers().items()}
    print(json.dumps({'numbers': numbers, 'compiled': compiled}))


def run_loops(environment: dict[str, str]) -> tuple[dict, list[str]]:
    """report_loops() in a new process with `environment` added: its report, and what it said on stderr."""
    code = (f'import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import test_hostile_cache; '
            f'test_hostile_cache.report_loops()')
    env = {key: value for key, value in os.environ.items() if not key.startswith('NUMBA_CACHE')}
    done = subprocess.run([sys.executable, '-c', code], env={**env, **environment}, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.splitlines()[-1]), done.stderr.splitlines()


def loops_folder(cache: Path, module: str) -> Path:
    """The folder of the checked cache `cache` holding the compiled code of this checkout's `module`
    ('ddarm.physics.plant'); the session's cache may also hold other checkouts' folders."""
    return cache / 'loops' / dynamics._loops_folder(importlib.import_module(module).__file__).name


@pytest.fixture
def warm_cache(tmp_path):
    """A private cache folder holding what the session's own holds of the loops and the paper's arm's dynamics,
    and loop_numbers() as computed in this process."""
    from ddarm.physics.dynamics import load_chain

    expected = loop_numbers()  # also caches anything it compiles that the session's warm-up did not
    source, cache = dynamics.cache_folder(), tmp_path / 'cache'
    cache.mkdir(mode=0o700)
    (cache / 'loops').mkdir(mode=0o700)
    for module in LOOP_MODULES:
        folder = loops_folder(source, module)
        if folder.is_dir():
            shutil.copytree(folder, cache / 'loops' / folder.name)
    name = module_name(load_chain(None))
    (cache / 'dynamics' / '__pycache__').mkdir(mode=0o700, parents=True)
    (cache / 'dynamics').chmod(0o700)
    shutil.copy2(source / 'dynamics' / f'{name}.py', cache / 'dynamics')
    for path in (source / 'dynamics' / '__pycache__').glob(f'{name}.*'):
        shutil.copy2(path, cache / 'dynamics' / '__pycache__')
    return cache, expected


@pytest.mark.parametrize('module, function, kind, spoil', [
    ('ddarm.physics.plant', '_advance_one', 'index', _truncate), ('ddarm.physics.plant', '_advance_one', 'data', _flip),
    ('ddarm.episodes.engine', '_run_chunks', 'index', _garbage),
    ('ddarm.episodes.engine', '_run_chunks', 'data', _truncate),
])
def test_a_spoiled_cache_file_of_the_compiled_loops_is_discarded_saying_so_and_rebuilt(warm_cache, module, function,
                                                                                      kind, spoil):
    cache, expected = warm_cache
    stem = module.rsplit('.', 1)[1]
    folder = loops_folder(cache, module)
    line = loop_dispatchers()[f'{module}.{function}'].py_func.__code__.co_firstlineno  # older lines' files stay
    files = sorted(folder.glob(f'{stem}.{function}-{line}.*{"nbi" if kind == "index" else "nbc"}'))
    assert len(files) == 1, sorted(folder.iterdir())
    spoil(files[0])
    report, said = run_loops({dynamics.CACHE_ENVIRONMENT: str(cache)})
    assert report['numbers'] == expected
    assert len(said) == 1 and str(files[0]) in said[0] and 'damaged' in said[0] and 'deleted' in said[0], said
    assert report['compiled'][f'{module}.{function}'] == 1
    # Rebuilt: the next process loads every compiled loop from the cache, and has nothing to say.
    report, said = run_loops({dynamics.CACHE_ENVIRONMENT: str(cache)})
    assert report['numbers'] == expected
    assert said == []
    assert not any(report['compiled'].values()), report['compiled']


def test_numba_cache_dir_holding_planted_code_for_the_compiled_loops_does_not_run_it(tmp_path, warm_cache):
    from numba.core.caching import UserProvidedCacheLocator

    cache, expected = warm_cache
    marker = tmp_path / 'planted-code-ran'
    hostile = shared(tmp_path / 'numba-cache')
    # Where numba's own cache would look for each function under NUMBA_CACHE_DIR.
    for dispatcher in loop_dispatchers().values():
        function = dispatcher.py_func
        source = inspect.getfile(function)
        folder = hostile / UserProvidedCacheLocator.get_suitable_cache_subpath(source)
        folder.mkdir(exist_ok=True)
        name = (f'{Path(source).stem}.{function.__qualname__}-{function.__code__.co_firstlineno}.py'
                f'{sys.version_info[0]}{sys.version_info[1]}{getattr(sys, "abiflags", "")}.nbi')
        (folder / name).write_bytes(pickle.dumps(_Planted(marker)))
    report, said = run_loops({dynamics.CACHE_ENVIRONMENT: str(cache), 'NUMBA_CACHE_DIR': str(hostile)})
    assert not marker.exists()
    assert report['numbers'] == expected
    assert said == []


@pytest.mark.parametrize('open_folder', ['cache', 'loops'])
def test_the_compiled_loops_refuse_a_cache_folder_others_may_write_and_load_nothing_from_it(tmp_path, warm_cache,
                                                                                            open_folder):
    cache, _ = warm_cache
    marker = tmp_path / 'planted-code-ran'
    planted = sorted((cache / 'loops').glob('*/*.nbi'))
    assert planted
    for path in planted:
        path.write_bytes(pickle.dumps(_Planted(marker)))
    unsafe = shared(cache if open_folder == 'cache' else cache / 'loops', 0o770)
    # Only the indices' sums: a command that scores a recording runs no other compiled code.
    code = ('import numpy as np\n'
            'from ddarm.errors import DdarmError\n'
            'from ddarm.episodes.indices import score_series\n'
            'try:\n'
            '    score_series(np.zeros((3, 2)), np.zeros((3, 2)), np.ones((3, 2)), np.full((3, 2), 2.0), 2)\n'
            'except DdarmError as error:\n'
            '    raise SystemExit(str(error))\n')
    env = {key: value for key, value in os.environ.items() if not key.startswith('NUMBA_CACHE')}
    done = subprocess.run([sys.executable, '-c', code], env={**env, dynamics.CACHE_ENVIRONMENT: str(cache)},
                          capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and str(unsafe) in done.stderr and 'writable by' in done.stderr, done.stderr
    assert not marker.exists()


# Cache files with the right name that are not regular files: each once hung (a FIFO), read 5 GB into memory (a
# link to /dev/zero) or failed (a folder) every later command. A later command, a new process, must find the entry
# damaged, say so, remove it (never what a link points to) and compile again.
HOSTILE_STATE = (np.array([[0.3]]), np.array([[-1.2]]), np.array([[0.7]]))
# A guard against a hang only (a regression fails instead): a new process imports ddarm and compiles a 1-joint chain.
HOSTILE_TIMEOUT = 600


def report_dynamics(mass: float) -> None:
    """small_chain(mass)'s inverse dynamics at HOSTILE_STATE, loaded from the cache or compiled, as JSON on stdout."""
    torque = inverse_dynamics_at(small_chain(mass), *HOSTILE_STATE)
    print(json.dumps([float(value).hex() for value in np.ravel(torque)]))


def _fifo(path: Path, outside: Path) -> None:
    os.mkfifo(path)


def _link_to_zeros(path: Path, outside: Path) -> None:
    path.symlink_to('/dev/zero')


def _folder(path: Path, outside: Path) -> None:
    path.mkdir()
    (path / 'inside').write_bytes(b'kept in a folder in place of a cache file')


def _link_to_a_folder_outside(path: Path, outside: Path) -> None:
    path.symlink_to(outside, target_is_directory=True)


@pytest.mark.parametrize('kind', ['index', 'data', 'module'])
@pytest.mark.parametrize('hostile', [_fifo, _link_to_zeros, _folder, _link_to_a_folder_outside],
                         ids=['fifo', 'link to /dev/zero', 'folder', 'link to a folder outside'])
def test_a_cache_file_that_is_not_a_regular_file_is_removed_saying_so_and_a_later_command_compiles_again(
        tmp_path, monkeypatch, capsys, no_chain_loaded, kind, hostile):
    mass = 3.25
    chain = small_chain(mass)
    cache = tmp_path / 'cache'
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(cache))
    load_from_disk(chain)  # compiled into this test's cache (another test may have left the module imported)
    expected = [float(value).hex() for value in np.ravel(inverse_dynamics_at(chain, *HOSTILE_STATE))]
    folder = cache / 'dynamics'
    files = {'index': sorted((folder / '__pycache__').glob('*.nbi')),
             'data': sorted((folder / '__pycache__').glob('*.nbc')),
             'module': [folder / f'{module_name(chain)}.py']}[kind]
    assert len(files) == (2 if kind in ('index', 'data') else 1)
    outside = tmp_path / 'outside'
    outside.mkdir()
    (outside / 'kept').write_bytes(b'not the cache\'s')
    for path in files:
        path.unlink()
        hostile(path, outside)
    capsys.readouterr()
    code = (f'import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import test_hostile_cache; '
            f'test_hostile_cache.report_dynamics({mass!r})')
    env = {key: value for key, value in os.environ.items() if not key.startswith('NUMBA_CACHE')}
    done = subprocess.run([sys.executable, '-c', code], env={**env, dynamics.CACHE_ENVIRONMENT: str(cache)},
                          capture_output=True, text=True, timeout=HOSTILE_TIMEOUT)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == expected
    said = done.stderr.splitlines()
    assert len(said) == len(files), said
    for path, line in zip(files, said):
        assert str(path) in line and 'damaged' in line and 'deleted' in line, said
        status = os.lstat(path)  # written again: the index, data file or module is needed by the next command
        assert stat.S_ISREG(status.st_mode), f'{path} mode {status.st_mode:o}'
    assert sorted(outside.iterdir()) == [outside / 'kept']  # a link is removed, never what it points to
    # Rebuilt: the next process loads the compiled code from the cache, and has nothing to say.
    load_from_disk(chain)
    assert capsys.readouterr().err == ''
    kernels = [sys.modules[module_name(chain)].forward_dynamics, sys.modules[module_name(chain)].inverse_dynamics]
    assert all(sum(kernel.stats.cache_hits.values()) == 1 for kernel in kernels)


def test_a_cache_file_larger_than_any_ddarm_writes_is_not_read_and_is_discarded(tmp_path, monkeypatch, capsys,
                                                                               no_chain_loaded):
    chain = small_chain(3.5)
    cache = tmp_path / 'cache'
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(cache))
    load_from_disk(chain)
    index = sorted((cache / 'dynamics' / '__pycache__').glob('*.nbi'))[0]
    with open(index, 'r+b') as file:  # sparse: the size is what is checked, before anything is read
        file.truncate(dynamics.CACHE_FILE_LIMIT + 1)
    capsys.readouterr()
    load_from_disk(chain)
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 1 and str(index) in said[0] and f'{dynamics.CACHE_FILE_LIMIT + 1} bytes' in said[0], said
    assert 0 < index.stat().st_size < dynamics.CACHE_FILE_LIMIT


@pytest.mark.parametrize('where, why', [('afile', 'is not a folder'),
                                        ('afile/cache', 'cannot be made a folder: a folder above it is not a folder')])
def test_a_cache_dir_that_is_a_file_or_inside_one_is_refused_saying_so(tmp_path, monkeypatch, where, why):
    (tmp_path / 'afile').write_text('x')
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(tmp_path / where))
    with pytest.raises(ModelError, match=f'the dynamics cache {tmp_path / where} \\(\\$DDARM_CACHE_DIR\\) {why}: '):
        dynamics.cache_folder()
