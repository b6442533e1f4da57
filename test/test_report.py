"""The report: REPORT.md with our figures beside the paper's, linked to their bags, and the PNG figures;
results without a required key, or an output folder already holding a report, are refused."""

import shutil
import struct

import pytest

from ddarm.recording.bags import EpisodeBagWriter, score_bag
from ddarm.episodes.spec import EpisodeSpec
from ddarm.paper.report import ReportError, write_report
from ddarm.paper.schema import Results
from ddarm.paper.tables import number
from ddarm.ros.node_parameters import episode_record
from graph_helpers import InProcessGraph

CONTROLLERS = ('pd_gravity', 'computed_torque')
DELAYS = {'pd_gravity': 0, 'computed_torque': 1}
GAINS = {'pd_gravity': ((28000.0, 27000.0, 3500.0), (1760.0, 1700.0, 220.0)),
         'computed_torque': ((900.0,) * 3, (60.0,) * 3)}
TAUS = [round(0.01 * i, 2) for i in range(11)]
PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
# The fields of an episode row beyond its indices and bag (results.json's schema).
EPISODE = {'diverged': False, 'max_abs_torque': [10.0, 300.0, 50.0], 'torque_limit': [20.0, 400.0, 100.0],
           'within_limits': True}


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """One episode per controller (trajectory 1, T = 1 s, Δ = 0.01 s) recorded through in-process nodes."""
    import rclpy

    folder = tmp_path_factory.mktemp('recorded')
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        for controller in CONTROLLERS:
            kp, kv = GAINS[controller]
            spec = EpisodeSpec(controller=controller, kp=kp, kv=kv, delay=DELAYS[controller])
            graph = InProcessGraph(context, spec)
            with EpisodeBagWriter(folder / 'bags' / controller,
                                  episode_record(spec, graph.plan, 'ros-lockstep', 'test')) as bag:
                graph.bag = bag
                try:
                    graph.run()
                    bag.close(complete=True)
                finally:
                    graph.close()
    finally:
        rclpy.try_shutdown(context=context)
    return folder


