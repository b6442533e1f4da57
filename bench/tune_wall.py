"""`ddarm tune`'s whole wall time, from the command to its answer, beside its search's own, for the paper's default
computed torque (I1) tuning; optionally alternating with another checkout run the same way.

    .venv/bin/python bench/tune_wall.py [--rounds 3] [--other PATH]

Each round runs `ddarm tune --controller computed_torque --index I1 --json` (in a temporary folder, on a ROS domain
of its own) as a new process: the imports, the search, the best gains' episode through the ROS graph (node processes
started, the episode recorded and scored from its bag), the report. With --other, each round first runs the same
command with PYTHONPATH=PATH (a checkout of another commit: `git worktree add /tmp/before <commit>`), so that both see
the same load; the machine's load moves the times by 10 % from one minute to the next. Prints each run's total and
search seconds and their medians.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

COMMAND = ['tune', '--controller', 'computed_torque', '--index', 'I1', '--json']


def timed_tune(folder: str, pythonpath: str | None) -> tuple[float, float]:
    """The wall time of one `ddarm tune` process, and its search's (the JSON's wall_time_s)."""
    environment = dict(os.environ)
    environment.pop('PYTHONPATH', None)
    if pythonpath is not None:
        environment['PYTHONPATH'] = pythonpath
    started = time.perf_counter()
    # Run in `folder`: with -c the working directory comes first on sys.path, before PYTHONPATH.
    done = subprocess.run([sys.executable, '-c', 'import sys; from ddarm.cli.main import main; sys.exit(main())',
                           *COMMAND], cwd=folder, env=environment, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - started
    return wall, json.loads(done.stdout)['wall_time_s']


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--other', help='a checkout to alternate with (PYTHONPATH)')
    options = parser.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(200 + os.getpid() % 30))
    codes = ([('other', options.other)] if options.other else []) + [('this', None)]
    rows: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in codes}
    with tempfile.TemporaryDirectory(prefix='ddarm-tune-wall-') as folder:
        for _ in range(options.rounds):
            for label, path in codes:
                rows[label].append(timed_tune(folder, path))
                total, search = rows[label][-1]
                print(f'{label}: ddarm tune {total:.2f} s, of which the search {search:.2f} s', flush=True)
    for label, _ in codes:
        total, search = np.median(np.array(rows[label]), axis=0)
        print(f'{label}, median of {len(rows[label])}: ddarm tune {total:.2f} s, the search {search:.2f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
