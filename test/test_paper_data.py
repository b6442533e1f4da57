"""The paper as data: settings.yaml holds what the code held before, frozen; bad settings and results.json
that does not follow the schema are refused naming the file and the key; the claims are judged from typed
results; the experiments score through any recorder and need no ROS."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from ddarm.deprecation import DeprecatedName
from ddarm.paper.claims import judge_claims
from ddarm.paper.schema import (SCHEMA_VERSION, Claim, GainSet, OmegaProcedureRow, Results, ResultsError, StabilityRow,
                                TauRow)
from ddarm.paper.settings import SETTINGS_PATH, Budget, Case, Range, SettingsError, load_settings, paper_settings

ROOT = Path(__file__).resolve().parent.parent
CONTROLLERS = ('pd_gravity', 'computed_torque')

# What ddarm/paper/experiments.py held before the settings were data (spec §10).
TAUS = tuple(round(0.01 * i, 2) for i in range(11))
TABLE2 = {
    ('pd_gravity', False): (0.086, 0.089, 0.095, 0.107, 0.106, 0.113, 0.122, 0.129, 0.138, 0.149, 0.156),
    ('pd_gravity', True): (None, None, None, None, 0.772, 0.628, 2.04, 3.32, 3.96, 4.92, 5.57),
    ('computed_torque', False): (0.046, 0.073, 0.12, 0.16, 0.21, 0.255, 0.301, 0.384, 0.396, 0.443, 0.491),
    ('computed_torque', True): (None, None, None, None, None, None, 1.60, 1.95, 1.90, 1.67, 2.01),
}
TABLE3 = {
    'pd_gravity': (0.274, 0.276, 0.278, 0.278, 0.280, 0.283, 0.285, 0.281, 0.292, 0.296, 0.303),
    'computed_torque': (0.072, 0.083, 0.093, 0.109, 0.122, 0.135, 0.148, 0.144, 0.177, 0.195, 0.215),
}
TABLE4 = {
    ('pd_gravity', 1, 1.0, 0.01): (1.07, 0.27, 0.80), ('computed_torque', 1, 1.0, 0.01): (0.30, 0.07, 0.23),
    ('pd_gravity', 1, 1.0, 0.02): (2.6, 0.64, 1.96), ('computed_torque', 1, 1.0, 0.02): (1.18, 0.53, 0.66),
    ('pd_gravity', 1, 0.5, 0.01): (4.4, 0.76, 3.6), ('computed_torque', 1, 0.5, 0.01): (1.6, 0.63, 1.03),
    ('pd_gravity', 2, 1.0, 0.01): (3.3, 0.96, 2.3), ('computed_torque', 2, 1.0, 0.01): (0.62, 0.17, 0.45),
}
TABLE4_CASES = ((1, 1.0, 0.01), (1, 1.0, 0.02), (1, 0.5, 0.01), (2, 1.0, 0.01))
OMEGA_PROCEDURE_CASES = {
    'computed_torque': ('external torque P^z = (0, 20, 5) N m', dict(external_torque=(0.0, 20.0, 5.0)), 0.5),
    'pd_gravity': ('links 2 and 3 10 % heavier than the model', dict(mass_scale=(1.0, 1.1, 1.1)), 1.0),
}


# Settings ----------------------------------------------------------------------------------

def test_the_settings_hold_what_the_code_held():
    settings = paper_settings()
    assert dict(settings.delays) == {'pd_gravity': 0, 'computed_torque': 1}
    assert settings.taus == TAUS and settings.case == Case(1, 1.0, 0.01) == settings.tracking_case
    for (controller, limited), figures in TABLE2.items():
        assert [settings.table2_figure(controller, limited, tau) for tau in TAUS] == list(figures)
    for controller, figures in TABLE3.items():
        assert [settings.table3_figure(controller, tau) for tau in TAUS] == list(figures)
    assert [(case.trajectory, case.duration, case.period) for case in settings.table4_cases] == list(TABLE4_CASES)
    for (controller, *case), (index, first, second) in TABLE4.items():
        figures = settings.table4_figures(controller, Case(*case))
        assert (figures.I, figures.I1, figures.I2) == (index, first, second)
    assert dict(settings.omega_rules) == {'computed_torque': 15.0, 'pd_gravity': 10.0}
    for controller, (case, disturbance, max_error) in OMEGA_PROCEDURE_CASES.items():
        procedure = settings.omega_procedure[controller]
        assert (procedure.case, dict(procedure.disturbance), procedure.max_error_deg) == (case, disturbance, max_error)
    assert settings.stability.periods == (0.005, 0.01, 0.02, 0.025, 0.04, 0.05)
    assert (settings.stability.omega, settings.stability.claimed_period) == (15.0, 0.01)
    assert Budget.full() == Budget(search_episodes=36000, de_popsize=15, taus=TAUS, pareto_episodes=12000,
                                   robust_episodes=16000)
    assert Budget.quick() == Budget(search_episodes=1200, de_popsize=8, taus=(0.0, 0.05, 0.1), pareto_episodes=1000,
                                    robust_episodes=1600)
    assert settings.claims.table4_I1_ratio == Range(1.5, 4.0)  # what claims.py held before it was data
    assert len(settings.reconstruction) == 8
    assert settings.reconstruction[1].startswith("Trajectory 1 starts at q = (0, π/3, -2π/3), the end at (1, 0, 0) "
                                                 "(docs/model-specification.md §4); the paper's Fig. 4 is lost. "
                                                 "Trajectory 2")
    # The report cites the repository's specification, never the earlier specification outside it.
    assert not any('MODEL.md' in note for note in settings.reconstruction)


def test_the_settings_are_frozen_all_the_way_down():
    settings = paper_settings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.taus = ()
    with pytest.raises(TypeError):
        settings.delays['pd_gravity'] = 1
    with pytest.raises(TypeError):
        settings.omega_procedure['pd_gravity'].disturbance['mass_scale'] = (1.0,) * 3


def _edit(document: dict, key: str, value) -> None:
    """Set (or, for value ..., delete) `key`, a dotted path with [i] for list items."""
    *parents, last = key.replace('[', '.[').split('.')
    for part in parents:
        document = document[int(part[1:-1])] if part.startswith('[') else document[part]
    if value is ...:
        del document[last]
    else:
        document[int(last[1:-1]) if last.startswith('[') else last] = value


@pytest.mark.parametrize('key, value, named', [
    ('table2.pd_gravity.limited', ..., "missing key 'table2.pd_gravity.limited'"),
    ('budgets.full.threads', 2, "unknown key 'budgets.full.threads'"),
    ('delays.pd_gravity', 'zero', 'delays.pd_gravity must be int'),
    ('delays.computed_torque', ..., "missing key 'delays.computed_torque'"),
    ('delays.pid', 2, 'delays.pid (a key) must be one of'),
    ('stability.omega', True, 'stability.omega must be a number'),
    ('taus', 0.1, 'taus must be a list'),
    ('table2.pd_gravity.unlimited', [0.086] * 10, 'table2.pd_gravity.unlimited has 10 figures for the 11 taus'),
    ('table3.computed_torque', [0.072] * 12, 'table3.computed_torque has 12 figures'),
    ('budgets.quick.taus', [0.0, 0.055], 'budgets.quick.taus [0.055]'),
    ('case.trajectory', 3, 'case.trajectory must be one of [1, 2], got 3'),
    ('case.period', 0.005, 'case Case(trajectory=1, duration=1.0, period=0.005) must be one of the table4 cases'),
    ('tracking_case.duration', 2.0,
     'tracking_case Case(trajectory=1, duration=2.0, period=0.01) must be one of the table4'),
    ('table4[3].case.trajectory', 7, 'table4[3].case.trajectory must be one of [1, 2]'),
    ('table4[1].paper.computed_torque.I2', ..., "missing key 'table4[1].paper.computed_torque.I2'"),
    ('table4[2].paper.pd_gravity', ..., "missing key 'table4[2].paper.pd_gravity'"),
    ('omega_procedure.pd_gravity.disturbance.mass_scale', [1.0, 1.1],
     'omega_procedure.pd_gravity.disturbance.mass_scale has 2 values for the 3 joints'),
    ('omega_procedure.pd_gravity.disturbance.friction', [0.0] * 3,
     "omega_procedure.pd_gravity.disturbance.friction (a key) must be one of ('external_torque', 'mass_scale')"),
    ('reconstruction[2]', 7, 'reconstruction[2] must be str'),
    # What the run would refuse only deep into a reproduction, refused when the settings load:
    ('stability.periods', [0.005, 0.01, 0.03],
     'stability.periods[2]: duration 1.0 s is not a whole number of sampling periods 0.03 s'),
    ('stability.periods', [0.005, 0.01, 0.01], "the stability.periods give two episodes the bag name(s) ['dt0.01']"),
    ('stability.periods', [0.01, -0.02], 'stability.periods[1] must be finite and positive, got -0.02'),
    ('table4[2].case.duration', 0.505,
     'table4[2].case: duration 0.505 s is not a whole number of sampling periods 0.01 s'),
    ('table4[1].case.period', 0.0, 'table4[1].case.period must be finite and positive, got 0.0'),
    ('table4[3].case.duration', float('inf'), 'table4[3].case.duration must be finite and positive, got inf'),
    ('table4[3].case', {'trajectory': 1, 'duration': 1.0, 'period': 0.02},
     "the table4 cases give two episodes the bag name(s) ['traj1-T1-dt0.02']"),
    ('delays.computed_torque', 1000, 'delays.computed_torque: compute delay must be a whole number of samples in '
                                     '[0, 100], got 1000'),
    ('delays.pd_gravity', -1, 'delays.pd_gravity: compute delay'),
    ('taus[9]', 5.0, 'taus[9]: tau must be within [0, T = 1.0] s, got 5.0'),
    ('taus[3]', 0.001, "the taus give two episodes the bag name(s) ['tau0.00']"),
    ('omega_rules.pd_gravity', 0.0, 'omega_rules.pd_gravity must be finite and positive, got 0.0'),
    ('omega_rules.computed_torque', -15.0, 'omega_rules.computed_torque must be finite and positive, got -15.0'),
    ('stability.omega', 0.0, 'stability.omega must be finite and positive, got 0.0'),
    ('stability.claimed_period', 0.0, 'stability.claimed_period must be finite and positive'),
    ('omega_procedure.computed_torque.max_error_deg', -0.5,
     'omega_procedure.computed_torque.max_error_deg must be finite and positive, got -0.5'),
    ('omega_procedure.pd_gravity.disturbance.mass_scale', [1.0, -1.1, 1.1], 'omega_procedure.pd_gravity.disturbance: '),
    ('omega_procedure.computed_torque.disturbance', {'external_torque': [0.0, 0.0, 0.0]},
     "omega_procedure.computed_torque.disturbance {'external_torque': (0.0, 0.0, 0.0)} causes no steady-state error"),
    ('budgets.quick.search_episodes', 9, 'budgets.quick.search_episodes must be at least 10, got 9'),
    ('budgets.quick.robust_episodes', 43, 'budgets.quick.robust_episodes must be at least 44, got 43'),
    ('budgets.full.pareto_episodes', 101, 'budgets.full.pareto_episodes must be at least 102, got 101'),
    ('beyond.case', {'trajectory': 2, 'duration': 1.0, 'period': 0.01},
     'beyond.case Case(trajectory=2, duration=1.0, period=0.01) must be case Case(trajectory=1, duration=1.0, '
     'period=0.01)'),
    ('beyond.robust.taus', [0.0, 2.0], 'beyond.robust.taus: 2.0 must be within [0, T = 1] s'),
    ('beyond.robust.mass_scales', [1.0, 1.0], 'beyond.robust.mass_scales must hold at least one value, none twice'),
    ('beyond.stability_map.zetas', [0.0], 'beyond.stability_map.zetas must be finite and positive'),
    ('beyond.law', 'pid', 'beyond.law must be one of'),
    ('budgets.full.de_popsize', 1, 'budgets.full.de_popsize must be at least 2, got 1'),
    ('budgets.quick.taus', [], 'budgets.quick.taus must hold at least one τ'),
    ('budgets.full.search_episodes', 10**400, 'budgets.full.search_episodes is an integer beyond the range of a float'),
    ('stability.omega', -10**400, 'stability.omega is an integer beyond the range of a float'),
    ('claims', ..., "missing key 'claims'"),
    ('claims.table4_I1_ratio.high', 1.0, 'claims.table4_I1_ratio.high must be finite and at least low = 1.5, got 1.0'),
    ('claims.table4_I1_ratio.low', 0.0, 'claims.table4_I1_ratio.low must be finite and positive, got 0.0'),
])
def test_bad_settings_are_refused_naming_the_file_and_the_key(tmp_path, key, value, named):
    document = yaml.safe_load(SETTINGS_PATH.read_text())
    _edit(document, key, value)
    path = tmp_path / 'settings.yaml'
    path.write_text(yaml.safe_dump(document, allow_unicode=True))
    with pytest.raises(SettingsError) as refused:
        load_settings(path)
    assert str(refused.value).startswith(f'{path}: ') and named in str(refused.value), str(refused.value)


def test_a_settings_file_with_a_cases_old_key_T_reads_it_as_duration(tmp_path):
    path = tmp_path / 'settings.yaml'
    path.write_text(SETTINGS_PATH.read_text().replace('duration: ', 'T: '))
    with pytest.warns(DeprecatedName) as notices:
        assert load_settings(path) == paper_settings()
    cases = ['case', 'tracking_case', 'beyond.case'] + [f'table4[{i}].case' for i in range(4)]
    assert sorted(str(notice.message) for notice in notices) == sorted(
        f"{path}: {case}: 'T' is deprecated, read as 'duration' (give 'duration' instead)" for case in cases)
    path.write_text(SETTINGS_PATH.read_text().replace('duration: 0.5,', 'duration: 0.5, T: 1.0,'))
    with pytest.raises(SettingsError, match=r'table4\[2\]\.case: duration given twice, as duration \(0\.5\) and by its '
                                            r'deprecated name T \(1\.0\)'):
        load_settings(path)


def test_a_settings_key_given_twice_is_refused(tmp_path):
    path = tmp_path / 'settings.yaml'
    path.write_text(SETTINGS_PATH.read_text() + '\ndelays: {pd_gravity: 1, computed_torque: 1}\n')
    with pytest.raises(SettingsError, match="duplicate key 'delays'"):
        load_settings(path)


def test_the_settings_file_as_written_loads_as_the_default():
    assert load_settings(SETTINGS_PATH) == paper_settings()


def test_a_case_on_a_trajectory_without_a_motion_file_is_refused(tmp_path):
    document = yaml.safe_load(SETTINGS_PATH.read_text())
    document['table4'].append({'case': {'trajectory': 9, 'duration': 1.0, 'period': 0.01},
                               'paper': document['table4'][0]['paper']})
    path = tmp_path / 'settings.yaml'
    path.write_text(yaml.safe_dump(document, allow_unicode=True))
    with pytest.raises(SettingsError, match=r'table4\[4\]\.case\.trajectory must be one of \[1, 2\], got 9'):
        load_settings(path)


def test_the_smallest_budget_is_the_one_the_search_accepts(tmp_path):
    """The settings' minimum search budget is the least the global search accepts."""
    import re

    from ddarm.control.gains import SEARCH_START_OMEGAS
    from ddarm.episodes.spec import EpisodeSpec
    from ddarm.tuning.search import SearchError, omega_starts, search_gains

    document = yaml.safe_load(SETTINGS_PATH.read_text())
    document['budgets']['quick']['search_episodes'] = 1
    path = tmp_path / 'settings.yaml'
    path.write_text(yaml.safe_dump(document, allow_unicode=True))
    with pytest.raises(SettingsError) as refused:
        load_settings(path)
    least = int(re.search(r'must be at least (\d+)', str(refused.value))[1])
    template = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3)
    start_kp, start_kv = omega_starts(template, SEARCH_START_OMEGAS)
    with pytest.raises(SearchError) as search_refused:  # refused before any episode runs
        search_gains(template, index='I', start_kp=start_kp, start_kv=start_kv, budget=0, method='global')
    assert least == int(re.search(r'at least (\d+) episodes', str(search_refused.value))[1])
    document['budgets']['quick']['search_episodes'] = least
    path.write_text(yaml.safe_dump(document, allow_unicode=True))
    assert load_settings(path).budgets.quick.search_episodes == least