def synthetic_results(scores: dict) -> dict:
    """A schema-complete results dict (results.json's) whose tables all point at the two recorded bags."""
    def bag(controller):
        return f'bags/{controller}'

    gains = [{'name': f'{controller}-{index}', 'controller': controller, 'index': index, 'trajectory': 1,
              'duration': 1.0, 'T': 1.0, 'period': 0.01, 'delay': DELAYS[controller], 'kp': list(GAINS[controller][0]),
              'kv': list(GAINS[controller][1]),
              'search': {'episodes': 600, 'wall_time_s': 0.5, 'episodes_per_s': 1200.0, 'in_process_index': 0.1,
                         'start_index': 4.0, 'method': 'global', 'evolution_generations': 3,
                         'restarts': [{'start': 'ω rule', 'popsize': 16, 'episodes': 20, 'index': 0.1, 'stopped_by': ['tolx']},
                                      {'start': 'random', 'popsize': 16, 'episodes': 10, 'index': None,
                                       'stopped_by': ['budget']}],
                         'restarts_within_1_percent': 1, 'converged': False,
                         'certainty': 'not converged: 1 of 2 runs within 1 %'}}
             for controller in CONTROLLERS for index in ('I1', 'I')]

    def tau_row(controller, tau, limited, index, first, paper):
        return {'controller': controller, 'tau': tau, 'limited': limited, 'gains': f'{controller}-{index}',
                'I1': first, 'I2': 1.0, 'I': first + 1.0, 'diverged': False, 'max_abs_torque': [10.0, 300.0, 50.0],
                'torque_limit': [20.0, 400.0, 100.0] if tau < 0.05 else [20.0, 200.0, 100.0],
                'within_limits': tau < 0.05, 'bag': bag(controller), 'paper': paper}

    table2 = [tau_row(controller, tau, limited, 'I1', 0.1 + tau * (3 if limited else 0.6) + 0.00123,
                      0.156 if tau == 0.1 and not limited else None)
              for controller in CONTROLLERS for limited in (False, True) for tau in TAUS]
    table3 = [tau_row(controller, tau, False, 'I', 0.3 + tau * 0.2 + 0.00456, 0.303 if tau == 0.1 else None)
              for controller in CONTROLLERS for tau in TAUS]
    table2[-1]['diverged'] = True
    table3[0]['bag'] = 'bags/never-recorded'
    cases = [(1, 1.0, 0.01), (1, 1.0, 0.02), (1, 0.5, 0.01), (2, 1.0, 0.01)]
    table4 = []
    for trajectory, duration, period in cases:
        for controller in CONTROLLERS:
            scored = scores[controller] if (trajectory, duration, period) == cases[0] else {
                'I': 2.5, 'I1': 0.5, 'I2': 2.0}
            table4.append({'controller': controller, 'trajectory': trajectory, 'duration': duration,
                           'T': duration, 'period': period, 'delay': DELAYS[controller], 'gains': f'{controller}-I',
                           'kp': list(GAINS[controller][0]), 'kv': list(GAINS[controller][1]), 'I': scored['I'],
                           'I1': scored['I1'], 'I2': scored['I2'], **EPISODE, 'bag': bag(controller),
                           'paper': {'I': 1.07, 'I1': 0.27, 'I2': 0.80} if controller == 'pd_gravity'
                           else {'I': 0.30, 'I1': 0.07, 'I2': 0.23}})
    section2 = {
        'omega_rules': [{'controller': controller, 'omega': 15.0, 'kp': [225.0] * 3, 'kv': [30.0] * 3, 'I1': 0.7,
                         'I2': 1.2, 'I': 1.9, **EPISODE, 'bag': bag(controller)} for controller in CONTROLLERS],
        'omega_procedure': [
            {'controller': 'computed_torque', 'case': 'external torque P^z = (0, 20, 5) N m', 'max_error_deg': 0.5,
             'omega_min': 12.3, 'omega': 20.5, 'kp': [420.25] * 3, 'kv': [41.0] * 3, 'I1': 0.4, 'I2': 0.9,
             'I': 1.3, 'bag': bag('computed_torque'), **EPISODE},
            {'controller': 'pd_gravity', 'case': 'links 10 % heavier', 'max_error_deg': 0.01, 'omega_min': 80.0,
             'omega': None, 'kp': None, 'kv': None, 'I1': None, 'I2': None, 'I': None, 'bag': None,
             **dict.fromkeys(EPISODE)}],
        'stability': [{'period': period, 'omega_max_stable': 0.6 / period, 'omega_15_stable': 0.6 / period > 15,
                       'I1_at_omega_15': 0.5, 'diverged_at_omega_15': False, 'bag': bag('computed_torque')}
                      for period in (0.005, 0.01, 0.05)],
    }
    claims = [{'claim': 'computed torque tracks better: Table 4 I1 1.5 to 4 times smaller', 'reproduced': True,
               'evidence': 'I1 ratios PD/CT: 3.9, 1.2, 1.2, 5.6'},
              {'claim': 'with torque limits PD + gravity degrades far more', 'reproduced': False,
               'evidence': 'limited at τ = 0.1: PD 0.4, CT 0.5'}]
    search = gains[0]['search']
    front = [{'I1': 0.07 + 0.01 * i, 'I2': 0.4 - 0.03 * i, 'kp': [900.0] * 3, 'kv': [60.0] * 3} for i in range(5)]
    pareto = {'controller': 'computed_torque', 'trajectory': 1, 'duration': 1.0, 'T': 1.0, 'period': 0.01, 'delay': 1,
              'method': 'NSGA-II', 'episodes': 1000, 'wall_time_s': 2.0, 'front_size': 9, 'searches': 3,
              'searches_converged': 1, 'seeds': ['computed_torque-I1', 'computed_torque-I'],
              'seeds_on_front': [True, True], 'front': front}
    rows = [{'tau': tau, 'mass_scale': [scale] * 3, 'gains': name, 'I1': 0.1, 'I2': 0.3, 'I': 0.4 + tau,
             'diverged': False, 'bag': bag('computed_torque')}
            for tau in (0.0, 0.1) for scale in (0.8, 1.2) for name in ('robust', 'nominal')]
    robust = {'controller': 'computed_torque', 'trajectory': 1, 'duration': 1.0, 'T': 1.0, 'period': 0.01, 'delay': 1,
              'objective': 'worst', 'kp': [900.0] * 3, 'kv': [60.0] * 3, 'nominal': 'computed_torque-I',
              'search': search, 'rows': rows}
    stability_map = [{'delay': d, 'zeta': z, 'omega_delta': w} for d, z, w in
                     ((0, 0.7, 1 / 0.7), (0, 1.0, 1.0), (1, 0.7, 0.495), (1, 1.0, 0.4262))]
    return {'schema_version': 3, 'command': 'ddarm reproduce --out runs/paper --quick', 'quick': True,
            'started': '2026-11-23T12:30:00+0000', 'wall_time_s': 41.7,
            'settings': {'paper_delays': DELAYS, 'search_budget': 600, 'de_popsize': 16, 'taus': TAUS,
                         'start_omegas': [8.0, 12.0, 15.0, 20.0, 30.0], 'pareto_budget': 1000,
                         'robust_budget': 1000},
            'gains': gains, 'table2': table2, 'table3': table3, 'table4': table4, 'section2': section2,
            'pareto': pareto, 'robust': robust, 'stability_map': stability_map,
            'claims': claims,
            'reconstruction': ['Joint 2 at the origin, on the z axis at z = 0.',
                               'Trajectory 1 starts at q0 = (0, π/3, -2π/3).']}


def output_folder(bags, tmp_path):
    out = tmp_path / 'out'
    shutil.copytree(bags / 'bags', out / 'bags')
    return out


@pytest.fixture(scope='module')
def scores(bags):
    return {controller: score_bag(bags / 'bags' / controller) for controller in CONTROLLERS}


@pytest.fixture(scope='module')
def written(bags, scores, tmp_path_factory):
    out = output_folder(bags, tmp_path_factory.mktemp('report'))
    results = synthetic_results(scores)
    return out, results, write_report(out, Results.from_json(results))


