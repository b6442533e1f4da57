"""`ddarm pareto`: the I1-I2 front is mutually non-dominated and sorted, its ends reach the single-index optima of
`ddarm tune`'s search, every point re-runs alone to its reported indices, its controller YAMLs load with its
gains, and a bad option is refused in one line before anything is searched."""

import contextlib
import io
import json

import numpy as np
import pytest
import yaml

from ddarm.cli.main import main
from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.ros.interface import flat_parameters, given_gains
from ddarm.tuning.methods import DEFAULT_METHOD
from ddarm.tuning.methods import ParetoError
from ddarm.tuning.pareto import pareto_front, spread_points
from ddarm.tuning.tune import tune

# The paper's arm and trajectory 1 over half its T, small budgets: a front in a few seconds.
DURATION = 0.5
TUNE_BUDGET = 300
BUDGET = 800
POINTS = 12
COMMAND = ['pareto', '--controller', 'computed_torque', '--duration', str(DURATION), '--budget', str(BUDGET),
           '--tune-budget', str(TUNE_BUDGET), '--points', str(POINTS)]
TEMPLATE = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, duration=DURATION)
# The front's ends against the single-index searches': as low, but for the last digits of a sum.
RELATIVE = 1e-12


def run_main(arguments) -> tuple[int, str]:
    output = io.StringIO()
    with contextlib.redirect_stdout(output):
        code = main(arguments)
    return code, output.getvalue()


@pytest.fixture(scope='module')
def front_run(tmp_path_factory):
    """The JSON report of one `ddarm pareto --json --yaml-dir --plot` run, and its output folder."""
    folder = tmp_path_factory.mktemp('pareto')
    code, output = run_main([*COMMAND, '--json', '--yaml-dir', str(folder / 'gains'),
                             '--plot', str(folder / 'front.png')])
    assert code == 0
    return json.loads(output), folder


def test_the_json_holds_the_front_as_gains_and_indices(front_run):
    report, _ = front_run
    assert report['controller'] == 'computed_torque' and report['joint_names'] == ['joint1', 'joint2', 'joint3']
    assert 3 <= len(report['front']) <= POINTS
    for point in report['front']:
        assert set(point) == {'I1', 'I2', 'kp', 'kv'}
        assert len(point['kp']) == len(point['kv']) == 3
        assert all(gain > 0 for gain in point['kp'] + point['kv'])
    assert report['episodes'] <= BUDGET
    assert report['front_size'] >= len(report['front'])
    assert set(report['single_index_optima']) == {'I1', 'I'}


def test_the_front_is_sorted_by_I1_and_mutually_non_dominated(front_run):
    front = front_run[0]['front']
    I1 = np.array([point['I1'] for point in front])
    I2 = np.array([point['I2'] for point in front])
    assert np.all(np.diff(I1) > 0) and np.all(np.diff(I2) < 0)
    for a in range(len(front)):
        for b in range(len(front)):
            assert a == b or not (I1[b] <= I1[a] and I2[b] <= I2[a]), f'point {b} dominates point {a}'


def test_the_ends_reach_the_single_index_optima_of_the_tune_search(front_run):
    report, _ = front_run
    front = report['front']
    optimum_I1 = tune(TEMPLATE, 'I1', DEFAULT_METHOD, TUNE_BUDGET, SEARCH_START_OMEGAS, 0).best
    optimum_I = tune(TEMPLATE, 'I', DEFAULT_METHOD, TUNE_BUDGET, SEARCH_START_OMEGAS, 0).best
    assert front[0]['I1'] <= optimum_I1['I1'] * (1 + RELATIVE)
    least_I = min(point['I1'] + point['I2'] for point in front)
    assert least_I <= optimum_I['I'] * (1 + RELATIVE)
    least = front[report['least_I_point']]
    assert least['I1'] + least['I2'] == least_I
    # The report's own account of the optima is the searches' (the same arguments, so the same result), each
    # on the front or dominated by it.
    reported = report['single_index_optima']
    assert reported['I1']['I1'] == optimum_I1['I1'] and reported['I']['I'] == optimum_I['I']
    for optimum in reported.values():
        assert optimum['where'].startswith('on the front') or optimum['where'] == 'dominated by the front'


