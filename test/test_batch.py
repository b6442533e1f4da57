"""The batch engine against the plain reference loop (reference_episode.py), episode by episode (spec §5–8),
and the compiled dynamics against Pinocchio's own algorithms."""

import dataclasses
import importlib.util
import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from ddarm.physics.arm import ModelError
from ddarm.physics.dynamics import chain_from_model, inverse_dynamics_at
from ddarm.motion.programmed import ProgrammedMotion
from ddarm.episodes.engine import MAX_BATCH, BatchError, run_episode, simulate_batch
from ddarm.cli.main import main
from ddarm.episodes.spec import EpisodeSpec, plan_episode, plan_motion
from dynamics_checks import compiled_mass_matrix_and_acceleration
from reference_episode import reference_episode

CT_15 = dict(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3)
PD_10 = dict(controller='pd_gravity', kp=(2800.0, 2700.0, 350.0), kv=(560.0, 540.0, 70.0))
# Per controller: the ω-rule gains, a perturbation of them, and gains that diverge.
GAINS = {
    'computed_torque': ([[225.0] * 3, [150.0, 400.0, 90.0], [1e6] * 3], [[30.0] * 3, [20.0, 45.0, 25.0], [3e3] * 3]),
    'pd_gravity': ([[2800.0, 2700.0, 350.0], [5000.0, 2000.0, 500.0], [1e7] * 3],
                   [[560.0, 540.0, 70.0], [700.0, 400.0, 90.0], [10.0] * 3]),
}
TOLERANCE = 1e-9
ROOT = Path(__file__).resolve().parents[1]


def assert_member_matches(batch, member, scalar):
    """Member `member` of a batch is the reference episode: indices to 1e-9 relative, same divergence."""
    for key, value in scalar.indices.items():
        assert batch.indices(member)[key] == pytest.approx(value, rel=TOLERANCE, abs=1e-300), key
    assert bool(batch.diverged[member]) == scalar.diverged
    assert batch.diverged_at[member] == (scalar.diverged_at if scalar.diverged else -1)
    assert batch.samples_scored[member] == len(scalar.torque)


@pytest.mark.parametrize('controller', sorted(GAINS))
@pytest.mark.parametrize('delay', [0, 1, 2])
@pytest.mark.parametrize('torque_limit', ['none', 'paper'])
@pytest.mark.parametrize('tau', [0.0, 0.1])
def test_every_member_is_the_reference_episode(controller, delay, torque_limit, tau):
    kp, kv = GAINS[controller]
    template = EpisodeSpec(controller=controller, kp=kp[0], kv=kv[0], delay=delay, torque_limit=torque_limit,
                           tau=tau)
    batch = simulate_batch(template, kp, kv)
    for member in range(len(kp)):
        scalar = reference_episode(dataclasses.replace(template, kp=kp[member], kv=kv[member]))
        assert_member_matches(batch, member, scalar)


@pytest.mark.parametrize('controller, delay', [('computed_torque', 1), ('computed_torque', 2), ('pd_gravity', 0)])
def test_a_diverging_member_stops_where_the_reference_does_and_the_others_go_on(controller, delay):
    kp, kv = GAINS[controller]
    template = EpisodeSpec(controller=controller, kp=kp[0], kv=kv[0], delay=delay, tau=0.1)
    batch = simulate_batch(template, kp, kv)
    assert batch.diverged.tolist() == [False, False, True]
    assert 0 < batch.diverged_at[2] < batch.plan.k_max
    for member in range(3):
        assert_member_matches(batch, member, reference_episode(dataclasses.replace(template, kp=kp[member],
                                                                                   kv=kv[member])))


def test_plant_options_and_mass_mismatch_match_the_reference_episode():
    template = EpisodeSpec(**CT_15, delay=1, tau=0.1, torque_limit='paper', external_torque=(5.0, 5.0, 1.0),
                           viscous_friction=(1.0, 1.0, 0.5), coulomb_friction=(0.5, 0.5, 0.2),
                           mass_scale=(1.0, 1.1, 0.9))
    kp, kv = GAINS['computed_torque']
    batch = simulate_batch(template, kp, kv)
    for member in range(3):
        assert_member_matches(batch, member, reference_episode(dataclasses.replace(template, kp=kp[member],
                                                                                   kv=kv[member])))