@pytest.mark.parametrize('text, named', [
    ('? [a, b]\n: 1\n', "unknown key \"? ['a', 'b']\""),
    ('delays: {? [pd_gravity]: 0, computed_torque: 1}\n', "delays.? ['pd_gravity'] (a key) must be one of"),
])
def test_a_complex_key_in_the_settings_is_refused_naming_it(tmp_path, text, named):
    plain = 'delays: {pd_gravity: 0, computed_torque: 1}\n'
    path = tmp_path / 'settings.yaml'
    path.write_text(SETTINGS_PATH.read_text().replace(plain, '') + text + (plain if text.startswith('?') else ''))
    with pytest.raises(SettingsError) as refused:
        load_settings(path)
    assert str(refused.value).startswith(f'{path}: ') and named in str(refused.value), str(refused.value)


# The results schema ------------------------------------------------------------------------

def _episode(i1: float, within: bool = True, bag: str = 'bags/x') -> dict:
    return {'I1': i1, 'I2': 1.0, 'I': i1 + 1.0, 'diverged': False, 'max_abs_torque': [1.0, 2.0, 3.0],
            'torque_limit': [2.0, 4.0, 6.0] if within else [2.0, 1.0, 6.0], 'within_limits': within, 'bag': bag}


def results_json() -> dict:
    """A results.json in the schema, every part present, with numbers the claims can be judged from."""
    gains = [{'name': f'{controller}-{index}-traj{t}-T{d:g}-dt{p:g}', 'controller': controller, 'index': index,
              'trajectory': t, 'duration': d, 'T': d, 'period': p, 'delay': delay, 'kp': [1.0, 2.0, 3.0],
              'kv': [4.0, 5.0, 6.0],
              'search': {'episodes': 30, 'wall_time_s': 0.5, 'episodes_per_s': 60.0, 'in_process_index': 0.1,
                         'start_index': float('inf'), 'method': 'global', 'evolution_generations': 3,
                         'restarts': [{'start': 'ω rule', 'popsize': 16, 'episodes': 20, 'index': 0.1, 'stopped_by': ['tolx']},
                                      {'start': 'random', 'popsize': 16, 'episodes': 10, 'index': None,
                                       'stopped_by': ['budget']}],
                         'restarts_within_1_percent': 1, 'converged': False,
                         'certainty': 'not converged: 1 of 2 runs within 1 %'}}
             for controller, delay in (('pd_gravity', 0), ('computed_torque', 1))
             for index, cases in (('I1', TABLE4_CASES[:1]), ('I', TABLE4_CASES)) for t, d, p in cases]
    # PD + gravity: I1 grows 2x with τ, 4x when limited; computed torque: 3x, 1.1x limited; Table 3: 1.5x.
    table2 = [{'controller': controller, 'tau': tau, 'limited': limited,
               'gains': f'{controller}-I1-traj1-T1-dt0.01',
               **_episode(base * (1 + (growth - 1) * tau / 0.1) * (factor if limited and tau else 1.0)),
               'paper': TABLE2[(controller, limited)][TAUS.index(tau)]}
              for controller, base, growth, factor in (('pd_gravity', 0.1, 2.0, 4.0),
                                                       ('computed_torque', 0.05, 3.0, 1.1))
              for limited in (False, True) for tau in (0.0, 0.1)]
    table3 = [{'controller': controller, 'tau': tau, 'limited': False, 'gains': f'{controller}-I-traj1-T1-dt0.01',
               **_episode(0.3 * (1.5 if tau else 1.0), within=tau == 0.0), 'paper': TABLE3[controller][TAUS.index(tau)]}
              for controller in CONTROLLERS for tau in (0.0, 0.1)]
    table4 = [{'controller': controller, 'trajectory': t, 'duration': d, 'T': d, 'period': p, 'delay': delay,
               'gains': f'{controller}-I-traj{t}-T{d:g}-dt{p:g}', 'kp': [1.0, 2.0, 3.0], 'kv': [4.0, 5.0, 6.0],
               **_episode(i1), 'paper': dict(zip(('I', 'I1', 'I2'), TABLE4[(controller, t, d, p)]))}
              for t, d, p in TABLE4_CASES
              for controller, delay, i1 in (('pd_gravity', 0, 0.6), ('computed_torque', 1, 0.2))]
    section2 = {
        'omega_rules': [{'controller': 'computed_torque', 'omega': 15.0, 'kp': [225.0] * 3, 'kv': [30.0] * 3,
                         **_episode(0.4)}],
        'omega_procedure': [{'controller': 'pd_gravity', 'case': 'heavier', 'max_error_deg': 1.0, 'omega_min': 9.0,
                             'omega': None, 'kp': None, 'kv': None, 'I1': None, 'I2': None, 'I': None, 'bag': None,
                             'diverged': None, 'max_abs_torque': None, 'torque_limit': None, 'within_limits': None}],
        'stability': [{'period': period, 'omega_max_stable': 0.426 / period, 'omega_15_stable': 0.426 / period > 15,
                       'I1_at_omega_15': 43 * period, 'diverged_at_omega_15': False, 'bag': 'bags/s'}
                      for period in (0.005, 0.01, 0.05)],
    }
    return {'schema_version': 3, 'command': 'ddarm reproduce --quick', 'quick': True,
            'started': '2026-12-01T09:36:23+0000',
            'settings': {'paper_delays': {'pd_gravity': 0, 'computed_torque': 1}, 'search_budget': 30,
                         'de_popsize': 16, 'taus': [0.0, 0.1], 'start_omegas': [8.0, 15.0],
                         'pareto_budget': 1000, 'robust_budget': 1000},
            'gains': gains, 'table2': table2, 'table3': table3, 'table4': table4, 'section2': section2,
            'pareto': None, 'robust': None, 'stability_map': [{'delay': 1, 'zeta': 1.0, 'omega_delta': 0.4261589}],
            'reconstruction': ['a note'], 'claims': [{'claim': 'c', 'reproduced': True, 'evidence': 'e'}],
            'wall_time_s': 12.5}


