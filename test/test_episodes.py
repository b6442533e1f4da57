"""The in-process episode runner against the paper's analysis (spec §5–8)."""

import dataclasses

import numpy as np
import pytest

from ddarm.control.gains import computed_torque_error_external
from ddarm.physics.arm import Arm
from ddarm.motion.programmed import paper_trajectory
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, plan_episode, plan_motion

CT_15 = dict(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3)
PD_10 = dict(controller='pd_gravity', kp=(2800.0, 2700.0, 350.0), kv=(560.0, 540.0, 70.0))


def test_computed_torque_errors_follow_the_critically_damped_solution_of_2_8():
    omega, period = 15.0, 0.001
    spec = EpisodeSpec(**CT_15, delay=0, period=period)
    plan = plan_episode(spec)
    e0, e0_rate = np.array([0.02, -0.01, 0.03]), np.array([-0.1, 0.2, 0.05])
    plan = dataclasses.replace(plan, q0=plan.q_ref[0] - e0, v0=plan.v_ref[0] - e0_rate)
    result = run_episode(spec, plan)
    t = plan.times[:, None]
    exact = (e0 + (e0_rate + omega * e0) * t) * np.exp(-omega * t)
    # The zero-order hold lags the continuous law by Δ/2 on average, which changes the
    # response by about ωΔ/2 of its size; allow twice ωΔ of the largest error.
    tolerance = 2 * omega * period * np.max(np.abs(exact))
    assert np.max(np.abs(result.scored('errors') - exact)) <= tolerance
    assert not result.diverged[0]


def test_computed_torque_settles_at_the_external_torque_steady_state_error():
    spec = EpisodeSpec(**CT_15, delay=0, period=0.005, external_torque=(2.0, -3.0, 0.8))
    motion = paper_trajectory(1, 1.0)
    # The formula takes M at q_f: a small P^z keeps the arm close enough for 1 %.
    times = np.arange(801) * spec.period  # four seconds: three of holding q_f
    result = run_episode(spec, plan_motion(spec, motion, times))
    arm = Arm.from_urdf()
    expected = computed_torque_error_external(arm.mass_matrix(motion.qf), np.full(3, 225.0),
                                              np.array(spec.external_torque))
    np.testing.assert_allclose(result.scored('errors')[-1], expected, rtol=0.01)


@pytest.mark.parametrize('delay', [0, 1, 2])
def test_each_command_uses_the_state_of_sample_n_minus_d(delay):
    spec = EpisodeSpec(**CT_15, delay=delay, tau=0.05)
    result = run_episode(spec)
    arm, plan = Arm.from_urdf(), result.plan
    q, v, command = result.scored('q'), result.scored('v'), result.scored('command')
    for n in (0, 1, 2, 3, 40, plan.k_max):
        m = max(n - delay, 0)
        error, rate = plan.q_ref[m] - q[m], plan.v_ref[m] - v[m]
        expected = (arm.mass_matrix(q[m]) @ (plan.a_ref[n] + 225 * error + 30 * rate)
                    + arm.bias(q[m], v[m]))
        np.testing.assert_allclose(command[n], expected, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize('case', [
    dict(**CT_15, delay=1),
    dict(**CT_15, delay=1, trajectory=2, tau=0.1),
    dict(**PD_10, delay=0),
    dict(**PD_10, delay=0, tau=0.1, torque_limit='paper'),
    dict(**CT_15, delay=1, tau=0.1, torque_limit='paper', external_torque=(5.0, 5.0, 1.0),
         viscous_friction=(1.0, 1.0, 0.5), coulomb_friction=(0.5, 0.5, 0.2), mass_scale=(1.0, 1.1, 0.9)),
])
def test_halving_the_integration_step_changes_the_indices_by_less_than_1e_4(case):
    coarse = run_episode(EpisodeSpec(**case)).indices()
    fine = run_episode(EpisodeSpec(**case, substeps=2 * EpisodeSpec(**case).substeps)).indices()
    for key in ('I1', 'I2', 'I'):
        assert abs(coarse[key] - fine[key]) <= 1e-4 * abs(fine[key])


def test_the_paper_torque_limit_clamps_the_applied_torque_and_keeps_the_sign():
    stiff = dict(controller='pd_gravity', kp=(28000.0, 27000.0, 3500.0), kv=(1760.0, 1700.0, 220.0))
    result = run_episode(EpisodeSpec(**stiff, delay=0, tau=0.1, torque_limit='paper'))
    limit = result.plan.torque_limit
    torque, command = result.scored('torque'), result.scored('command')
    assert np.all(np.abs(torque) <= limit)
    clamped = np.abs(command) > limit
    assert clamped.any()
    np.testing.assert_array_equal(np.sign(torque[clamped]), np.sign(command[clamped]))


def test_tau_starts_the_arm_against_the_programmed_motion():
    plan = plan_episode(EpisodeSpec(**CT_15, tau=0.1))
    _, v_at_tau, _ = paper_trajectory(1, 1.0).sample(0.1)
    np.testing.assert_array_equal(plan.q0, plan.q_ref[0])
    np.testing.assert_array_equal(plan.v0, -v_at_tau)


def test_indices_are_scored_from_the_applied_torque_over_k_max():
    result = run_episode(EpisodeSpec(**PD_10, delay=0, tau=0.1, torque_limit='paper'))
    indices = result.indices()
    degrees = np.degrees(np.abs(result.scored('errors'))).sum() / 100
    weights = 10 / np.abs(result.plan.nominal).max(axis=0)
    torque_term = (np.abs(result.scored('torque') - result.plan.nominal) * weights).sum() / 100
    assert indices['I1'] == pytest.approx(degrees, rel=1e-12)
    assert indices['I2'] == pytest.approx(torque_term, rel=1e-12)
    assert indices['I'] == pytest.approx(degrees + torque_term, rel=1e-12)


def test_a_diverging_episode_is_flagged_with_finite_numbers():
    result = run_episode(EpisodeSpec(controller='computed_torque', kp=(1e6,) * 3, kv=(3e3,) * 3, delay=1))
    assert result.diverged[0]
    summary = result.summary()
    assert summary['diverged'] and 0 < summary['diverged_at_sample'] <= 100
    assert all(np.isfinite(summary[key]) for key in ('I1', 'I2', 'I'))
    assert np.all(np.isfinite(result.scored('q'))) and np.all(np.isfinite(result.scored('torque')))


@pytest.mark.parametrize('change, problem', [
    (dict(controller='pid'), 'controller'),
    (dict(tau=-0.1), 'tau'),
    (dict(period=0.003), 'whole number'),
    (dict(period=0.0), 'period'),
    (dict(delay=-1), 'delay'),
    (dict(torque_limit='double'), 'torque_limit'),
    (dict(duration=1e5, period=1e-3), 'samples'),
])
def test_bad_specs_are_refused(change, problem):
    with pytest.raises(EpisodeError, match=problem):
        EpisodeSpec(**{**CT_15, **change})


@pytest.mark.parametrize('change, problem', [
    (dict(kp=(1.0, 2.0)), 'kp needs 3'),
    (dict(kv=(1.0, -2.0, 3.0)), 'positive'),
    (dict(torque_limit=(1.0, 2.0)), 'torque_limit'),
    (dict(external_torque=(1.0, float('nan'), 0.0)), 'external_torque'),
])
def test_bad_gains_and_plant_options_are_refused(change, problem):
    with pytest.raises(ValueError, match=problem):
        run_episode(EpisodeSpec(**{**CT_15, **change}))