def test_a_batch_of_one_is_the_reference_episode_with_its_series():
    template = EpisodeSpec(**PD_10, delay=0, tau=0.1, torque_limit='paper')
    batch = simulate_batch(template, [template.kp], [template.kv], series=True)
    scalar = reference_episode(template)
    assert batch.size == 1
    assert_member_matches(batch, 0, scalar)
    for name in ('q', 'v', 'command', 'torque'):
        np.testing.assert_allclose(batch.scored(name), getattr(scalar, name), rtol=1e-9, atol=1e-9)
    # run_episode is this batch of one, series and all.
    alone = run_episode(template)
    assert alone.indices() == batch.indices()
    for name in ('q', 'v', 'command', 'torque'):
        np.testing.assert_array_equal(alone.scored(name), batch.scored(name))


def test_the_series_of_a_diverged_member_end_where_it_was_scored():
    kp, kv = GAINS['computed_torque']
    batch = simulate_batch(EpisodeSpec(**CT_15), kp, kv, series=True)
    stop = batch.samples_scored[2]
    assert stop < batch.plan.k_max + 1
    assert np.all(np.isfinite(batch.torque[2, :stop])) and np.all(np.isnan(batch.torque[2, stop:]))
    assert np.all(np.isfinite(batch.q[:2]))


def test_per_episode_tau_limits_and_mass_scale_are_each_members_own_episode():
    template = EpisodeSpec(**CT_15, delay=1)
    kp = np.array([[225.0] * 3, [150.0, 400.0, 90.0], [300.0, 200.0, 250.0]])
    kv = np.array([[30.0] * 3, [20.0, 45.0, 25.0], [35.0, 25.0, 30.0]])
    tau = np.array([0.0, 0.05, 0.1])
    limits = np.array([[400.0, 600.0, 200.0], [300.0, 500.0, 150.0], [1e4, 1e4, 1e4]])
    scales = np.array([[1.0, 1.0, 1.0], [1.0, 1.2, 0.8], [0.9, 1.1, 1.3]])
    batch = simulate_batch(template, kp, kv, tau=tau, torque_limit=limits, mass_scale=scales)
    for member in range(3):
        spec = dataclasses.replace(template, kp=kp[member], kv=kv[member], tau=tau[member],
                                   torque_limit=tuple(limits[member]), mass_scale=tuple(scales[member]))
        assert_member_matches(batch, member, reference_episode(spec))


def test_the_result_does_not_depend_on_the_number_of_threads():
    rng = np.random.default_rng(5)
    kp = 225.0 * np.exp(0.3 * rng.normal(size=(37, 3)))
    kv = 30.0 * np.exp(0.3 * rng.normal(size=(37, 3)))
    template = EpisodeSpec(**CT_15, tau=0.1)
    one, two = simulate_batch(template, kp, kv, threads=1), simulate_batch(template, kp, kv, threads=2)
    np.testing.assert_array_equal(one.I, two.I)
    np.testing.assert_array_equal(one.diverged_at, two.diverged_at)


@pytest.mark.parametrize('size, threads, arm', [(5, 1, None), (12, 1, None), (10, 2, None), (15, 2, None),
                                                (90, 2, None), (13, 2, 'ur5')])