def test_results_json_reads_and_writes_back_key_for_key_in_order():
    data = results_json()
    results = Results.from_json(data)
    assert isinstance(results.table2[0], TauRow) and isinstance(results.gains[0], GainSet)
    assert results.section2.omega_procedure[0] == OmegaProcedureRow('pd_gravity', 'heavier', 1.0, 9.0, None, None, None)
    assert json.dumps(results.to_json()) == json.dumps(data)
    assert Results.from_json(json.loads(json.dumps(results.to_json()))) == results


def test_the_schema_has_the_documented_keys():
    fields = {kind: [field.name for field in dataclasses.fields(kind)]
              for kind in (Results, GainSet, TauRow, StabilityRow, Claim)}
    assert fields[Results] == ['schema_version', 'command', 'quick', 'started', 'settings', 'gains', 'table2',
                               'table3', 'table4', 'section2', 'pareto', 'robust', 'stability_map',
                               'reconstruction', 'claims', 'wall_time_s']
    assert fields[TauRow] == ['controller', 'tau', 'limited', 'gains', 'I1', 'I2', 'I', 'diverged', 'max_abs_torque',
                              'torque_limit', 'within_limits', 'bag', 'paper']
    assert fields[GainSet] == ['name', 'controller', 'index', 'trajectory', 'duration', 'period', 'delay', 'kp',
                               'kv', 'search']
    assert fields[StabilityRow] == ['period', 'omega_max_stable', 'omega_15_stable', 'I1_at_omega_15',
                                    'diverged_at_omega_15', 'bag']
    written = Results.from_json(results_json()).to_json()
    assert list(written['gains'][0]) == ['name', 'controller', 'index', 'trajectory', 'duration', 'T', 'period',
                                         'delay', 'kp', 'kv', 'search']
    assert set(written['table4'][0]) == {'controller', 'trajectory', 'duration', 'T', 'period', 'delay', 'gains', 'kp',
                                         'kv', 'I1', 'I2', 'I', 'diverged', 'max_abs_torque', 'torque_limit',
                                         'within_limits', 'bag', 'paper'}


