"""The in-process episode runner against the paper's analysis (spec §5–8)."""

import dataclasses
import re

import numpy as np
import pytest

from ddarm.control.gains import computed_torque_error_external
from ddarm.errors import DdarmError
from ddarm.physics.arm import Arm
from ddarm.motion.programmed import paper_trajectory
from ddarm.episodes.engine import run_episode
from ddarm.episodes.result import Episodes, RecordingError
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
    assert summary['diverged'] and 0 < summary['diverged_at'] <= 100
    assert summary['diverged_at_sample'] == summary['diverged_at']  # its deprecated name
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


# Recorded samples: the one rule that turns them into a scored episode ---------------------------------------------

def recorded(result):
    """What a recording of `result` holds: states n = 0 … (with the torque applied over n - 1) and commands."""
    q, v, command, torque = (result.scored(name) for name in ('q', 'v', 'command', 'torque'))
    count = len(torque)
    states = {n: (q[n], v[n], None if n == 0 else torque[n - 1]) for n in range(count)}
    # The state the last scored period ends in: a position (or none, if the plant diverged) and the torque held.
    states[count] = (None, None, torque[-1]) if result.diverged[0] else (q[-1] + 0.1, v[-1], torque[-1])
    return states, {n: command[n] for n in range(count)}


def test_recorded_samples_score_as_the_episode_that_made_them():
    result = run_episode(EpisodeSpec(**PD_10, delay=0, tau=0.1, torque_limit='paper'))
    states, commands = recorded(result)
    again = Episodes.from_recorded(result.template, result.plan, states, commands, plant_report={'ticks': 101})
    for key in ('I1', 'I2', 'I'):
        assert again.indices()[key] == pytest.approx(result.indices()[key], rel=1e-12)
    assert not again.diverged[0] and again.samples_scored[0] == result.plan.k_max + 1
    np.testing.assert_array_equal(again.scored('torque'), result.scored('torque'))
    assert again.plant_report == {'ticks': 101}


def test_a_recorded_divergence_is_scored_on_the_samples_before_it():
    result = run_episode(EpisodeSpec(controller='computed_torque', kp=(1e6,) * 3, kv=(3e3,) * 3, delay=1))
    states, commands = recorded(result)
    states[int(result.diverged_at[0]) + 5] = (None, None, None)  # later states are not scored
    again = Episodes.from_recorded(result.template, result.plan, states, commands)
    assert again.diverged_at[0] == result.diverged_at[0] and again.samples_scored[0] == result.samples_scored[0]
    for key in ('I1', 'I2', 'I'):
        assert again.indices()[key] == pytest.approx(result.indices()[key], rel=1e-12)


def test_missing_recorded_samples_are_named():
    result = run_episode(EpisodeSpec(**CT_15))
    states, commands = recorded(result)
    del commands[5], states[7]
    with pytest.raises(RecordingError, match=re.escape(
            'the states (position and velocity) of samples [7]; the torques applied over samples [6] (each the '
            'effort of the next state); the commands of samples [5] are missing: the episode is incomplete')) as error:
        Episodes.from_recorded(result.template, result.plan, states, commands)
    assert error.value.samples == [5, 6, 7]
    assert isinstance(error.value, DdarmError)
    states, commands = recorded(result)
    states[0] = (None, None, None)  # no position at sample 0 is a missing state, not a divergence
    with pytest.raises(RecordingError, match=re.escape('the states (position and velocity) of samples [0] are')):
        Episodes.from_recorded(result.template, result.plan, states, commands)


@pytest.mark.parametrize('name, rows', [('q', 5), ('v', 2), ('command', 6), ('torque', 3)])
def test_samples_of_different_lengths_are_refused(name, rows):
    result = run_episode(EpisodeSpec(**CT_15))
    series = {key: result.scored(key)[:4] for key in ('q', 'v', 'command', 'torque')}
    series[name] = result.scored(name)[:rows]
    with pytest.raises(RecordingError, match=f"same number of samples.*'{name}': \\({rows}, 3\\)"):
        Episodes.from_samples(result.template, result.plan, **series)


def test_more_samples_than_the_plan_or_other_joints_are_refused():
    result = run_episode(EpisodeSpec(**CT_15))
    too_many = {key: np.vstack([result.scored(key), result.scored(key)[:1]])
                for key in ('q', 'v', 'command', 'torque')}
    with pytest.raises(RecordingError, match='at most k_max \\+ 1 = 101'):
        Episodes.from_samples(result.template, result.plan, **too_many)
    two_joints = {key: result.scored(key)[:, :2] for key in ('q', 'v', 'command', 'torque')}
    with pytest.raises(RecordingError, match=r'shape \(samples, 3\)'):
        Episodes.from_samples(result.template, result.plan, **two_joints)


def test_an_episode_without_gains_is_a_template_checked_but_never_run():
    from ddarm.episodes.spec import EpisodeError, EpisodeSpec, check_episode

    template = EpisodeSpec(controller='computed_torque', trajectory=2, delay=0)
    assert template.is_template and template.to_dict()['kp'] is None
    check_episode(template)  # everything but the gains
    with pytest.raises(EpisodeError, match='template has no gains'):
        run_episode(template)
    spec = template.with_gains([225.0] * 3, [30.0] * 3)
    assert not spec.is_template and spec.kp == (225.0,) * 3
    assert dataclasses.replace(spec, kp=None, kv=None) == template
    assert run_episode(spec).indices() == run_episode(EpisodeSpec(
        controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, trajectory=2, delay=0)).indices()
