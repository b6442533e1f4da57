"""A URDF's <dynamics damping friction> and <ddarm:armature>: read by the plant and by the law's model.

Checked against what they mean, written out here: the armature on M(q)'s diagonal (Pinocchio's crba and aba with
the model's armature set by hand), the friction as the plant's and the model's viscous and Coulomb friction given
as options on a URDF without them.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec, check_episode, gains_from_omega, model_chain, plant_arm, plant_chain
from ddarm.physics.arm import Arm, ModelError
from dynamics_checks import compiled_mass_matrix_and_acceleration

ROOT = Path(__file__).resolve().parents[1]
PAPER_URDF = ROOT / 'config' / 'ddarm.urdf'
DAMPING, FRICTION, ARMATURE = (0.8, 1.5, 0.3), (0.4, 0.0, 0.25), (0.05, 0.2, 0.0)
NAMESPACE = 'xmlns:ddarm="https://github.com/ddarm/ddarm"'


def paper_urdf_with(folder: Path, name: str, damping=None, friction=None, armature=None) -> Path:
    """The paper's arm with each joint's <dynamics> and <ddarm:armature> given (None: left out)."""
    text = PAPER_URDF.read_text().replace('<robot ', f'<robot {NAMESPACE} ', 1)
    for i in range(3):
        extra = ''
        if damping is not None or friction is not None:
            attributes = ''.join(f' {key}="{values[i]!r}"' for key, values in (('damping', damping),
                                                                              ('friction', friction))
                                 if values is not None)
            extra += f'<dynamics{attributes}/>'
        if armature is not None:
            extra += f'<ddarm:armature value="{armature[i]!r}"/>'
        text = re.sub(rf'(<joint name="joint{i + 1}" type="revolute">)', rf'\1{extra}', text)
    path = folder / name
    path.write_text(text)
    return path


def spec_on(urdf: Path, controller: str, **options) -> EpisodeSpec:
    spec = EpisodeSpec(controller=controller, kp=(1.0,) * 3, kv=(1.0,) * 3, urdf=str(urdf), tau=0.1, **options)
    kp, kv = gains_from_omega(spec, 8.0)
    return dataclasses.replace(spec, kp=tuple(kp), kv=tuple(kv))


def test_the_urdfs_joint_dynamics_reach_the_plants_and_the_models_chain(tmp_path):
    urdf = paper_urdf_with(tmp_path, 'dynamics.urdf', DAMPING, FRICTION, ARMATURE)
    spec = spec_on(urdf, 'computed_torque')
    for chain in (plant_chain(spec), model_chain(spec)):
        assert chain.damping.tolist() == list(DAMPING)
        assert chain.friction.tolist() == list(FRICTION)
        assert chain.armature.tolist() == list(ARMATURE)
    viscous, coulomb = plant_chain(spec).joint_friction([0.1, 0.2, 0.3], None)
    assert viscous == pytest.approx(np.add(DAMPING, [0.1, 0.2, 0.3]), abs=0) and coulomb.tolist() == list(FRICTION)


@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
def test_urdf_friction_is_the_episodes_friction_as_the_options_give_it(tmp_path, controller):
    """The plant's F(q̇) and, for computed torque, the model's F̂: the same episode as the friction options give on
    a URDF without <dynamics>; and both add up."""
    with_dynamics = run_episode(spec_on(paper_urdf_with(tmp_path, 'd.urdf', DAMPING, FRICTION), controller))
    as_options = run_episode(spec_on(PAPER_URDF, controller, viscous_friction=DAMPING, coulomb_friction=FRICTION))
    assert with_dynamics.I[0] == as_options.I[0]
    assert np.array_equal(with_dynamics.q, as_options.q)
    half = tuple(0.5 * x for x in DAMPING)
    added = run_episode(spec_on(paper_urdf_with(tmp_path, 'h.urdf', half, FRICTION), controller,
                                viscous_friction=half))
    assert np.allclose(added.q, as_options.q, rtol=0, atol=1e-12)
    frictionless = run_episode(spec_on(PAPER_URDF, controller))
    assert not np.allclose(frictionless.q, as_options.q, atol=1e-6)


def test_the_model_urdfs_friction_is_the_laws_and_the_plant_urdfs_the_plants(tmp_path):
    """Computed torque's F̂ comes from the model URDF: a plant with friction and a model without it differ from both
    having it."""
    urdf = paper_urdf_with(tmp_path, 'd.urdf', DAMPING, FRICTION)
    both = run_episode(spec_on(urdf, 'computed_torque'))
    unmodelled = run_episode(spec_on(urdf, 'computed_torque', model_urdf=str(PAPER_URDF)))
    assert not np.allclose(both.q, unmodelled.q, atol=1e-6)
    assert np.max(np.abs(both.scored('errors'))) < np.max(np.abs(unmodelled.scored('errors')))


def test_armature_is_added_to_the_mass_matrix_diagonal(tmp_path):
    urdf = paper_urdf_with(tmp_path, 'a.urdf', armature=ARMATURE)
    arm = Arm.from_urdf(urdf)
    by_hand = pin.buildModelFromUrdf(str(PAPER_URDF))
    by_hand.armature = np.array(ARMATURE)
    data = by_hand.createData()
    rng = np.random.default_rng(3)
    chain = plant_chain(spec_on(urdf, 'pd_gravity'))
    for _ in range(5):
        q, v, torque = rng.uniform(-2, 2, 3), rng.uniform(-2, 2, 3), rng.uniform(-50, 50, 3)
        upper = pin.crba(by_hand, data, q)
        expected = np.triu(upper) + np.triu(upper, 1).T
        assert np.allclose(arm.mass_matrix(q), expected, rtol=1e-13, atol=1e-13)
        assert np.allclose(arm.mass_matrix(q) - Arm.from_urdf(PAPER_URDF).mass_matrix(q), np.diag(ARMATURE),
                           rtol=0, atol=1e-13)
        mass, acceleration = compiled_mass_matrix_and_acceleration(chain, q, v, torque)
        assert np.allclose(mass, expected, rtol=1e-12, atol=1e-12)
        assert np.allclose(acceleration, pin.aba(by_hand, data, q, v, torque), rtol=1e-10, atol=1e-10)


def test_armature_moves_the_omega_rule_and_the_episode(tmp_path):
    urdf = paper_urdf_with(tmp_path, 'a.urdf', armature=ARMATURE)
    heavy, plain = spec_on(urdf, 'pd_gravity'), spec_on(PAPER_URDF, 'pd_gravity')
    # PD + gravity's ω rule takes m_ii of the model, armature included.
    assert np.allclose(np.array(heavy.kp) - np.array(plain.kp), 64.0 * np.array(ARMATURE), rtol=1e-12, atol=1e-9)
    assert run_episode(heavy).I[0] != run_episode(dataclasses.replace(heavy, urdf=str(PAPER_URDF))).I[0]


@pytest.mark.parametrize('element, words', [
    ('<dynamics damping="-0.1"/>', ['damping', '-0.1', 'negative']),
    ('<dynamics friction="-2"/>', ['friction', '-2', 'negative']),
    ('<dynamics damping="nan"/>', ['damping', 'nan']),
    ('<ddarm:armature value="-0.5"/>', ['ddarm:armature', 'negative']),
    ('<ddarm:armature value="heavy"/>', ['ddarm:armature', 'heavy']),
    ('<ddarm:armature/>', ['ddarm:armature', 'value']),
    ('<ddarm:armature value="0.1"/><ddarm:armature value="0.2"/>', ['2 <ddarm:armature>']),
    ('<ddarm:armature value="1e200"/>', ['ddarm:armature', 'too large']),
])
def test_a_joint_dynamics_no_joint_has_is_refused_naming_it(tmp_path, element, words):
    text = PAPER_URDF.read_text().replace('<robot ', f'<robot {NAMESPACE} ', 1)
    path = tmp_path / 'bad.urdf'
    path.write_text(text.replace('<joint name="joint2" type="revolute">',
                                 f'<joint name="joint2" type="revolute">{element}', 1))
    with pytest.raises(ModelError) as refused:
        Arm.from_urdf(path)
    assert "joint 'joint2'" in str(refused.value)
    for word in words:
        assert word in str(refused.value)


def test_friction_that_stops_a_joint_within_a_period_is_said():
    z1 = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 6, kv=(1.0,) * 6,
                     urdf=str(ROOT / 'config/arms/z1/z1.urdf'), motion=str(ROOT / 'config/arms/z1/z1-motion.yaml'))
    warned = [line for line in check_episode(z1).warnings if 'friction' in line]
    assert len(warned) == 1 and "joint 'joint6'" in warned[0] and 'within one sampling period' in warned[0]
    panda = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 7, kv=(1.0,) * 7,
                        urdf=str(ROOT / 'config/arms/panda/panda.urdf'),
                        motion=str(ROOT / 'config/arms/panda/panda-motion.yaml'))
    assert not [line for line in check_episode(panda).warnings if 'friction' in line]
    assert plant_arm(panda).model.damping.tolist() == [0.003] * 7


def test_other_urdf_readers_ignore_the_armature_element(tmp_path):
    """The extension is one other readers skip: urdfdom (through Pinocchio, unchanged model) and MuJoCo's compiler."""
    # MuJoCo refuses the paper arm's point-mass links: a two-link arm with moments.
    link = ('<link name="{}"><inertial><mass value="1"/><origin xyz="0.1 0 0"/><inertia ixx="0.01" iyy="0.01" '
            'izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>')
    joint = ('<joint name="j{0}" type="revolute"><parent link="{1}"/><child link="l{0}"/><axis xyz="0 0 1"/>'
             '<limit lower="-1" upper="1" effort="10" velocity="1"/><dynamics damping="{2!r}" friction="{3!r}"/>'
             '<ddarm:armature value="{4!r}"/></joint>')
    urdf = tmp_path / 'two.urdf'
    urdf.write_text(f'<robot name="two" {NAMESPACE}><link name="base"/>{link.format("l1")}{link.format("l2")}'
                    f'{joint.format(1, "base", DAMPING[0], FRICTION[0], ARMATURE[0])}'
                    f'{joint.format(2, "l1", DAMPING[1], FRICTION[1], ARMATURE[1])}</robot>')
    assert Arm.from_urdf(urdf).model.armature.tolist() == list(ARMATURE[:2])
    assert list(pin.buildModelFromUrdf(str(urdf)).armature) == [0.0] * 2
    robot = mujoco.MjModel.from_xml_path(str(urdf))
    assert (robot.dof_damping.tolist(), robot.dof_frictionloss.tolist(), robot.dof_armature.tolist()) == (
        list(DAMPING[:2]), list(FRICTION[:2]), [0.0] * 2)


@pytest.mark.parametrize('option', ['--viscous-friction', '--coulomb-friction'])
def test_friction_options_of_the_wrong_length_are_refused_in_one_line(capsys, option):
    from ddarm.cli.main import main

    assert main(['episode', '--controller', 'pd_gravity', '--omega', '5', option, '1', '2']) == 2
    err = capsys.readouterr().err
    assert f"{option.removeprefix('--').replace('-', '_')} needs 3 values (one per joint)" in err
    assert 'Traceback' not in err
