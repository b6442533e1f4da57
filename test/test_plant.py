"""The plant core: zero-order hold, saturation, refusals and divergence (spec §3, §5, §7; docs/faults.md)."""

import numpy as np
import pytest

from ddarm.physics.arm import Arm
from ddarm.physics.dynamics import chain_from_model
from ddarm.physics.plant import Plant, PlantError, PlantOptions


@pytest.fixture(scope='module')
def arm():
    """Pinocchio's model of the arm: the expected values (gravity, energy) come from it."""
    return Arm.from_urdf()


def make_plant(arm, **options):
    return Plant(chain_from_model(arm.model), PlantOptions(**options), np.array([0.0, 0.5, -0.5]), np.zeros(3))


@pytest.mark.parametrize('torque', [[np.nan, 0, 0], [0, np.inf, 0], [1.0, 2.0], [[1, 2, 3]]])
def test_non_finite_or_misshapen_torque_is_refused_and_nothing_integrated(arm, torque):
    plant = make_plant(arm)
    q, v = plant.q.copy(), plant.v.copy()
    with pytest.raises(PlantError, match='sample 0'):
        plant.advance(torque)
    np.testing.assert_array_equal(plant.q, q)
    np.testing.assert_array_equal(plant.v, v)
    assert plant.sample == 0


@pytest.mark.parametrize('options, problem', [
    (dict(period=0.0), 'period'), (dict(period=-0.01), 'period'), (dict(period=10.5), 'period'), (dict(period=5e-7), 'period'),
    (dict(period=float('nan')), 'period'), (dict(substeps=0), 'substeps'), (dict(substeps=2.5), 'substeps'),
])
def test_bad_sampling_options_are_refused(options, problem):
    with pytest.raises(PlantError, match=problem):
        PlantOptions(**options)


def test_per_joint_options_need_one_finite_value_per_joint(arm):
    with pytest.raises(PlantError, match='torque_limit needs 3'):
        make_plant(arm, torque_limit=[1.0, 2.0])
    with pytest.raises(PlantError, match='positive'):
        make_plant(arm, torque_limit=[1.0, 0.0, 2.0])
    with pytest.raises(PlantError, match='viscous_friction'):
        make_plant(arm, viscous_friction=[1.0, -1.0, 0.0])


def test_saturation_clamps_and_keeps_the_sign(arm):
    plant = make_plant(arm, torque_limit=[10.0, 20.0, 30.0])
    np.testing.assert_array_equal(plant.saturate(np.array([-15.0, 5.0, 40.0])), [-10.0, 5.0, 30.0])


def test_holding_gravity_keeps_the_arm_still_and_external_torque_moves_it(arm):
    plant = make_plant(arm)
    hold = arm.gravity(plant.q)
    for _ in range(10):
        plant.advance(hold)
    np.testing.assert_allclose(plant.v, 0.0, atol=1e-12)
    pushed = make_plant(arm, external_torque=[0.0, 5.0, 0.0])
    pushed.advance(hold)
    assert pushed.v[1] > 0


def test_viscous_friction_takes_energy_out(arm):
    chain = chain_from_model(arm.model)
    free = Plant(chain, PlantOptions(), np.array([0.0, 0.5, -0.5]), np.array([2.0, 0.0, 0.0]))
    damped = Plant(chain, PlantOptions(viscous_friction=[5.0, 5.0, 5.0]), free.q, free.v)
    for _ in range(50):
        free.advance(np.zeros(3))
        damped.advance(np.zeros(3))
    assert arm.energy(damped.q, damped.v) < arm.energy(free.q, free.v)


def test_divergence_freezes_the_last_state_within_bounds(arm):
    plant = make_plant(arm, max_velocity=5.0)
    steps = 0
    while plant.advance(np.array([0.0, 0.0, 500.0])):
        steps += 1
    assert plant.diverged and steps < 100
    assert np.all(np.abs(plant.v) <= 5.0)
    frozen = plant.q.copy()
    assert not plant.advance(np.zeros(3))
    np.testing.assert_array_equal(plant.q, frozen)


def test_a_period_is_the_reference_rk4_on_pinocchios_aba(arm):
    # The compiled step against the plain RK4 of reference_episode.py, on a plant that differs from the
    # model (mass scale), with friction and an external torque.
    from reference_episode import rk4_period

    scale = np.array([1.0, 1.2, 0.9])
    options = dict(substeps=8, external_torque=[1.0, -2.0, 0.5], viscous_friction=[0.5, 1.0, 0.2],
                   coulomb_friction=[0.3, 0.2, 0.1])
    plant = Plant(chain_from_model(arm.model), PlantOptions(**options), np.array([0.1, 0.5, -0.5]),
                  np.array([1.0, -0.5, 2.0]), mass_scale=scale)
    heavy = Arm.from_urdf(mass_scale=scale)
    q, v = plant.q, plant.v
    for n in range(20):
        torque = np.array([5.0, 150.0 + n, 40.0])
        assert plant.advance(torque)
        q, v = rk4_period(heavy, q, v, torque, 0.01, 8, np.array(options['external_torque']),
                    np.array(options['viscous_friction']), np.array(options['coulomb_friction']))
        np.testing.assert_allclose(plant.q, q, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(plant.v, v, rtol=1e-12, atol=1e-12)
    assert plant.sample == 20


@pytest.mark.parametrize('command', [[1.0, 2.0], [[1.0, 2.0, 3.0]], [1.0, 2.0, 3.0, 4.0], 5.0, 'strong'])
def test_a_misshapen_command_is_refused_before_the_compiled_clamp(arm, command):
    plant = make_plant(arm, torque_limit=[10.0, 20.0, 30.0])
    with pytest.raises(PlantError, match='sample 0: command must be 3 numbers'):
        plant.saturate(command)


def test_saturation_passes_a_nan_through_for_advance_to_refuse(arm):
    plant = make_plant(arm, torque_limit=[10.0, 20.0, 30.0])
    applied = plant.saturate([np.nan, 50.0, -50.0])
    np.testing.assert_array_equal(applied, [np.nan, 20.0, -30.0])
    with pytest.raises(PlantError, match='finite'):
        plant.advance(applied)
