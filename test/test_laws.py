"""The control laws, the delay buffer and the gain rules of spec §5–6."""

import numpy as np
import pytest

from ddarm.control.gains import (computed_torque_error_external, computed_torque_error_mass,
                                 omega_rule_computed_torque, omega_rule_pd_gravity, pd_gravity_error,
                                 smallest_omega)
from ddarm.control.laws import (gravity_feedforward, ComputedTorqueLaw, DelayBuffer, GainError, Measurement, PDGravityLaw,
                                ReferencePoint, SampledController, checked_delay, checked_gains,
                                computed_torque, pd_gravity)
from ddarm.physics.arm import Arm
from ddarm.physics.dynamics import chain_from_model, compiled_dynamics


@pytest.fixture(scope='module')
def arm():
    return Arm.from_urdf()


@pytest.fixture(scope='module')
def chain(arm):
    """The controller's model as the compiled laws read it; the expected values below come from Pinocchio (arm)."""
    return chain_from_model(arm.model)


@pytest.mark.parametrize('delay', [0, 1, 2])
def test_delay_buffer_hands_back_sample_n_minus_d_or_sample_0(delay):
    buffer = DelayBuffer(delay)
    handed = [buffer.push(n) for n in range(6)]
    assert handed == [max(n - delay, 0) for n in range(6)]
    buffer.clear()
    assert buffer.push('new episode') == 'new episode'


def test_delay_buffer_is_the_compiled_loops_delay_and_counts_arrivals_after_a_gap():
    from ddarm.control.laws import measured_sample

    assert [measured_sample(n, 2) for n in range(5)] == [0, 0, 0, 1, 2]
    buffer = DelayBuffer(1)
    assert buffer.push('sample 0') == 'sample 0'
    assert buffer.push('sample 2') == 'sample 0'  # sample 1 never arrived: the state one arrival ago
    assert buffer.push('sample 3') == 'sample 2'


@pytest.mark.parametrize('delay', [-1, 1.5, True, 101, 'one'])
def test_bad_delay_is_refused(delay):
    with pytest.raises(GainError, match='compute delay'):
        checked_delay(delay)


def test_pd_gravity_is_equation_2_1(arm, chain):
    kp, kv = np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 6.0])
    law = PDGravityLaw(chain, kp, kv)
    measured = Measurement(q=np.array([0.1, 0.2, 0.3]), v=np.array([1.0, 1.0, 1.0]),
                           q_ref=np.array([0.2, 0.2, 0.1]), v_ref=np.zeros(3))
    reference = ReferencePoint(q=np.array([0.5, 0.4, -0.2]), v=np.zeros(3), a=np.ones(3))
    expected = kp * (measured.q_ref - measured.q) + kv * (0 - measured.v) + arm.gravity(reference.q)
    feedforward = gravity_feedforward(arm, reference.q[None])[0]
    np.testing.assert_allclose(law.torque(measured, reference, feedforward), expected)
    with pytest.raises(GainError, match='gravity feedforward'):
        law.torque(measured, reference)


def test_computed_torque_is_equation_2_6_with_kp_on_the_error(arm, chain):
    kp, kv = np.array([100.0, 200.0, 300.0]), np.array([1.0, 2.0, 3.0])
    law = ComputedTorqueLaw(chain, kp, kv)
    measured = Measurement(q=np.array([0.1, 0.2, 0.3]), v=np.array([0.5, -0.2, 0.1]),
                           q_ref=np.array([0.2, 0.1, 0.3]), v_ref=np.array([0.0, 0.3, 0.0]))
    reference = ReferencePoint(q=np.zeros(3), v=np.zeros(3), a=np.array([1.0, -1.0, 2.0]))
    inner = reference.a + kp * measured.error + kv * measured.error_rate
    expected = arm.mass_matrix(measured.q) @ inner + arm.bias(measured.q, measured.v)
    np.testing.assert_allclose(law.torque(measured, reference), expected)


