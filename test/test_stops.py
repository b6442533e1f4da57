"""Clean stops (docs/faults.md 16, 23): SIGINT and SIGTERM end any ddarm command with one line and 128 + the signal,
its bag under way closed as incomplete and its run marked interrupted; SIGKILL leaves no node process behind."""

import json
import os
import signal

import pytest

from ddarm.recording.bags import BagError, bag_status, score_bag
from process_helpers import alive, children, ddarm, interrupt, wait_for

LONG_EPISODE = ('episode', '--controller', 'computed_torque', '--omega', '15', '--realtime', '--duration', '60',
                '--json')


def started_episode(tmp_path):
    """A long real-time episode through the graph, once its bag is open (so its nodes run and it records)."""
    process = ddarm(*LONG_EPISODE, '--bag', str(tmp_path / 'bag'))
    wait_for(lambda: (tmp_path / 'bag').exists() or process.poll() is not None, 120, 'the bag opened')
    assert process.poll() is None, process.communicate()[1]
    nodes = children(process.pid)
    assert len(nodes) == 2, 'the plant and the controller run as child processes'
    return process, nodes


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_an_episode_cleanly(tmp_path, signum):
    process, nodes = started_episode(tmp_path)
    err = interrupt(process, signum)
    assert process.returncode == 128 + signum, err
    assert 'Traceback' not in err and len(err.strip().splitlines()) == 1, err
    assert signal.Signals(signum).name in err
    wait_for(lambda: not any(alive(pid) for pid in nodes), 10, 'the node processes ended')
    assert bag_status(tmp_path / 'bag') == 'incomplete'
    with pytest.raises(BagError, match='marked incomplete'):
        score_bag(tmp_path / 'bag')


def test_no_node_outlives_a_killed_driver(tmp_path):
    process, nodes = started_episode(tmp_path)
    process.kill()
    process.wait()
    wait_for(lambda: not any(alive(pid) for pid in nodes), 10, 'the orphaned node processes ended')
    with pytest.raises(BagError, match='never closed'):
        score_bag(tmp_path / 'bag')


def test_a_stopped_search_prints_one_line_and_leaves_nothing_half_written(tmp_path):
    process = ddarm('tune', '--controller', 'computed_torque', '--index', '3.2', '--budget', '100000',
                    '--runs', str(tmp_path / 'runs'), '--run', 'stopped')
    first = process.stderr.readline()  # printed as the search starts
    assert first.startswith('searching'), first
    # The graph's nodes start while the search runs: they stop with it.
    wait_for(lambda: len(children(process.pid)) == 2 or process.poll() is not None, 60, 'the nodes started')
    nodes = children(process.pid)
    err = interrupt(process, signal.SIGINT)
    assert process.returncode == 130, err
    assert 'Traceback' not in err and 'stopped by SIGINT' in err
    assert not (tmp_path / 'runs' / 'stopped').exists()
    wait_for(lambda: not any(alive(pid) for pid in nodes), 10, 'the node processes ended')


def test_an_interrupted_reproduction_is_marked_interrupted(tmp_path):
    out = tmp_path / 'paper'
    process = ddarm('reproduce', '--quick', '--out', str(out))
    wait_for(lambda: (out / 'summary.json').exists() or process.poll() is not None, 60, 'the run folder')
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['status'] == 'running' and summary['pid'] == process.pid
    err = interrupt(process, signal.SIGTERM)
    assert process.returncode == 143 and 'Traceback' not in err, err
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['status'] == 'interrupted'
    assert not (out / 'REPORT.md').exists()


def _descendants(pid: int) -> set[int]:
    found, frontier = set(), {pid}
    while frontier:
        frontier = set().union(*(children(parent) for parent in frontier)) - found
        found |= frontier
    return found


@pytest.mark.parametrize('signum', [signal.SIGTERM, signal.SIGKILL])
def test_no_search_worker_or_node_outlives_a_stopped_or_killed_reproduction(tmp_path, signum):
    process = ddarm('reproduce', '--quick', '--jobs', '2', '--out', str(tmp_path / 'paper'))
    # The workers' server and its two workers, the plant and the first law's controller (and multiprocessing's
    # resource tracker): all started while the first searches run.
    wait_for(lambda: len(_descendants(process.pid)) >= 5 or process.poll() is not None, 60, 'the workers and nodes')
    assert process.poll() is None, process.communicate()[1]
    spawned = _descendants(process.pid)
    os.kill(process.pid, signum)
    _, err = process.communicate(timeout=60)
    assert process.returncode == (128 + signum if signum != signal.SIGKILL else -signum), err
    wait_for(lambda: not any(alive(pid) for pid in spawned), 20, 'every worker and node ended')