def test_every_point_re_run_alone_gives_its_reported_indices(front_run):
    for point in front_run[0]['front']:
        episode = run_episode(TEMPLATE.with_gains(point['kp'], point['kv']))
        assert not episode.diverged[0]
        assert (float(episode.I1[0]), float(episode.I2[0])) == (point['I1'], point['I2'])


def test_the_yaml_dir_holds_each_points_controller_yaml_with_its_gains(front_run):
    report, folder = front_run
    files = sorted((folder / 'gains').iterdir())
    assert [path.name for path in files] == [f'point-{rank:02d}.yaml' for rank in range(len(report['front']))]
    assert report['yaml_files'] == [str(path) for path in files]
    for path, point in zip(files, report['front']):
        parameters = yaml.safe_load(path.read_text())['computed_torque']['ros__parameters']
        assert given_gains(flat_parameters(parameters), report['joint_names']) == (point['kp'], point['kv'])
        assert (parameters['delay'], parameters['period']) == (1, 0.01)


def test_the_plot_is_a_png(front_run):
    report, folder = front_run
    assert report['plot'] == str(folder / 'front.png')
    assert (folder / 'front.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_without_json_a_table_names_the_ends_and_the_least_I_point(capsys):
    assert main(['pareto', '--controller', 'computed_torque', '--duration', str(DURATION), '--budget', '150',
                 '--tune-budget', str(TUNE_BUDGET), '--points', '5']) == 0
    output = capsys.readouterr().out
    assert 'least I1' in output and 'least I2' in output and 'least I' in output
    assert 'kp (joint1, joint2, joint3)' in output


@pytest.mark.parametrize('arguments, option', [
    (['--budget', '50'], '--budget'),
    (['--points', '2'], '--points'),
    (['--seed', '-1'], '--seed'),
    (['--plot', 'front.txt'], '--plot'),
    (['--tune-budget', '5'], '--tune-budget'),
])
def test_bad_options_are_refused_in_one_line_naming_the_option(capsys, arguments, option):
    try:
        code = main(['pareto', '--controller', 'computed_torque', '--duration', str(DURATION), *arguments])
    except SystemExit as refused:  # argparse's refusal, when parsing the option
        code = refused.code
    assert code == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('ddarm pareto: ') and option in lines[0]


def test_an_existing_yaml_dir_with_files_is_refused_and_left_alone(capsys, tmp_path):
    (tmp_path / 'kept.yaml').write_text('mine')
    assert main([*COMMAND, '--yaml-dir', str(tmp_path)]) == 2
    assert '--yaml-dir' in capsys.readouterr().err
    assert [path.name for path in tmp_path.iterdir()] == ['kept.yaml']


def test_the_core_keeps_its_seeds_and_refuses_what_it_cannot_run():
    seed_kp, seed_kv = (900.0, 1300.0, 1300.0), (45.0, 55.0, 55.0)
    seeded = run_episode(TEMPLATE.with_gains(seed_kp, seed_kv))
    result = pareto_front(TEMPLATE, budget=101, seeds=[(seed_kp, seed_kv)], searches=0, points=1000)
    # Nothing evaluated is lost: the seed, as given, is a point of the front, or a point of the front dominates it.
    on_front = ((float(seeded.I1[0]), float(seeded.I2[0])) in [(point.I1, point.I2) for point in result.front])
    assert result.seeds_on_front == (on_front,)
    assert on_front or any(point.I1 <= seeded.I1[0] and point.I2 <= seeded.I2[0] for point in result.front)
    assert result.episodes == 101 and result.generations == 1 and result.searches == 0
    for arguments, name in (({'budget': 100, 'points': 2}, 'points'), ({'budget': 50}, 'budget'),
                            ({'budget': 100, 'searches': 2}, 'searches'),
                            ({'budget': 100, 'seeds': [((1.0, 2.0), (1.0, 2.0))]}, 'seed 0')):
        with pytest.raises(ParetoError, match=name):
            pareto_front(TEMPLATE, **arguments)


def test_spread_points_keeps_both_ends_and_the_least_I_point():
    I1 = np.linspace(1.0, 2.0, 50)
    indices = np.column_stack([I1, 3.0 / I1 ** 4])
    kept = spread_points(indices, 5)
    assert len(kept) == 5 and list(kept) == sorted(kept)
    assert {0, 49, int(np.argmin(indices.sum(axis=1)))} <= set(kept.tolist())
    assert list(spread_points(indices[:4], 5)) == [0, 1, 2, 3]