def compiled_laws(chain, kp, kv, q_ref, v_ref, a_ref, gravity_ref, qm, vm, viscous, coulomb):
    """Both compiled laws over lanes: gains and measured states of shape (n, lanes), one column per episode."""
    n, lanes = kp.shape
    kp, kv, qm, vm = (np.ascontiguousarray(x) for x in (kp, kv, qm, vm))
    pd, ct = np.empty((n, lanes)), np.empty((n, lanes))
    pd_gravity(kp, kv, q_ref, v_ref, gravity_ref, qm, vm, pd, lanes)
    computed_torque(compiled_dynamics(chain).inverse_dynamics, np.ones((n, lanes)), kp, kv, q_ref, v_ref, a_ref, qm,
                    vm, viscous, coulomb, np.empty((n, lanes)), ct, lanes)
    return pd, ct


def test_the_compiled_laws_over_lanes_equal_each_column_alone(arm, chain):
    # Several gain columns (and measured states) in one call: each column is that column's law alone,
    # and both are (2.1) and (2.6) as Pinocchio's M, V + G and G give them.
    rng = np.random.default_rng(1)
    lanes = 5
    kp, kv = rng.uniform(1, 10, (3, lanes)), rng.uniform(1, 10, (3, lanes))
    qm, vm = rng.normal(size=(3, lanes)), rng.normal(size=(3, lanes))
    q_ref, v_ref, accel, q_now = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    viscous, coulomb = np.array([1.0, 0.5, 0.2]), np.array([0.3, 0.0, 0.1])
    gravity = arm.gravity(q_now)
    batch_pd, batch_ct = compiled_laws(chain, kp, kv, q_ref, v_ref, accel, gravity, qm, vm, viscous, coulomb)
    for b in range(lanes):
        alone_pd, alone_ct = compiled_laws(chain, kp[:, b:b + 1], kv[:, b:b + 1], q_ref, v_ref, accel, gravity,
                                           qm[:, b:b + 1], vm[:, b:b + 1], viscous, coulomb)
        np.testing.assert_array_equal(batch_pd[:, b], alone_pd[:, 0])
        np.testing.assert_array_equal(batch_ct[:, b], alone_ct[:, 0])
        error, rate = q_ref - qm[:, b], v_ref - vm[:, b]
        np.testing.assert_allclose(batch_pd[:, b], kp[:, b] * error + kv[:, b] * rate + gravity, rtol=1e-12)
        expected = (arm.mass_matrix(qm[:, b]) @ (accel + kp[:, b] * error + kv[:, b] * rate)
                    + arm.bias(qm[:, b], vm[:, b]) + viscous * vm[:, b] + coulomb * np.sign(vm[:, b]))
        np.testing.assert_allclose(batch_ct[:, b], expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('kp, kv, problem', [
    ([1, 2], [1, 2, 3], 'kp needs 3'),
    ([1, 2, 3], [1, 2, 3, 4], 'kv needs 3'),
    ([1, -2, 3], [1, 2, 3], 'positive'),
    ([1, 0, 3], [1, 2, 3], 'positive'),
    ([1, float('nan'), 3], [1, 2, 3], 'finite'),
    ([1, 2, 3], [1, float('inf'), 3], 'finite'),
    (['a', 2, 3], [1, 2, 3], 'numbers'),
])
def test_bad_gains_are_refused_and_the_old_ones_kept(chain, kp, kv, problem):
    with pytest.raises(GainError, match=problem):
        checked_gains(kp, kv, 3)
    law = PDGravityLaw(chain, [1, 1, 1], [2, 2, 2])
    with pytest.raises(GainError):
        law.set_gains(kp, kv)
    np.testing.assert_array_equal(law.kp, [1, 1, 1])


def test_sampled_controller_uses_the_delayed_measurement_and_the_current_reference(arm, chain):
    law = PDGravityLaw(chain, np.ones(3), np.ones(3))
    controller = SampledController(law, delay=1)
    refs = [ReferencePoint(np.full(3, 0.1 * n), np.zeros(3), np.zeros(3)) for n in range(3)]
    gravity = [arm.gravity(r.q) for r in refs]
    meas = [Measurement(np.full(3, n), np.zeros(3), np.zeros(3), np.zeros(3)) for n in range(3)]
    torques = [controller.step(m, r, g) for m, r, g in zip(meas, refs, gravity)]
    np.testing.assert_allclose(torques[0], law.torque(meas[0], refs[0], gravity[0]))
    np.testing.assert_allclose(torques[2], law.torque(meas[1], refs[2], gravity[2]))
    controller.reset()
    np.testing.assert_allclose(controller.step(meas[2], refs[0], gravity[0]), law.torque(meas[2], refs[0], gravity[0]))


def test_omega_rules(arm):
    kp, kv = omega_rule_computed_torque(3, 15.0)
    np.testing.assert_array_equal(kp, [225, 225, 225])
    np.testing.assert_array_equal(kv, [30, 30, 30])
    diagonal = np.diag(arm.mass_matrix(np.array([np.pi / 2, 0, 0])))
    np.testing.assert_allclose(diagonal, [28.0, 27.0, 3.5])
    kp, kv = omega_rule_pd_gravity(diagonal, 10.0)
    np.testing.assert_allclose(kp, [2800, 2700, 350])
    np.testing.assert_allclose(kv, [560, 540, 70])
    batch_kp, _ = omega_rule_computed_torque(3, np.array([1.0, 2.0]))
    assert batch_kp.shape == (2, 3)


def test_steady_state_formulas_and_the_smallest_omega(arm):
    q_final = np.array([np.pi / 2, 0, 0])
    mass = arm.mass_matrix(q_final)
    external = np.array([0.0, 10.0, 0.0])
    kp = np.full(3, 100.0)
    error = computed_torque_error_external(mass, kp, external)
    np.testing.assert_allclose(kp * (mass @ error), -external, atol=1e-12)
    heavy = Arm.from_urdf(mass_scale=[1, 1.1, 1.1])
    error = computed_torque_error_mass(mass, heavy.gravity(q_final), arm.gravity(q_final), kp)
    np.testing.assert_allclose(mass @ (kp * error), heavy.gravity(q_final) - arm.gravity(q_final))
    np.testing.assert_allclose(pd_gravity_error(np.ones(3), np.zeros(3), np.zeros(3), kp), 0.01)
    # e_i = c_i / ω²: with c = (0, 4, 1) and a permitted 0.01, ω² = 400.
    assert smallest_omega(np.array([0.0, 4.0, 1.0]), np.ones(3), np.full(3, 0.01)) == pytest.approx(20.0)


def test_the_sampled_model_boundary_scales_with_the_period_and_grows_without_delay():
    from ddarm.control.gains import largest_stable_omega

    for delay in (0, 1, 2):
        products = [largest_stable_omega(period, delay) * period for period in (0.005, 0.01, 0.02, 0.05)]
        np.testing.assert_allclose(products, products[0], rtol=1e-9)  # only ωΔ matters
    assert largest_stable_omega(0.01, 0) > largest_stable_omega(0.01, 1) > largest_stable_omega(0.01, 2)
    assert largest_stable_omega(0.01, 1) > 15  # the paper's ω = 15 at 100 Hz


def test_the_sampled_model_boundary_matches_the_simulated_arm():
    import dataclasses

    from ddarm.control.gains import largest_stable_omega
    from ddarm.episodes.engine import run_episode
    from ddarm.episodes.spec import EpisodeSpec

    period = 0.01
    boundary = largest_stable_omega(period, 1)
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, period=period, delay=1)
    worst = {}
    for factor in (0.9, 1.1):
        omega = factor * boundary
        result = run_episode(dataclasses.replace(spec, kp=(omega**2,) * 3, kv=(2 * omega,) * 3))
        errors = result.scored('errors')
        late = np.abs(errors[-len(errors) // 10:])  # the last tenth: decayed, or growing
        worst[factor] = np.inf if result.diverged[0] else float(late.max())
    assert np.isfinite(worst[0.9]) and worst[1.1] > 10 * worst[0.9]