def test_a_padded_chunk_gives_each_member_its_own_episode_to_the_last_bit(size, threads, arm):
    # Chunks with 4 to 7 members left over past a whole vector run padded (VECTOR_LANES): the spare lanes repeat a
    # member and are dropped; every member, one that diverges among them, is its batch of one, series and all. The
    # UR5's dynamics run in blocks copied to the stack (ddarm.physics.generated), the paper's arm's directly.
    rng = np.random.default_rng(9)
    n = 3 if arm is None else 6
    kp = 225.0 * np.exp(0.3 * rng.normal(size=(size, n)))
    kv = 30.0 * np.exp(0.3 * rng.normal(size=(size, n)))
    kp[size - 2], kv[size - 2] = 1e6, 3e3
    template = EpisodeSpec(**CT_15, tau=0.1) if arm is None else EpisodeSpec(
        controller='computed_torque', kp=kp[0], kv=kv[0], urdf=str(ROOT / 'config' / 'arms' / arm / f'{arm}.urdf'),
        motion=str(ROOT / 'config' / 'arms' / arm / f'{arm}-motion.yaml'), delay=1)
    batch = simulate_batch(template, kp, kv, series=True, threads=threads)
    assert batch.I.shape == (size,) and batch.q.shape[0] == size and batch.diverged[size - 2]
    for member in range(size):
        alone = simulate_batch(template, kp[member:member + 1], kv[member:member + 1], series=True, threads=1)
        assert batch.I[member] == alone.I[0] and batch.diverged_at[member] == alone.diverged_at[0]
        assert batch.samples_scored[member] == alone.samples_scored[0]
        for series in ('q', 'v', 'command', 'torque'):
            np.testing.assert_array_equal(getattr(batch, series)[member], getattr(alone, series)[0])


@pytest.mark.parametrize('case, delay', [(CT_15, 1), (PD_10, 0)])
def test_the_default_substeps_keep_the_indices_within_1e_6_of_40_substeps(case, delay):
    # The ω-rule gains in the paper's settings: the reference case, with and without its
    # disturbance and limits. (Gains that swing the arm at 100+ rad/s need more substeps.)
    kp, kv = [case['kp']], [case['kv']]
    for spec in (EpisodeSpec(**case, delay=delay), EpisodeSpec(**case, delay=delay, tau=0.1, torque_limit='paper')):
        default = simulate_batch(spec, kp, kv)
        reference = simulate_batch(dataclasses.replace(spec, substeps=40), kp, kv)
        for got, want in ((default.I1, reference.I1), (default.I2, reference.I2), (default.I, reference.I)):
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)


# A serial arm unlike the paper's: prismatic and revolute joints, aligned and unaligned axes,
# turned placements and inertial frames (nothing here is specific to the paper's arm).
GENERIC_URDF = """<?xml version="1.0"?>
<robot name="generic5">
  <link name="base"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0.1 0.0 0.3" rpy="0.2 0.0 0.4"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="10"/></joint>
  <link name="l1"><inertial><origin xyz="0.05 0.1 -0.02" rpy="0.1 0.2 0.3"/><mass value="2.0"/>
    <inertia ixx="0.3" ixy="0.01" ixz="0.02" iyy="0.2" iyz="0.03" izz="0.25"/></inertial></link>
  <joint name="j2" type="prismatic"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.0 0.2 0.1" rpy="0.0 0.3 0.0"/><axis xyz="0.6 0.0 0.8"/>
    <limit lower="-1" upper="1" effort="100" velocity="10"/></joint>
  <link name="l2"><inertial><origin xyz="0.0 0.0 0.2" rpy="0 0 0"/><mass value="1.5"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.12" iyz="0" izz="0.05"/></inertial></link>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.3 0.0 0.0" rpy="-0.5 0.1 0.2"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="10"/></joint>
  <link name="l3"><inertial><origin xyz="0.25 0.0 0.0" rpy="0 0 0"/><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.08" iyz="0" izz="0.08"/></inertial></link>
  <joint name="j4" type="prismatic"><parent link="l3"/><child link="l4"/>
    <origin xyz="0.5 0.0 0.0" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="100" velocity="10"/></joint>
  <link name="l4"><inertial><origin xyz="0.0 0.05 0.1" rpy="0 0 0"/><mass value="0.5"/>
    <inertia ixx="0.02" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.01"/></inertial></link>
  <joint name="j5" type="revolute"><parent link="l4"/><child link="l5"/>
    <origin xyz="0.0 0.0 0.2" rpy="0.3 -0.2 0.1"/><axis xyz="0.0 -0.6 0.8"/>
    <limit lower="-3" upper="3" effort="100" velocity="10"/></joint>
  <link name="l5"><inertial><origin xyz="0.1 0.02 0.0" rpy="0 0.4 0"/><mass value="0.4"/>
    <inertia ixx="0.01" ixy="0.001" ixz="0" iyy="0.015" iyz="0" izz="0.012"/></inertial></link>
</robot>
"""


