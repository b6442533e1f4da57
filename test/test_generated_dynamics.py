"""The generated dynamics' cache (ddarm.physics.dynamics): where it lives, that a module is written once and
never half-seen, and refusals. Their numbers are checked against Pinocchio in test_batch.py and test_arms.py."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import numpy as np
import pinocchio as pin
import pytest
from dynamics_checks import compiled_mass_matrix_and_acceleration

from ddarm.physics import dynamics, generated
from ddarm.physics.arm import ModelError
from ddarm.physics.dynamics import (cache_folder, chain_from_model, compiled_dynamics, forward_dynamics_at,
                                    inverse_dynamics_at, load_chain)
from ddarm.physics.generated import dynamics_source


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    """An empty cache folder, and no chain loaded yet in this process."""
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(tmp_path / 'cache'))
    monkeypatch.setattr(dynamics, '_loaded', {})
    return tmp_path / 'cache'


def shifted_chain(shift: float):
    """The paper's arm with link 3 a little heavier: a chain whose code no cache holds yet."""
    chain = load_chain(None)
    mass = chain.mass.copy()
    mass[2] += shift
    return dynamics.Chain(**{**chain.__dict__, 'mass': mass})


def test_the_cache_is_the_named_folder_else_the_users_else_a_private_temporary_one(tmp_path, monkeypatch):
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(tmp_path / 'given'))
    assert cache_folder() == tmp_path / 'given'
    monkeypatch.delenv(dynamics.CACHE_ENVIRONMENT)
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'xdg'))
    assert cache_folder() == tmp_path / 'xdg' / 'ddarm'
    # A cache home that cannot be used (here a file where the folder should be): the user's private temporary one.
    (tmp_path / 'blocked').write_text('')
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'blocked'))
    monkeypatch.setenv('TMPDIR', str(tmp_path / 'tmp'))
    (tmp_path / 'tmp').mkdir()
    monkeypatch.setattr(dynamics.tempfile, 'tempdir', None)
    private = cache_folder()
    assert private == tmp_path / 'tmp' / f'ddarm-{os.getuid()}'
    assert private.stat().st_mode & 0o077 == 0


def test_a_temporary_folder_others_may_write_is_not_used(tmp_path, monkeypatch):
    (tmp_path / 'blocked').write_text('')
    monkeypatch.delenv(dynamics.CACHE_ENVIRONMENT, raising=False)
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'blocked'))
    (tmp_path / 'tmp').mkdir()
    monkeypatch.setenv('TMPDIR', str(tmp_path / 'tmp'))
    monkeypatch.setattr(dynamics.tempfile, 'tempdir', None)
    shared = tmp_path / 'tmp' / f'ddarm-{os.getuid()}'
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)
    monkeypatch.setattr(dynamics, '_process_folder', None)
    folder = cache_folder()
    assert folder != shared and folder.parent == tmp_path / 'tmp' and folder.stat().st_mode & 0o077 == 0
    assert cache_folder() == folder  # one per process


def test_a_module_is_written_once_and_a_corrupted_one_is_replaced(fresh_cache):
    source = dynamics_source(shifted_chain(0.25))
    name, path = dynamics._module_file(source)
    assert path.parent == fresh_cache / 'dynamics' and path.read_text(encoding='utf-8') == source
    stamp = path.stat().st_mtime_ns
    assert dynamics._module_file(source) == (name, path) and path.stat().st_mtime_ns == stamp  # numba's stamp holds
    path.write_text('broken')
    dynamics._module_file(source)
    assert path.read_text(encoding='utf-8') == source
    assert [file.name for file in path.parent.iterdir() if file.suffix == '.tmp'] == []


def test_threads_asking_for_a_new_chain_at_once_all_get_its_compiled_dynamics(fresh_cache):
    chain = shifted_chain(0.5)
    results, errors = [], []

    def ask():
        try:
            results.append(compiled_dynamics(chain))
        except Exception as error:  # noqa: BLE001 - the test reports whatever a thread met
            errors.append(error)

    threads = [threading.Thread(target=ask) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == [] and len({id(result) for result in results}) == 1
    q = np.array([[0.1, 0.4, -0.3]])
    torque = inverse_dynamics_at(chain, q, np.zeros((1, 3)), np.array([[1.0, 2.0, 3.0]]))
    np.testing.assert_allclose(forward_dynamics_at(chain, q, np.zeros((1, 3)), torque), [[1.0, 2.0, 3.0]],
                               rtol=1e-12)


def test_a_folder_that_cannot_be_written_is_named_in_the_error(tmp_path, monkeypatch):
    (tmp_path / 'file').write_text('')
    monkeypatch.setenv(dynamics.CACHE_ENVIRONMENT, str(tmp_path / 'file'))
    monkeypatch.setattr(dynamics, '_loaded', {})
    with pytest.raises(ModelError, match=f'{tmp_path / "file"}.*{dynamics.CACHE_ENVIRONMENT}'):
        compiled_dynamics(shifted_chain(0.75))


def test_states_of_the_wrong_length_are_refused_before_the_compiled_code_runs():
    chain = load_chain(None)
    with pytest.raises(ValueError, match='3 joint values'):
        inverse_dynamics_at(chain, np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)))