@pytest.mark.parametrize('edit, named', [
    (lambda data: data.pop('wall_time_s'), "missing key 'wall_time_s'"),
    (lambda data: data.update(version=2), "unknown key 'version'"),
    (lambda data: data['settings'].pop('taus'), "missing key 'settings.taus'"),
    (lambda data: data['table2'][1].update(bagg='bags/x'), "unknown key 'table2[1].bagg'"),
    (lambda data: data['table4'][3]['paper'].update(I3=1.0), "unknown key 'table4[3].paper.I3'"),
    (lambda data: data['section2']['omega_procedure'][0].pop('within_limits'),
     "missing key 'section2.omega_procedure[0].within_limits'"),
    (lambda data: data['section2']['stability'][2].pop('diverged_at_omega_15'),
     "missing key 'section2.stability[2].diverged_at_omega_15'"),
    (lambda data: data['gains'][0].update(index='2.5'), "gains[0].index must be one of ('I1', 'I2', 'I'), got '2.5'"),
    (lambda data: data['gains'][3].update(controller='pid'), 'gains[3].controller must be one of'),
    (lambda data: data['table3'][0].update(tau='0.1'), "table3[0].tau must be a number, got '0.1'"),
    (lambda data: data['table3'][0].update(I1=True), 'table3[0].I1 must be a number, got True'),
    (lambda data: data['table2'][0].update(limited=0), 'table2[0].limited must be bool, got 0'),
    (lambda data: data['table4'][0].update(kp=5.0), 'table4[0].kp must be a list'),
    (lambda data: data['table4'][0].update(trajectory=1.0), 'table4[0].trajectory must be int, got 1.0'),
    (lambda data: data['table2'][0].update(paper='0.086'), "table2[0].paper must be a number, got '0.086'"),
    (lambda data: data['claims'][0].update(reproduced=None), 'claims[0].reproduced must be bool, got None'),
    (lambda data: data['table4'][5].update(gains='pd_gravity-3.2-traj1-T1-dt0.01'),
     "table4[5].gains names 'pd_gravity-3.2-traj1-T1-dt0.01', which is not in results.gains"),
    (lambda data: data['gains'][2].update(name=data['gains'][1]['name']), 'gains[2].name'),
    (lambda data: data.update(section2=[]), 'section2 must be a mapping'),
    (lambda data: data.pop('schema_version'), "missing key 'schema_version'"),
    (lambda data: data.update(schema_version=1), 'schema_version is 1: this ddarm reads results.json of '
                                                 'schema_version 3 only'),
    (lambda data: data.update(schema_version='1'), "schema_version is '1'"),
    (lambda data: data.update(schema_version=True), 'schema_version is True'),
])
def test_results_off_the_schema_are_refused_naming_the_key(edit, named):
    data = results_json()
    edit(data)
    with pytest.raises(ResultsError) as refused:
        Results.from_json(data, 'runs/x/results.json')
    assert str(refused.value).startswith('runs/x/results.json: ') and named in str(refused.value), str(refused.value)