@pytest.mark.parametrize('controller', ['computed_torque', 'pd_gravity'])
def test_any_serial_urdf_arm_runs_as_in_the_reference_loop(tmp_path, controller):
    urdf = tmp_path / 'generic5.urdf'
    urdf.write_text(GENERIC_URDF)
    motion = tmp_path / 'generic5-motion.yaml'
    motion.write_text('joint_names: [j1, j2, j3, j4, j5]\nduration: 1.0\nprofile: bang_bang\n'
                      'start: [0.1, 0.0, -0.3, 0.1, 0.5]\ngoal: [0.8, 0.2, 0.4, -0.1, -0.5]\n')
    kp = np.array([[100.0] * 5, [150.0, 200.0, 80.0, 300.0, 60.0]])
    kv = np.array([[20.0] * 5, [25.0, 30.0, 15.0, 35.0, 12.0]])
    template = EpisodeSpec(controller=controller, kp=kp[0], kv=kv[0], urdf=str(urdf), motion=str(motion), delay=1,
                           torque_limit='paper', mass_scale=(1.1, 0.9, 1.0, 1.2, 0.8))
    plan = plan_episode(template)
    batch = simulate_batch(template, kp, kv, plan=plan)
    for member in range(2):
        scalar = reference_episode(dataclasses.replace(template, kp=kp[member], kv=kv[member]), plan)
        assert_member_matches(batch, member, scalar)


# A tree (two branches from l1) with joints along -x, +z, -z, -y and a prismatic -x: the generated code's
# exact-axis rotations of every sign, and a parent that is not the joint before.
TREE_URDF = """<?xml version="1.0"?>
<robot name="tree5">
  <link name="base"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.2" rpy="0 0 0"/><axis xyz="-1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l1"><inertial><origin xyz="0 0.1 0.1"/><mass value="2.0"/>
    <inertia ixx="0.2" ixy="0.01" ixz="0" iyy="0.3" iyz="0.02" izz="0.1"/></inertial></link>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0.3 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l2"><inertial><origin xyz="0.2 0 0"/><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.05" iyz="0" izz="0.05"/></inertial></link>
  <joint name="j3" type="revolute"><parent link="l1"/><child link="l3"/>
    <origin xyz="0 -0.3 0" rpy="0.3 0 0"/><axis xyz="0 0 -1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l3"><inertial><origin xyz="0.1 0.05 0"/><mass value="1.5"/>
    <inertia ixx="0.02" ixy="0" ixz="0.003" iyy="0.04" iyz="0" izz="0.03"/></inertial></link>
  <joint name="j4" type="revolute"><parent link="l2"/><child link="l4"/>
    <origin xyz="0.4 0 0" rpy="0 0 0.2"/><axis xyz="0 -1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l4"><inertial><origin xyz="0.15 0 0"/><mass value="0.7"/>
    <inertia ixx="0.005" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <joint name="j5" type="prismatic"><parent link="l3"/><child link="l5"/>
    <origin xyz="0.2 0 0" rpy="0 0.4 0"/><axis xyz="-1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <link name="l5"><inertial><origin xyz="0 0 0.05"/><mass value="0.5"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.005"/></inertial></link>
</robot>
"""


def pinocchio_model(name):
    """The paper's arm, the generic one or the tree above, with a non-zero armature on every joint."""
    model = pin.buildModelFromUrdf(str(ROOT / 'config' / 'ddarm.urdf')) if name == 'paper' else (
        pin.buildModelFromXML(GENERIC_URDF if name == 'generic' else TREE_URDF))
    model.armature = np.linspace(0.05, 0.3, model.nv)
    return model


def random_states(model, count, seed):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-np.pi, np.pi, (count, model.nv)), rng.uniform(-3, 3, (count, model.nv)),
            rng.uniform(-10, 10, (count, model.nv)))


