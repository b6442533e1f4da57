"""Robust tuning (`ddarm tune --robust-*`): the scenario grid, its refusals, the worst case it buys over the nominal
optimum, and a JSON whose every per-scenario number is the scenario's own episode."""

import dataclasses
import json

import numpy as np
import pytest
import yaml

from ddarm.cli.main import main
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning.robust import RobustError, scenario_grid, scenario_scores
from ddarm.tuning.search import SearchError, omega_starts, search_gains
from ddarm.tuning.tune import tune

CT = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, duration=0.5)
TUNE = ['tune', '--controller', 'computed_torque', '--index', 'I', '--duration', '0.5', '--omegas', '10', '15']


def alone(scenario: EpisodeSpec, kp, kv) -> dict:
    """The scenario's episode with these gains, run by itself."""
    episode = run_episode(dataclasses.replace(scenario, kp=tuple(kp), kv=tuple(kv)))
    return {**episode.indices(), 'diverged': bool(episode.diverged[0])}


def test_the_grid_is_every_combination_and_an_axis_not_given_is_the_templates():
    template = dataclasses.replace(CT, tau=0.05, external_torque=(0.0, 5.0, 1.0))
    grid = scenario_grid(template, taus=[0.0, 0.1], mass_scales=[0.8, (1.0, 1.1, 1.2)])
    assert [(s.tau, s.mass_scale) for s in grid] == [
        (0.0, (0.8,) * 3), (0.0, (1.0, 1.1, 1.2)), (0.1, (0.8,) * 3), (0.1, (1.0, 1.1, 1.2))]
    assert all(s.external_torque == (0.0, 5.0, 1.0) and s.controller == 'computed_torque' for s in grid)
    assert scenario_grid(template, external_torques=[(0, 0, 0)]) == (
        dataclasses.replace(template, external_torque=(0.0, 0.0, 0.0)),)


@pytest.mark.parametrize('axes, named', [
    (dict(taus=[0.0, 0.6]), '--robust-tau'),
    (dict(taus=[0.1, 0.1]), '--robust-tau'),
    (dict(taus=[]), '--robust-tau'),
    (dict(mass_scales=[(1.0, 1.1)]), '--robust-mass-scale'),
    (dict(mass_scales=[-1.0]), '--robust-mass-scale'),
    (dict(external_torques=[(5.0,)]), '--robust-external-torque'),
    (dict(external_torques=[(0.0, np.inf, 0.0)]), '--robust-external-torque'),
])
def test_a_grid_that_cannot_be_run_is_refused_naming_its_option(axes, named):
    with pytest.raises(RobustError, match=named):
        scenario_grid(CT, **axes)


@pytest.mark.parametrize('options, named', [
    (['--robust-tau', '0', '0.7'], '--robust-tau'),
    (['--robust-mass-scale', '1,1.1'], '--robust-mass-scale 1,1.1: 2 values for an arm of 3 joints'),
    (['--robust-mass-scale', '0'], '--robust-mass-scale'),
    (['--robust-external-torque', '5'], '--robust-external-torque 5: 1 value for an arm of 3 joints'),
    (['--objective', 'mean'], '--objective'),
    (['--robust-tau', '0', '0.1', '--method', 'nelder-mead', '--budget', '30'], 'budget'),
])
def test_ddarm_tune_refuses_a_bad_robust_option_in_one_line_before_any_work(capsys, tmp_path, options, named):
    assert main([*TUNE, '--runs', str(tmp_path), '--json', *options]) == 2
    captured = capsys.readouterr()
    assert named in captured.err and len(captured.err.strip().splitlines()) == 1 and captured.out == ''
    assert not any(tmp_path.iterdir())


def test_a_vector_that_is_not_numbers_is_an_argument_error(capsys, tmp_path):
    with pytest.raises(SystemExit) as stop:
        main([*TUNE, '--runs', str(tmp_path), '--robust-external-torque', '0,x,0'])
    assert stop.value.code == 2 and '--robust-external-torque' in capsys.readouterr().err


def test_the_search_refuses_a_bad_aggregate_or_scenarios():
    kp, kv = omega_starts(CT, [15.0])
    with pytest.raises(SearchError, match='aggregate'):
        search_gains(CT, index='I', start_kp=kp, start_kv=kv, budget=100, aggregate='median')
    with pytest.raises(SearchError, match='scenarios'):
        search_gains(CT, index='I', start_kp=kp, start_kv=kv, budget=100, scenarios=())


def test_the_robust_gains_worst_case_beats_the_nominal_optimums():
    """τ ∈ {0, 0.1} x mass scale ∈ {0.8, 1.2}: the nominal optimum, tuned on τ = 0 and the model's masses, does
    far worse on the disturbed, mismatched scenarios than gains tuned for the worst of them."""
    scenarios = scenario_grid(CT, taus=[0.0, 0.1], mass_scales=[0.8, 1.2])
    tuning = tune(CT, 'I', 'nelder-mead', 150, (10.0, 15.0), scenarios=scenarios)
    robust = tuning.robust
    assert robust.chosen.worst <= robust.nominal_optimum.worst  # by construction: the nominal optimum is a start
    assert robust.chosen.worst < 0.8 * robust.nominal_optimum.worst
    # Every number reported is the scenario's own episode, and the search's batches agree with it.
    for gains in (robust.chosen, robust.nominal_optimum):
        for scenario, scores in zip(scenarios, gains.per_scenario):
            assert scores == alone(scenario, gains.kp, gains.kv)
    assert tuning.search.index == pytest.approx(robust.chosen.worst, rel=1e-12)
    assert robust.chosen.worst == max(scores['I'] for scores in robust.chosen.per_scenario)
    np.testing.assert_array_equal(robust.chosen.kp, tuning.search.kp)
    # The budget is in episodes: each point evaluated costs one per scenario.
    assert tuning.search.episodes == 4 * len(tuning.search.history_index) <= 150
    assert robust.nominal_search.episodes <= 150


