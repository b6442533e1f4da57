"""The default search's own episodes/s against the engine's batch rate on the same episode (issue 37), and its wall
time, for `ddarm tune`'s default searches of the paper's arm.

    .venv/bin/python bench/search_rate.py [--rounds 3]
    PYTHONPATH=<checkout of another commit> .venv/bin/python bench/search_rate.py   # the same for that code

Each round runs, for computed torque (I1) and PD + gravity (I) on the paper's default episode, the global search with
`ddarm tune`'s default budget, then `ddarm bench`'s batch (1000 episodes around the gains found) right after it, so
that both rates see the same load; it prints the wall time, the episodes, the batch calls, the search's episodes/s,
the batch rate and their ratio, and the median of the rounds. Run two checkouts alternately to compare them: the
machine's load moves both rates by 20 % from one minute to the next.

It also times the engine's batch calls inside the search, and prints what the search would reach if everything
outside them (the optimisers, the scheduling) took no time: its episodes over the engine's time, against the batch
rate. That ceiling is set by the sizes of the batches the search's runs ask for, not by Python: for each case it
also prints the engine's calls split by their batch size (B), with the episodes/s the engine ran each group at
(summed over the rounds), beside the batch rate at B = 1000.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.episodes.bench import BENCH_EPISODES, batch_rates
from ddarm.episodes.engine import BatchRunner, warm_up
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning.search import omega_starts, search_gains

from batch_overhead import Timed

CASES = (('computed_torque', 'I1'), ('pd_gravity', 'I'))
DEFAULT_BUDGET = 100_000  # ddarm tune's
# The batch sizes the engine's calls are grouped by: one member alone, a few, one SIMD vector, two threads' vectors.
SIZE_EDGES = (1, 2, 8, 9, 16, 32, 64, 128)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rounds', type=int, default=3)
    options = parser.parse_args()
    warm_up()
    engine, sizes = Timed(BatchRunner.__call__), []

    def batch_call(runner, kp, *arguments, **keywords):
        sizes.append(len(kp))
        return engine(runner, kp, *arguments, **keywords)

    BatchRunner.__call__ = batch_call
    for controller, index in CASES:
        template = EpisodeSpec(controller=controller)
        kp, kv = omega_starts(template, SEARCH_START_OMEGAS)
        rows, calls = [], []
        for _ in range(options.rounds):
            engine.seconds, engine.durations, sizes[:] = 0.0, [], []
            started = time.perf_counter()
            result = search_gains(template, index=index, start_kp=kp, start_kv=kv, budget=DEFAULT_BUDGET)
            wall, engine_seconds = time.perf_counter() - started, engine.seconds
            calls += zip(sizes, engine.durations)
            batch = batch_rates(template.with_gains(result.kp, result.kv), (BENCH_EPISODES,), rounds=1)[0]
            rows.append((wall, result.episodes / wall, batch['episodes_per_s'], engine_seconds))
            print(f'{controller} {index}: {wall:.2f} s ({engine_seconds:.2f} s in the engine), {result.episodes} '
                  f'episodes in {result.batches} batch calls, {rows[-1][1]:.0f} episodes/s against a batch rate of '
                  f'{rows[-1][2]:.0f} ({rows[-1][1] / rows[-1][2]:.2f}; with no time outside the engine '
                  f'{result.episodes / engine_seconds / rows[-1][2]:.2f}); index {result.index:.9g}, '
                  f'converged {result.converged}', flush=True)
        wall, rate, batch_rate, engine_seconds = np.median(np.array(rows), axis=0)
        ratio = np.median([row[1] / row[2] for row in rows])
        ceiling = np.median([row[1] * row[0] / row[3] / row[2] for row in rows])
        print(f'{controller} {index}, median of {len(rows)}: {wall:.2f} s ({engine_seconds:.2f} s in the engine), '
              f'{rate:.0f} episodes/s, batch {batch_rate:.0f}, ratio {ratio:.2f}, with no time outside the engine '
              f'{ceiling:.2f}')
        print_by_size(np.array(calls), batch_rate)
    return 0


def print_by_size(calls: np.ndarray, batch_rate: float) -> None:
    """The engine's calls (rows of B and seconds) grouped by B: calls, episodes, seconds, episodes/s and its ratio to
    `batch_rate`."""
    print(f"{'B':>9} {'calls':>7} {'episodes':>9} {'seconds':>8} {'episodes/s':>11} {'of the batch rate':>18}")
    for low, high in zip(SIZE_EDGES, SIZE_EDGES[1:] + (np.inf,)):
        group = calls[(calls[:, 0] >= low) & (calls[:, 0] < high)]
        if len(group):
            episodes, seconds = group[:, 0].sum(), group[:, 1].sum()
            sizes = f'{low}-{high - 1:.0f}' if np.isfinite(high) else f'{low}-'
            print(f'{sizes:>9} {len(group):>7} {episodes:>9.0f} {seconds:>8.2f} {episodes / seconds:>11.0f} '
                  f'{episodes / seconds / batch_rate:>18.2f}')


if __name__ == '__main__':
    raise SystemExit(main())