def test_results_of_before_duration_read_from_T_alone():
    data = results_json()
    for row in data['gains'] + data['table4']:
        del row['duration']
    assert Results.from_json(data) == Results.from_json(results_json())


def test_a_duration_and_a_T_that_differ_are_refused():
    data = results_json()
    data['table4'][2]['T'] = 2.0
    with pytest.raises(ResultsError,
                       match=r'table4\[2\]\.duration is 1\.0 but its deprecated name table4\[2\]\.T is 2\.0'):
        Results.from_json(data, 'runs/x/results.json')


def test_results_are_written_with_their_schema_version_first():
    results = Results(command='ddarm reproduce', quick=True, started='now', settings=Results.from_json(
        results_json()).settings)
    assert SCHEMA_VERSION == 3 and list(results.to_json())[0] == 'schema_version'
    assert results.to_json()['schema_version'] == 3


def test_another_versions_keys_are_refused_by_the_version_not_by_a_key():
    data = results_json()
    data.update(schema_version=1, table5=[])
    del data['table2']
    with pytest.raises(ResultsError, match='schema_version is 1'):
        Results.from_json(data, 'old.json')


def test_a_results_file_that_is_not_json_is_refused_naming_it(tmp_path):
    path = tmp_path / 'results.json'
    path.write_text('{"command": ')
    with pytest.raises(ResultsError, match=f'^{path}: cannot read the results'):
        Results.load(path)
    path.write_text(json.dumps(results_json()))
    assert Results.load(path) == Results.from_json(results_json())


