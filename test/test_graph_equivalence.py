"""A lockstep episode over ROS 2 gives the in-process runner's numbers at every sample (both paths share the core)."""

import numpy as np
import pytest

from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.ros.session import run_graph_episode
from graph_helpers import run_in_process

GAINS = {'computed_torque': dict(kp=(225.0,) * 3, kv=(30.0,) * 3),
         'pd_gravity': dict(kp=(2800.0, 2700.0, 350.0), kv=(560.0, 540.0, 70.0))}


def assert_same_episode(graph_result, reference):
    assert graph_result.scored('errors').shape == reference.scored('errors').shape
    np.testing.assert_allclose(graph_result.scored('errors'), reference.scored('errors'), rtol=0, atol=1e-9)
    np.testing.assert_allclose(graph_result.scored('torque'), reference.scored('torque'), rtol=0, atol=1e-9)
    for key in ('I1', 'I2', 'I'):
        assert graph_result.indices()[key] == pytest.approx(reference.indices()[key], rel=1e-9)


@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
@pytest.mark.parametrize('delay', [0, 1])
@pytest.mark.parametrize('trajectory', [1, 2])
def test_in_process_graph_equals_the_core(ros_context, controller, delay, trajectory):
    spec = EpisodeSpec(controller=controller, **GAINS[controller], delay=delay, trajectory=trajectory)
    assert_same_episode(run_in_process(ros_context, spec), run_episode(spec))


def test_limits_disturbance_and_plant_options_go_through_the_graph(ros_context):
    spec = EpisodeSpec(controller='computed_torque', kp=(900.0,) * 3, kv=(60.0,) * 3, tau=0.1,
                       torque_limit='paper', external_torque=(5.0, -5.0, 1.0), viscous_friction=(1.0, 1.0, 0.5),
                       coulomb_friction=(0.5, 0.5, 0.2), mass_scale=(1.0, 1.1, 0.9))
    result = run_in_process(ros_context, spec)
    reference = run_episode(spec)
    assert np.any(np.abs(reference.scored('command')) > reference.plan.torque_limit)  # the limit is exercised
    assert_same_episode(result, reference)


def test_a_diverging_episode_over_the_graph_is_reported_like_the_core(ros_context):
    spec = EpisodeSpec(controller='computed_torque', kp=(1e6,) * 3, kv=(3e3,) * 3, delay=1)
    result = run_in_process(ros_context, spec)
    reference = run_episode(spec)
    assert result.diverged_at[0] == reference.diverged_at[0]
    assert_same_episode(result, reference)


@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
def test_separate_processes_over_dds_equal_the_core(controller):
    spec = EpisodeSpec(controller=controller, **GAINS[controller], tau=0.05, torque_limit='paper')
    assert_same_episode(run_graph_episode(spec), run_episode(spec))


def test_realtime_mode_runs_on_the_wall_clock_and_reports_its_timing():
    spec = EpisodeSpec(controller='computed_torque', **GAINS['computed_torque'])
    result = run_graph_episode(spec, realtime=True)
    report = result.plant_report
    assert report['event'] == 'complete' and report['mode'] == 'realtime'
    assert {'stale_commands', 'deadline_misses', 'period_jitter_p99_ms'} <= set(report)
    assert len(result.scored('errors')) == 101 and np.all(np.isfinite(result.scored('errors')))