def scaled(model, mass_scale):
    """A copy of `model` whose link i has mass and central inertia times mass_scale[i], as the plant's."""
    model = model.copy()
    for joint_id, factor in enumerate(mass_scale, start=1):
        inertia = model.inertias[joint_id]
        model.inertias[joint_id] = pin.Inertia(factor * inertia.mass, inertia.lever, factor * inertia.inertia)
    return model


@pytest.mark.parametrize('name', ['paper', 'generic', 'tree'])
@pytest.mark.parametrize('with_scale', [False, True])
def test_the_compiled_dynamics_are_pinocchios_rnea_crba_and_aba(name, with_scale):
    # Random states, armature on every joint, revolute and prismatic joints (generic), a plant mass scale.
    model = pinocchio_model(name)
    chain = chain_from_model(model)
    mass_scale = np.linspace(0.8, 1.3, model.nv) if with_scale else np.ones(model.nv)
    plant = scaled(model, mass_scale)
    data = plant.createData()
    q, v, a = random_states(model, 40, seed=11)
    torque = inverse_dynamics_at(chain, q, v, a, mass_scale=mass_scale if with_scale else None)
    mass_matrix, acceleration = compiled_mass_matrix_and_acceleration(chain, q, v, torque, mass_scale)
    for m in range(len(q)):
        expected_torque = pin.rnea(plant, data, q[m], v[m], a[m])
        np.testing.assert_allclose(torque[m], expected_torque, rtol=1e-12, atol=1e-11 * np.max(np.abs(expected_torque)))
        upper = pin.crba(plant, data, q[m])
        expected_mass = np.triu(upper) + np.triu(upper, 1).T
        np.testing.assert_allclose(mass_matrix[m], expected_mass, rtol=1e-10, atol=1e-10 * np.max(expected_mass))
        expected_acceleration = pin.aba(plant, data, q[m], v[m], torque[m])
        np.testing.assert_allclose(expected_acceleration, a[m], rtol=1e-9, atol=1e-9)  # Pinocchio's own round trip
        np.testing.assert_allclose(acceleration[m], expected_acceleration, rtol=1e-10, atol=1e-10)


def test_the_chain_refuses_joints_other_than_revolute_and_prismatic():
    model = pin.Model()
    model.addJoint(0, pin.JointModelTranslation(), pin.SE3.Identity(), 'slider')
    with pytest.raises(ModelError, match='slider'):
        chain_from_model(model)


@pytest.mark.parametrize('kp, kv, problem', [
    ([225.0] * 3, [30.0] * 3, r'kp must have shape \(B, 3\)'),
    ([[225.0] * 2], [[30.0] * 2], r'kp must have shape \(B, 3\)'),
    ([[225.0] * 3] * 2, [[30.0] * 3], 'same shape'),
    ([[225.0] * 3, [225.0, np.nan, 225.0]], [[30.0] * 3] * 2, 'kp must be finite and positive: episode 1'),
    ([[225.0] * 3], [[30.0, 0.0, 30.0]], 'kv must be finite and positive: episode 0'),
    ([[225.0] * 3], [[30.0, -1.0, np.inf]], 'kv must be finite and positive'),
    (np.zeros((0, 3)), np.zeros((0, 3)), 'B = 0'),
    (np.ones((MAX_BATCH + 1, 3)), np.ones((MAX_BATCH + 1, 3)), f'B = {MAX_BATCH + 1}'),
    ([['a', 'b', 'c']], [[30.0] * 3], 'kp must be numbers'),
])
def test_bad_gains_are_refused_with_the_problem_named(kp, kv, problem):
    with pytest.raises(BatchError, match=problem):
        simulate_batch(EpisodeSpec(**CT_15), kp, kv)