# Claims and experiments ----------------------------------------------------------------------

def test_the_claims_are_judged_from_the_typed_results():
    claims = judge_claims(Results.from_json(results_json()), paper_settings())
    verdicts = [claim.reproduced for claim in claims]
    # CT better everywhere (ratio 3); within 1.5-4; CT grows faster; PD degrades more when limited; Table 3
    # grows less (1.5 vs 2 and 3); two Table 3 episodes beyond the limit; stable at Δ <= 0.01 only.
    assert verdicts == [True, True, True, True, True, False, True]
    assert claims[0].evidence == 'Table 4 I1 ratios PD / CT per case: 3.00, 3.00, 3.00, 3.00'
    assert claims[5].evidence.startswith('2 of 4 Table 3 episodes exceed a limit; the largest |P_i| / limit_i is 2.00')
    assert claims[6].claim == 'At 100 Hz and above, computed torque stays stable at ω = 15'
    assert claims[6].evidence.count('Δ = ') == 2


class Recorder:
    """An EpisodeRecorder that records nothing and scores what it is told."""

    def __init__(self, scored: dict) -> None:
        self.scored, self.runs = scored, []

    def record_and_score(self, spec, bag, command=None):
        self.runs.append((spec, bag, command))
        return None, self.scored


def test_an_episode_row_holds_the_papers_torque_limit_from_the_bags_nominal_maxima(tmp_path):
    from ddarm.episodes.spec import EpisodeSpec
    from ddarm.paper.experiments import Reproduction

    (tmp_path / 'bags').mkdir()
    reproduction = Reproduction(tmp_path, Budget.quick(), 'ddarm reproduce --quick')
    nominal = [281.6, 254.5, 55.3]
    recorder = Recorder({'I1': 0.5, 'I2': 1.5, 'I': 2.0, 'diverged': False, 'max_abs_torque': [563.2, 100.0, 1.0],
                         'max_abs_nominal_torque': nominal})
    spec = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3)
    row = reproduction._episode(recorder, spec, 'one')
    assert row['torque_limit'] == tuple((np.array(nominal) * 2.0).tolist())
    assert row['within_limits'] is True and row['bag'] == 'bags/one'
    assert recorder.runs == [(spec, tmp_path / 'bags' / 'one', 'ddarm reproduce --quick')]
    assert reproduction.results.quick is True and reproduction.results.settings.taus == (0.0, 0.05, 0.1)


def test_the_experiments_import_nothing_from_ros():
    done = subprocess.run([sys.executable, '-c', 'import sys, ddarm.paper.experiments, ddarm.paper.report; '
                           "print(sorted(name for name in sys.modules if name.startswith('ddarm.ros')))"],
                          capture_output=True, text=True, cwd=ROOT, check=True)
    assert done.stdout.strip() == '[]'
