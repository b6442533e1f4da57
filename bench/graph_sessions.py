"""Benchmark: the reproduction's reported episodes through 1 graph session and through N, side by side.

The searches run once first (a quick budget, or --full); then every reported episode (Tables 2-4, section 2,
the robust rows, the stability rows) runs through the ROS graph, recorded and scored from its bag, with 1
session and with N, alternately, and the rows of each run must be equal. Prints JSON: each run's wall time
the speed-up, and how many of the machine's cores were busy meanwhile (/proc/stat). Run from the repository:
    .venv/bin/python bench/graph_sessions.py [--sessions 2] [--rounds 2] [--full]
"""

import argparse
import contextlib
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

from ddarm.paper.experiments import Reproduction
from ddarm.paper.settings import Budget
from ddarm.ros.session import GraphSession
from ddarm.ros.session_process import SessionProcess

COMMAND = 'bench/graph_sessions.py'


def cpu_times() -> tuple[int, int]:
    """(busy, total) jiffies of every core of the machine so far (/proc/stat)."""
    values = [int(value) for value in Path('/proc/stat').read_text().split('\n')[0].split()[1:]]
    idle = values[3] + values[4]  # idle, iowait
    return sum(values) - idle, sum(values)


class Found:
    """The searches' results, all done: what BackgroundJobs gives once every search has ended."""

    def __init__(self, found: dict) -> None:
        self.found, self.labels = found, {key: str(key) for key in found}

    def ready(self, keys) -> bool:
        return True

    def wait(self, keys=None) -> dict:
        return dict(self.found) if keys is None else {key: self.found[key] for key in keys}

    def wait_for_change(self) -> None:
        pass


def rows(results) -> list:
    """Every reported row, without the bag's path (each run writes its own folder)."""
    return [dataclasses.replace(row, bag=None) for table in (
        results.table2, results.table3, results.table4, results.section2.omega_rules, results.robust.rows,
        results.section2.stability) for row in table]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--sessions', type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument('--rounds', type=int, default=2)
    parser.add_argument('--full', action='store_true', help="the paper's budgets and τ values (else --quick's)")
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    budget = Budget.full() if args.full else Budget.quick()
    with tempfile.TemporaryDirectory(prefix='ddarm-sessions-') as folder:
        folder = Path(folder)
        with Reproduction(folder, budget, COMMAND).start_searches(len(os.sched_getaffinity(0))) as searches:
            found = searches.wait()
        runs, reference = [], None
        for round_number in range(args.rounds):
            for count in (1, args.sessions):
                out = folder / f'{count}-sessions-{round_number}'
                (out / 'bags').mkdir(parents=True)
                reproduction = Reproduction(out, budget, COMMAND)
                with contextlib.ExitStack() as stack:
                    kind = GraphSession if count == 1 else SessionProcess
                    sessions = [stack.enter_context(kind(out / 'nodes' / str(number))) for number in range(count)]
                    for session in sessions:  # the nodes up before the clock starts
                        session.record_and_score(reproduction.first_episode(), out / f'warm-up-{id(session)}')
                    started, (busy, total) = time.perf_counter(), cpu_times()
                    reproduction.run_episodes(sessions if count > 1 else sessions[0], Found(found))
                    wall = time.perf_counter() - started
                    busy_after, total_after = cpu_times()
                episodes = len(list((out / 'bags').glob('*/metadata.yaml')))
                reference = reference or rows(reproduction.results)
                if rows(reproduction.results) != reference:
                    raise SystemExit(f'{count} sessions gave other rows than the first run')
                runs.append({'sessions': count, 'round': round_number, 'episodes': episodes, 'wall_time_s': wall,
                             'episodes_per_s': episodes / wall,
                             'cores_busy': (busy_after - busy) / (total_after - total) * os.cpu_count()})
    one = [run['wall_time_s'] for run in runs if run['sessions'] == 1]
    many = [run['wall_time_s'] for run in runs if run['sessions'] == args.sessions]
    print(json.dumps({'budget': 'full' if args.full else 'quick', 'runs': runs,
                      'speed_up_per_round': [a / b for a, b in zip(one, many)]}, indent=2))


if __name__ == '__main__':
    main()
