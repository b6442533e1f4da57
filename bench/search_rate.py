"""The default search's own episodes/s against the engine's batch rate on the same episode (issue 37), and its wall
time, for `ddarm tune`'s default searches of the paper's arm.

    .venv/bin/python bench/search_rate.py [--rounds 3]
    PYTHONPATH=<checkout of another commit> .venv/bin/python bench/search_rate.py   # the same for that code

Each round runs, for computed torque (I1) and PD + gravity (I) on the paper's default episode, the global search with
`ddarm tune`'s default budget, then `ddarm bench`'s batch (1000 episodes around the gains found) right after it, so
that both rates see the same load; it prints the wall time, the episodes, the batch calls, the search's episodes/s,
the batch rate and their ratio, and the median of the rounds. Run two checkouts alternately to compare them: the
machine's load moves both rates by 20 % from one minute to the next.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.episodes.bench import BENCH_EPISODES, batch_rates
from ddarm.episodes.engine import warm_up
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning.search import omega_starts, search_gains

CASES = (('computed_torque', 'I1'), ('pd_gravity', 'I'))
DEFAULT_BUDGET = 100_000  # ddarm tune's


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rounds', type=int, default=3)
    options = parser.parse_args()
    warm_up()
    for controller, index in CASES:
        template = EpisodeSpec(controller=controller)
        kp, kv = omega_starts(template, SEARCH_START_OMEGAS)
        rows = []
        for _ in range(options.rounds):
            started = time.perf_counter()
            result = search_gains(template, index=index, start_kp=kp, start_kv=kv, budget=DEFAULT_BUDGET)
            wall = time.perf_counter() - started
            batch = batch_rates(template.with_gains(result.kp, result.kv), (BENCH_EPISODES,), rounds=1)[0]
            rows.append((wall, result.episodes / wall, batch['episodes_per_s']))
            print(f'{controller} {index}: {wall:.2f} s, {result.episodes} episodes in {result.batches} batch calls, '
                  f'{rows[-1][1]:.0f} episodes/s against a batch rate of {rows[-1][2]:.0f} '
                  f'({rows[-1][1] / rows[-1][2]:.2f}); index {result.index:.9g}, converged {result.converged}',
                  flush=True)
        wall, rate, batch_rate = np.median(np.array(rows), axis=0)
        ratio = np.median([row[1] / row[2] for row in rows])
        print(f'{controller} {index}, median of {len(rows)}: {wall:.2f} s, {rate:.0f} episodes/s, '
              f'batch {batch_rate:.0f}, ratio {ratio:.2f}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