def test_the_mean_over_scenarios_of_other_external_torques_is_what_the_search_minimises():
    """Scenarios of another P^z need a batch call of their own; their indices still come out as run alone."""
    scenarios = scenario_grid(CT, taus=[0.0, 0.1], external_torques=[(0.0, 0.0, 0.0), (0.0, 20.0, 5.0)])
    kp, kv = omega_starts(CT, [10.0, 15.0])
    result = search_gains(CT, index='I1', start_kp=kp, start_kv=kv, budget=200, method='nelder-mead',
                          scenarios=scenarios, aggregate='mean')
    assert result.episodes == 4 * len(result.history_index) <= 200
    per_scenario = [alone(scenario, result.kp, result.kv) for scenario in scenarios]
    assert result.index == pytest.approx(np.mean([scores['I1'] for scores in per_scenario]), rel=1e-12)
    assert len({scores['I1'] for scores in per_scenario}) == 4  # every scenario is a different episode


def test_ddarm_tune_json_has_the_robust_comparison_and_the_yaml_says_it_is_robust(capsys, tmp_path):
    assert main([*TUNE, '--method', 'nelder-mead', '--budget', '150', '--robust-tau', '0', '0.1',
                 '--robust-mass-scale', '0.8', '1.2,1.1,1', '--robust-external-torque', '0,20,5',
                 '--objective', 'mean', '--runs', str(tmp_path), '--run', 'robust',
                 '--out', str(tmp_path / 'gains.yaml'), '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['agree'] and report['episodes'] <= 150  # the ROS check of the robust gains' nominal episode
    robust = report['robust']
    assert robust['objective'] == 'mean'
    assert robust['scenarios'] == [
        {'tau': tau, 'mass_scale': scale, 'external_torque': [0.0, 20.0, 5.0], 'urdf': None}
        for tau in (0.0, 0.1) for scale in ([0.8] * 3, [1.2, 1.1, 1.0])]
    assert robust['chosen']['kp'] == report['kp'] and robust['chosen']['kv'] == report['kv']
    for gains in (robust['chosen'], robust['nominal_optimum']):
        assert set(gains) == {'kp', 'kv', 'per_scenario', 'worst', 'mean'}
        for scenario, scores in zip(robust['scenarios'], gains['per_scenario']):
            spec = dataclasses.replace(CT, tau=scenario['tau'], mass_scale=scenario['mass_scale'],
                                       external_torque=scenario['external_torque'])
            assert scores == alone(spec, gains['kp'], gains['kv'])
        assert gains['worst'] == max(scores['I'] for scores in gains['per_scenario'])
        assert gains['mean'] == pytest.approx(np.mean([scores['I'] for scores in gains['per_scenario']]), rel=1e-15)
    assert robust['chosen']['mean'] <= robust['nominal_optimum']['mean']
    assert robust['nominal_search']['converged'] is None  # Nelder-Mead alone certifies nothing, and says so
    assert robust['nominal_search']['certainty'].startswith('not certified: --method nelder-mead')
    assert report['search_index'] == pytest.approx(robust['chosen']['mean'], rel=1e-12)
    page = (tmp_path / 'robust' / 'report.md').read_text()
    assert '## Robustness' in page and f"{robust['chosen']['mean']:.9g}" in page
    assert '# robust over 4 scenarios (mean I = ' in (tmp_path / 'gains.yaml').read_text()
    written = yaml.safe_load((tmp_path / 'gains.yaml').read_text())['computed_torque']['ros__parameters']
    assert [written['gains'][name]['p'] for name in report['joint_names']] == report['kp']


def test_ddarm_tune_prints_the_scenarios_robust_against_nominal(capsys, tmp_path):
    assert main([*TUNE, '--method', 'nelder-mead', '--budget', '60', '--robust-tau', '0', '0.1',
                 '--runs', str(tmp_path), '--run', 'printed']) == 0
    lines = capsys.readouterr().out.splitlines()
    header = next(i for i, line in enumerate(lines) if 'robust I' in line and 'nominal I' in line)
    assert lines[header + 1].split()[:3] == ['τ', '=', '0'] and lines[header + 2].split()[:3] == ['τ', '=', '0.1']
    assert lines[header + 3].split()[0] == 'worst' and lines[header + 4].split()[0] == 'mean'
    assert sum(line.strip().startswith("WARNING: the nominal optimum's search: not certified") for line in lines) == 1
    summary = json.loads((tmp_path / 'printed' / 'summary.json').read_text())['tune']['robust']
    worst = f"{summary['chosen']['worst']:.6g}"
    assert lines[header + 3].split()[1] == worst


def test_gains_that_diverge_in_a_scenario_have_no_worst_or_mean_to_report():
    pd = EpisodeSpec(controller='pd_gravity', kp=(1.0,) * 3, kv=(1.0,) * 3, delay=0, duration=0.5)
    scenarios = scenario_grid(pd, taus=[0.0, 0.1])
    scores = scenario_scores(scenarios, np.full(3, 1e7), np.full(3, 10.0), 'I1')
    assert all(entry['diverged'] for entry in scores.per_scenario)
    assert scores.worst is None and scores.mean is None
