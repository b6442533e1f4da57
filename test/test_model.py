"""The URDF through Pinocchio against spec §3's closed forms, and free-motion physics."""

import numpy as np
import pytest

from ddarm.physics.arm import Arm, ModelError
from ddarm.physics.dynamics import chain_from_model
from ddarm.physics.plant import Plant, PlantOptions

G = 9.81


def closed_form_mass_matrix(q):
    c2, c3, c23 = np.cos(q[1]), np.cos(q[2]), np.cos(q[1] + q[2])
    m11 = 1 + 2.5 * c2**2 + c2**2 + 10 * (c2 + 0.5 * c23) ** 2 + c23**2
    return np.array([[m11, 0, 0], [0, 17 + 10 * c3, 3.5 + 5 * c3], [0, 3.5 + 5 * c3, 3.5]])


def closed_form_mass_matrix_derivative(q):
    """dM[i, j, k] = ∂M_ij/∂q_k, differentiated by hand from docs/model-specification.md's M."""
    c2, s2, s3 = np.cos(q[1]), np.sin(q[1]), np.sin(q[2])
    c23, s23 = np.cos(q[1] + q[2]), np.sin(q[1] + q[2])
    reach = c2 + 0.5 * c23
    dm = np.zeros((3, 3, 3))
    dm[0, 0, 1] = -7 * c2 * s2 + 20 * reach * (-s2 - 0.5 * s23) - 2 * c23 * s23
    dm[0, 0, 2] = 20 * reach * (-0.5 * s23) - 2 * c23 * s23
    dm[1, 1, 2] = -10 * s3
    dm[1, 2, 2] = dm[2, 1, 2] = -5 * s3
    return dm


def closed_form_gravity(q):
    c2, c23 = np.cos(q[1]), np.cos(q[1] + q[2])
    return np.array([0.0, G * (5 * c2 + 10 * (c2 + 0.5 * c23)), 5 * G * c23])


def closed_form_bias(q, v):
    """V + G with V_i = Σ_jk (∂M_ij/∂q_k - ½ ∂M_jk/∂q_i) q̇_j q̇_k (Christoffel symbols of M)."""
    dm = closed_form_mass_matrix_derivative(q)
    coriolis = np.einsum('ijk,j,k->i', dm, v, v) - 0.5 * np.einsum('jki,j,k->i', dm, v, v)
    return coriolis + closed_form_gravity(q)


@pytest.fixture(scope='module')
def arm():
    return Arm.from_urdf()


def test_dynamics_match_the_closed_forms_at_random_states(arm):
    rng = np.random.default_rng(7)
    for _ in range(1000):
        q = rng.uniform(-np.pi, np.pi, 3)
        v = rng.uniform(-5, 5, 3)
        mass = arm.mass_matrix(q)
        np.testing.assert_allclose(mass, closed_form_mass_matrix(q), rtol=0, atol=1e-9)
        assert mass[0, 1] == pytest.approx(0, abs=1e-12) and mass[0, 2] == pytest.approx(0, abs=1e-12)
        np.testing.assert_allclose(arm.gravity(q), closed_form_gravity(q), rtol=0, atol=1e-9)
        np.testing.assert_allclose(arm.bias(q, v), closed_form_bias(q, v), rtol=0, atol=1e-9)


def test_forward_and_inverse_dynamics_agree_with_the_closed_forms(arm):
    rng = np.random.default_rng(8)
    q, v, torque = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3) * 50
    expected = np.linalg.solve(closed_form_mass_matrix(q), torque - closed_form_bias(q, v))
    np.testing.assert_allclose(arm.forward_dynamics(q, v, torque), expected, atol=1e-9)
    np.testing.assert_allclose(arm.inverse_dynamics(q, v, expected), torque, atol=1e-9)


def test_joint_names_come_from_the_urdf(arm):
    assert arm.joint_names == ['joint1', 'joint2', 'joint3']


def test_free_end_follows_section_1_kinematics(arm):
    rng = np.random.default_rng(9)
    for q in rng.uniform(-np.pi, np.pi, (50, 3)):
        reach = np.cos(q[1]) + np.cos(q[1] + q[2])
        expected = [reach * np.cos(q[0]), reach * np.sin(q[0]), np.sin(q[1]) + np.sin(q[1] + q[2])]
        np.testing.assert_allclose(arm.frame_position(q, 'tool'), expected, atol=1e-12)
        assert arm.frame_position(q, 'link3')[2] == pytest.approx(np.sin(q[1]), abs=1e-12)


def test_elbow_is_above_the_ground_plane_when_the_shoulder_is_raised(arm):
    for q2 in (0.1, 0.7, 1.5, 2.5):
        assert arm.frame_position(np.array([0.3, q2, -1.0]), 'link3')[2] > 0


def test_free_motion_conserves_energy(arm):
    plant = Plant(chain_from_model(arm.model), PlantOptions(period=0.01, substeps=20), np.array([0.2, 0.6, -0.4]),
                  np.array([1.0, -0.5, 2.0]))
    initial = arm.energy(plant.q, plant.v)
    for _ in range(200):
        assert plant.advance(np.zeros(3))
    assert plant.time == pytest.approx(2.0)
    assert abs(arm.energy(plant.q, plant.v) - initial) <= 1e-6 * abs(initial)


def test_mass_scale_scales_each_link(arm):
    heavy = Arm.from_urdf(mass_scale=[1.0, 1.2, 1.0])
    q = np.array([0.0, 0.3, 0.2])
    c2, c23 = np.cos(q[1]), np.cos(q[1] + q[2])
    # G3 does not see link 2; G2 gains 20 % of link 2's own term 5 g c2.
    assert heavy.gravity(q)[2] == pytest.approx(arm.gravity(q)[2])
    assert heavy.gravity(q)[1] - arm.gravity(q)[1] == pytest.approx(0.2 * 5 * G * c2)
    assert c23  # the scale leaves the geometry alone


@pytest.mark.parametrize('scale', [[1.0, 1.0], [1.0, -1.0, 1.0], [1.0, float('nan'), 1.0]])
def test_bad_mass_scale_is_refused(scale):
    with pytest.raises(ModelError, match='mass_scale'):
        Arm.from_urdf(mass_scale=scale)


def test_missing_urdf_is_refused(tmp_path):
    with pytest.raises(ModelError, match='does not exist'):
        Arm.from_urdf(tmp_path / 'nothing.urdf')