def test_a_chain_with_a_non_finite_constant_or_no_inertia_on_a_joint_is_refused():
    chain = load_chain(None)
    with pytest.raises(ModelError, match='non-finite'):
        dynamics_source(dynamics.Chain(**{**chain.__dict__, 'mass': np.array([1.0, np.inf, 10.0])}))
    # Link 1 is a point mass on joint 1's axis: with no inertia about z and no armature, M11 is 0 everywhere.
    massless = dynamics.Chain(**{**chain.__dict__, 'inertia': np.zeros((3, 3, 3)), 'mass': np.zeros(3)})
    with pytest.raises(ModelError, match='singular'):
        dynamics_source(massless)


def test_a_second_process_loads_the_compiled_dynamics_the_first_one_cached(tmp_path):
    # numba rebuilds a cached function's environment by importing its module by name: the second
    # process takes the cache's path, which the first one (compiling) does not.
    script = ('import sys; import numpy as np; from ddarm.physics import dynamics; '
              'chain = dynamics.load_chain(None); '
              'chain = dynamics.Chain(**{**chain.__dict__, "mass": chain.mass + [0, 0, 1.5]}); '
              'print(dynamics.inverse_dynamics_at(chain, np.array([[0.1, 0.4, -0.3]]), np.ones((1, 3)), '
              'np.ones((1, 3))).tolist())')
    environment = {**os.environ, dynamics.CACHE_ENVIRONMENT: str(tmp_path / 'cache')}
    runs = [subprocess.run([sys.executable, '-c', script], env=environment, capture_output=True, text=True,
                           timeout=300) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    assert runs[0].stdout == runs[1].stdout
    assert list((tmp_path / 'cache' / 'dynamics' / '__pycache__').glob('*.nbi'))


def random_model(n: int, seed: int, tree: bool) -> pin.Model:
    """n joints (a tree, or one after the other) of every kind the chain takes: revolute and prismatic about
    unaligned axes, about x, z and y; random placements, inertias and armature."""
    rng = np.random.default_rng(seed)
    model = pin.Model()
    for i in range(n):
        parent = int(rng.integers(0, i)) + 1 if tree and i > 0 else i
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        joint = [pin.JointModelRevoluteUnaligned(*axis), pin.JointModelRX(), pin.JointModelPrismaticUnaligned(*axis),
                 pin.JointModelRZ(), pin.JointModelPY()][i % 5]
        rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        placement = pin.SE3(rotation * np.sign(np.linalg.det(rotation)), rng.normal(size=3) * 0.3)
        joint_id = model.addJoint(parent, joint, placement, f'j{i}')
        shape = rng.normal(size=(3, 3)) * 0.1
        model.appendBodyToJoint(joint_id, pin.Inertia(rng.uniform(0.5, 2.0), rng.normal(size=3) * 0.1,
                                                      shape @ shape.T + 0.01 * np.eye(3)), pin.SE3.Identity())
    model.armature = rng.uniform(0.05, 0.3, n)
    return model


@pytest.mark.parametrize('n, tree', [(2 * generated.UNROLLED_JOINTS, True), (generated.UNROLLED_JOINTS + 1, False)])
def test_looped_dynamics_beyond_the_unrolled_size_are_pinocchios(fresh_cache, n, tree):
    model = random_model(n, seed=n, tree=tree)
    chain = chain_from_model(model)
    assert 'for i in range(N)' in dynamics_source(chain)
    data = model.createData()
    rng = np.random.default_rng(5)
    q, v, a = rng.uniform(-3, 3, (8, n)), rng.uniform(-3, 3, (8, n)), rng.uniform(-10, 10, (8, n))
    mass_scale = rng.uniform(0.8, 1.3, n)
    plant = model.copy()
    for joint_id, factor in enumerate(mass_scale, start=1):
        inertia = plant.inertias[joint_id]
        plant.inertias[joint_id] = pin.Inertia(factor * inertia.mass, inertia.lever, factor * inertia.inertia)
    torque = inverse_dynamics_at(chain, q, v, a, mass_scale=mass_scale)
    mass_matrix, acceleration = compiled_mass_matrix_and_acceleration(chain, q, v, torque, mass_scale)
    for m in range(len(q)):
        expected_torque = pin.rnea(plant, data, q[m], v[m], a[m])
        np.testing.assert_allclose(torque[m], expected_torque, rtol=1e-12, atol=1e-12 * np.max(np.abs(expected_torque)))
        # M from Pinocchio's RNEA, column by column (its crba is off for PrismaticUnaligned joints in a tree).
        gravity = pin.rnea(plant, data, q[m], np.zeros(n), np.zeros(n)).copy()
        expected_mass = np.stack([pin.rnea(plant, data, q[m], np.zeros(n), np.eye(n)[j]) - gravity
                                  for j in range(n)], axis=1)
        np.testing.assert_allclose(mass_matrix[m], expected_mass, rtol=1e-9, atol=1e-10 * np.max(expected_mass))
        np.testing.assert_allclose(acceleration[m], pin.aba(plant, data, q[m], v[m], torque[m]), rtol=1e-9,
                                   atol=1e-9)


@pytest.mark.parametrize('n, tree', [(generated.UNROLLED_JOINTS, True), (7, False), (3, False)])
def test_a_state_gets_the_same_bits_in_a_whole_block_in_a_partial_one_and_alone(fresh_cache, n, tree):
    # The unrolled kernels run VECTOR_LANES states at a time in SIMD registers and the rest one by one: 2 whole blocks
    # and 3 states over, against each state in a call of its own.
    chain = chain_from_model(random_model(n, seed=3 * n, tree=tree))
    assert 'for i in range(N)' not in dynamics_source(chain)
    rng = np.random.default_rng(n)
    count = 2 * generated.VECTOR_LANES + 3
    q, v, a = rng.uniform(-3, 3, (count, n)), rng.uniform(-3, 3, (count, n)), rng.uniform(-10, 10, (count, n))
    mass_scale = rng.uniform(0.8, 1.3, (count, n))
    torque = inverse_dynamics_at(chain, q, v, a, mass_scale=mass_scale)
    acceleration = forward_dynamics_at(chain, q, v, torque, mass_scale=mass_scale)
    for m in range(count):
        alone = slice(m, m + 1)
        np.testing.assert_array_equal(inverse_dynamics_at(chain, q[alone], v[alone], a[alone], mass_scale[alone]),
                                      torque[alone])
        np.testing.assert_array_equal(forward_dynamics_at(chain, q[alone], v[alone], torque[alone],
                                                          mass_scale[alone]), acceleration[alone])


def test_the_generated_code_grows_linearly_with_the_joint_count_beyond_the_unrolled_size():
    sizes = {n: len(dynamics_source(chain_from_model(random_model(n, seed=1, tree=False)))) for n in (16, 32, 64)}
    per_joint = [(sizes[32] - sizes[16]) / 16, (sizes[64] - sizes[32]) / 32]
    # Each joint adds its constants (about 35 numbers), not code: unrolled, 16 to 32 joints added 60 kB a joint.
    assert max(per_joint) < 1000 and max(per_joint) < 1.2 * min(per_joint), sizes


def serial_urdf(path, joints: int):
    links = ['<link name="l0"/>'] + [
        f'<joint name="j{i}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/><origin xyz="0 0 0.1"/>'
        f'<axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="10" velocity="3"/></joint>'
        f'<link name="l{i + 1}"><inertial><mass value="0.1"/><inertia ixx="1e-3" ixy="0" ixz="0" iyy="1e-3" iyz="0" '
        f'izz="1e-3"/></inertial></link>' for i in range(joints)]
    path.write_text(f'<?xml version="1.0"?><robot name="snake">{"".join(links)}</robot>')
    return str(path)


def test_a_chain_beyond_the_joint_bound_is_refused_naming_the_count_and_the_bound(tmp_path, monkeypatch):
    urdf = serial_urdf(tmp_path / 'snake.urdf', 200)
    monkeypatch.setattr(generated, '_Chain', None)  # nothing may be generated
    with pytest.raises(ModelError, match=f'200 joints.*at most {dynamics.MAX_JOINTS}'):
        load_chain(urdf)
    chain = load_chain(None)
    many = dynamics.Chain(**{key: np.repeat(value, 22, axis=0) if key != 'gravity' else value
                             for key, value in chain.__dict__.items()})
    with pytest.raises(ModelError, match=f'66 joints.*at most {dynamics.MAX_JOINTS}'):
        dynamics_source(many)
    # Up to the bound, every joint controlled: loaded, and the rest of them locked is a small chain.
    assert load_chain(serial_urdf(tmp_path / 'long.urdf', dynamics.MAX_JOINTS)).dof == dynamics.MAX_JOINTS
    assert load_chain(urdf, ('j0', 'j1')).dof == 2
