"""`ddarm reproduce --quick`: the report, bags and figures exist, and every table number is what `ddarm score`
gets from its bag."""

import json

import pytest
from rosbags.highlevel import AnyReader

from ddarm.recording.bags import read_episode_bag, score_bag
from ddarm.cli.main import main
from ddarm.paper.schema import Results

PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def reproduction(tmp_path_factory):
    out = tmp_path_factory.mktemp('paper') / 'paper'
    assert main(['reproduce', '--quick', '--jobs', '2', '--out', str(out)]) == 0
    return out, json.loads((out / 'results.json').read_text())


def _without_times(value):
    """results.json without what depends on the run rather than the episodes: wall times, rates, start, command."""
    if isinstance(value, dict):
        return {key: _without_times(item) for key, item in value.items()
                if key not in ('wall_time_s', 'episodes_per_s', 'started', 'command')}
    if isinstance(value, list):
        return [_without_times(item) for item in value]
    return value


def _recorded(bag):
    """What a bag holds of its episode, as plain values: the reference, every state and command, and the clock.

    Decoded, not as bytes: CDR's padding bytes are whatever was in memory. Not the plant's report, which names its
    session's node and wall time, nor the episode's record, which names the command."""
    episode = read_episode_bag(bag)
    with AnyReader([bag]) as reader:
        clock = [stamp for connection, stamp, _ in reader.messages() if connection.topic == '/clock']
    arrays = (episode.reference_times, episode.q_ref, episode.v_ref, episode.a_ref, episode.nominal)
    return ([array.tolist() for array in arrays],
            {n: [None if field is None else field.tolist() for field in state] for n, state in episode.states.items()},
            {n: effort.tolist() for n, effort in episode.commands.items()}, clock)


def test_one_graph_session_and_two_give_the_same_results_and_bags(reproduction, tmp_path):
    out, results = reproduction
    alone = tmp_path / 'paper'
    assert main(['reproduce', '--quick', '--jobs', '1', '--out', str(alone)]) == 0
    assert _without_times(json.loads((alone / 'results.json').read_text())) == _without_times(results)
    bags = sorted(path.parent.name for path in (out / 'bags').glob('*/metadata.yaml'))
    assert bags == sorted(path.parent.name for path in (alone / 'bags').glob('*/metadata.yaml')) and len(bags) > 40
    for name in bags:
        assert _recorded(alone / 'bags' / name) == _recorded(out / 'bags' / name), name


def test_the_report_and_its_figures_exist(reproduction):
    out, results = reproduction
    report = (out / 'REPORT.md').read_text()
    for figure in ('tracking', 'index_vs_tau', 'table4', 'stability'):
        path = out / 'figures' / f'{figure}.png'
        assert path.read_bytes()[:8] == PNG_SIGNATURE and path.stat().st_size > 10_000
        assert f'figures/{figure}.png' in report
    for claim in results['claims']:
        assert claim['claim'] in report


def test_every_table_number_is_the_score_of_its_bag(reproduction):
    out, results = reproduction
    rows = (results['table2'] + results['table3'] + results['table4'] + results['section2']['omega_rules']
            + [row for row in results['section2']['omega_procedure'] if row['bag']])
    assert len(rows) >= 2 * 3 * 2 + 2 * 3 + 8
    for row in rows:
        scored = score_bag(out / row['bag'])
        for key in ('I1', 'I2', 'I'):
            assert row[key] == scored[key], (row['bag'], key)
    for row in results['section2']['stability']:
        assert row['I1_at_omega_15'] == score_bag(out / row['bag'])['I1']


def test_results_have_the_documented_shape(reproduction):
    out, results = reproduction
    assert len(results['table4']) == 8
    for row in results['table4']:
        assert {'controller', 'trajectory', 'duration', 'T', 'period', 'I', 'I1', 'I2', 'kp', 'kv', 'bag',
                'paper'} <= set(row)
        assert row['T'] == row['duration']
        assert row['controller'] in ('pd_gravity', 'computed_torque')
        assert row['delay'] == (0 if row['controller'] == 'pd_gravity' else 1)
    assert {row['limited'] for row in results['table2']} == {False, True}
    assert results['quick'] is True and results['claims']
    # The schema reads it back (no key missing or extra), and names the indices I1, I2, I.
    assert Results.load(out / 'results.json').to_json() == results
    assert {entry['index'] for entry in results['gains']} == {'I1', 'I'}
    assert all(f"-{entry['index']}-" in entry['name'] for entry in results['gains'])


def test_reproduce_never_overwrites(reproduction, capsys):
    out, _ = reproduction
    assert main(['reproduce', '--quick', '--out', str(out)]) == 2
    assert 'exists already' in capsys.readouterr().err