def test_the_report_puts_our_figures_beside_the_papers_and_links_their_bags(written, scores):
    out, results, files = written
    assert files[0] == out / 'REPORT.md'
    text = (out / 'REPORT.md').read_text()
    assert '`ddarm reproduce --out runs/paper --quick`' in text and '**quick**' in text
    assert 'ddarm score bags/' in text
    # Table 2, PD + gravity, τ = 0.1, unlimited: ours 0.1612..., paper 0.156; limit reached there.
    assert '| 0.10 | [0.161](bags/pd_gravity) | 0.156 | [0.401](bags/pd_gravity) | — | **yes** (1.50×) |' in text
    assert '| 0.00 | [0.101](bags/pd_gravity) | — |' in text
    assert '**diverged**' in text  # computed torque, limited, τ = 0.1
    # Table 3: ours, the paper's 0.303, and the missing bag flagged rather than linked.
    assert '[0.325](bags/computed_torque) | 0.303 | **no** (1.50×)' in text
    assert '(**bag `bags/never-recorded` missing**)' in text
    # Table 4: the tracking case's figures are those its bags score.
    for controller, paper in (('pd_gravity', '1.07'), ('computed_torque', '0.3')):
        assert f"[{number(scores[controller]['I'])}](bags/{controller}) | {paper} |" in text
    assert '(28000, 27000, 3500)' in text
    # The optimised gains, with their undisturbed episode's index from its bag beside the search's own.
    assert '| `pd_gravity-I1` |' in text and '| 4.00 → 0.100 | [0.101](bags/pd_gravity) |' in text
    assert f"| 4.00 → 0.100 | [{number(scores['computed_torque']['I'])}](bags/computed_torque) |" in text
    # Each search's certificate beside its runs: one that did not converge gives its line.
    assert '| 1 of 2 | **not converged: 1 of 2 runs within 1 %** | 0.100, diverged |' in text
    assert 'none: even ω_min breaks the torque conditions' in text
    assert '| 0.05 | 20 | 12.0 | **no** |' in text
    for claim in results['claims']:
        assert claim['claim'] in text and claim['evidence'] in text
    assert '**REPRODUCED**: computed torque tracks better' in text
    assert '**NOT REPRODUCED**: with torque limits' in text
    # The model is cited where the repository holds it, by section; the earlier specification is not in the repository.
    assert 'fixed in docs/model-specification.md (§1, §4)' in text
    assert '## Claims (docs/model-specification.md §10)' in text
    assert '(docs/model-specification.md §6)' in text and 'MODEL.md' not in text
    for note in results['reconstruction']:
        assert f'- {note}' in text
    for name in ('tracking', 'index_vs_tau', 'table4', 'stability'):
        assert f'(figures/{name}.png)' in text


def test_every_figure_is_a_drawn_png(written):
    out, _, files = written
    names = {path.name for path in files[1:]}
    assert names == {'tracking.png', 'index_vs_tau.png', 'table4.png', 'stability.png', 'pareto.png'}
    for path in files[1:]:
        data = path.read_bytes()
        assert data[:8] == PNG_SIGNATURE and data[12:16] == b'IHDR', path
        width, height = struct.unpack('>II', data[16:24])
        assert width >= 800 and height >= 500, (path, width, height)
        assert len(data) > 20_000, path  # far beyond an empty canvas


@pytest.mark.parametrize('remove, named', [
    (lambda results: results.pop('table4'), "'table4'"),
    (lambda results: results['table2'][3].pop('bag'), 'table2[3].bag'),
    (lambda results: results['section2'].pop('stability'), 'section2.stability'),
    (lambda results: results['gains'][0]['search'].pop('episodes_per_s'), 'gains[0].search.episodes_per_s'),
    (lambda results: results['table4'][1]['paper'].pop('I2'), 'table4[1].paper.I2'),
    (lambda results: results['table3'][2].update(controller='pid'), 'table3[2].controller'),
])
def test_results_missing_a_key_or_naming_an_unknown_controller_are_refused_by_name(bags, scores, tmp_path, remove,
                                                                                   named):
    out = output_folder(bags, tmp_path)
    results = synthetic_results(scores)
    remove(results)
    with pytest.raises(ValueError, match=named.replace('[', r'\[').replace(']', r'\]')):
        write_report(out, Results.from_json(results))
    assert not (out / 'REPORT.md').exists() and not (out / 'figures').exists()


def test_a_missing_tracking_case_is_refused(bags, scores, tmp_path):
    results = synthetic_results(scores)
    results['table4'] = [row for row in results['table4']
                        if (row['trajectory'], row['duration'], row['period']) != (1, 1.0, 0.01)]
    with pytest.raises(ReportError, match='no row for pd_gravity, trajectory 1'):
        write_report(output_folder(bags, tmp_path), Results.from_json(results))


def test_an_existing_report_is_not_overwritten(bags, scores, tmp_path):
    out = output_folder(bags, tmp_path)
    (out / 'figures').mkdir()
    with pytest.raises(ReportError, match='exists already, not overwriting'):
        write_report(out, Results.from_json(synthetic_results(scores)))
    assert not (out / 'REPORT.md').exists()