@pytest.mark.parametrize('options, problem', [
    (dict(tau=[0.1]), r'tau must have shape \(2,\)'),
    (dict(tau=[0.1, 2.0]), 'episode 1'),
    (dict(torque_limit=[[1.0, 2.0, 3.0]]), r'torque_limit must have shape \(2, 3\)'),
    (dict(torque_limit=[[1.0, 2.0, 3.0], [1.0, 0.0, 3.0]]), 'torque_limit must be finite and positive'),
    (dict(mass_scale=[[1.0, 1.0, 1.0], [1.0, 1.0, np.nan]]), 'mass_scale must be finite and positive: episode 1'),
    (dict(threads=0), 'threads'),
    (dict(series=True, plan=None, tau=None, threads=1.5), 'threads'),
])
def test_bad_per_episode_options_are_refused_with_the_problem_named(options, problem):
    with pytest.raises(BatchError, match=problem):
        simulate_batch(EpisodeSpec(**CT_15), [[225.0] * 3] * 2, [[30.0] * 3] * 2, **options)


def test_per_episode_tau_disturbs_the_given_plans_own_motion_never_the_paper_trajectory():
    spec = EpisodeSpec(**CT_15)
    motion = ProgrammedMotion(np.zeros(3), np.ones(3), 1.0)
    plan = plan_motion(spec, motion, np.arange(101) * 0.01)
    batch = simulate_batch(spec, [[225.0] * 3], [[30.0] * 3], tau=[0.1], plan=plan, series=True)
    np.testing.assert_array_equal(batch.v[0, 0], -motion.sample(0.1)[1])
    recorded = dataclasses.replace(plan, motion=None)  # a plan read back from a bag knows no motion
    with pytest.raises(BatchError, match='tau'):
        simulate_batch(spec, [[225.0] * 3], [[30.0] * 3], tau=[0.1], plan=recorded)


def test_bad_template_plant_options_are_refused_as_run_episode_refuses_them():
    with pytest.raises(BatchError, match='external_torque'):
        simulate_batch(EpisodeSpec(**CT_15, external_torque=(1.0, np.nan, 0.0)), [[225.0] * 3], [[30.0] * 3])


def test_ddarm_bench_compares_the_two_paths_on_the_episodes_both_ran(capsys):
    assert main(['bench', '--episodes', '4', '--scalar-episodes', '2', '--json']) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures['B'] == 4 and figures['scalar_episodes'] == 2 and figures['substeps'] == 8
    assert figures['max_rel_index_diff'] < 1e-9 and figures['divergence_disagreements'] == 0
    assert figures['batch_episodes_per_s'] > 0 and figures['scalar_episodes_per_s'] > 0
    assert figures['peak_rss_mib'] > 0
    assert [rate['B'] for rate in figures['batch_sizes']] == [8, 64, 1000]
    many = figures['many_joint_arm']
    assert many['joints'] == 7 and Path(many['urdf']).name == 'panda.urdf'
    assert all(rate['episodes_per_s'] > 0 for rate in figures['batch_sizes'] + many['batch_sizes'])


def test_the_engine_equals_bench_closed_forms_hand_written_loop_for_the_papers_arm():
    # bench/closed_form.py writes M, V, G of docs/model-specification.md §3 as formulas (V from M's Christoffel
    # symbols) and the loop by hand: its indices are the engine's for every member, so the benchmark compares equal
    # work.
    spec = importlib.util.spec_from_file_location('closed_form', ROOT / 'bench' / 'closed_form.py')
    closed_form = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(closed_form)
    template = closed_form.REFERENCE
    plan = plan_episode(template)
    kp, kv = closed_form.perturbed_gains(template, 24, seed=3)
    episodes = simulate_batch(template, kp, kv, plan=plan)
    first, second = closed_form.closed_form_batch(
        kp, kv, np.array(plan.q0, dtype=float), np.tile(plan.v0, (24, 1)), plan.q_ref, plan.v_ref, plan.a_ref,
        plan.nominal, closed_form.error_weights(3), closed_form.torque_weights(plan.nominal), template.period,
        template.substeps, closed_form.DEFAULT_MAX_POSITION, closed_form.DEFAULT_MAX_VELOCITY)
    np.testing.assert_allclose(first / plan.k_max, episodes.I1, rtol=1e-11)
    np.testing.assert_allclose(second / plan.k_max, episodes.I2, rtol=1e-11)
