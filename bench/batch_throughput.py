"""Figures for the batch engine (issue 5): episodes/s against B and threads, one episode per call, memory, searches.

    .venv/bin/python bench/batch_throughput.py [--memory-batches 100] [--json]

Prints (a) batch episodes/s of the reference case at several B, on all cores and on one;
(b) `ddarm bench`'s comparison with one episode per call (`run_episode`); (c) what Pinocchio's abaInParallel
over a ModelPool would take for the same accelerations, the alternative the engine was
measured against; (d) the peak RSS before and after many batches of 1,000 (flat memory);
(e) the wall time of a small CMA-ES and Nelder-Mead search.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import pinocchio as pin

from ddarm.episodes.engine import simulate_batch
from ddarm.episodes.bench import REFERENCE, peak_rss_mib, perturbed_gains, run_bench
from ddarm.episodes.spec import EpisodeSpec
from ddarm.physics.arm import load_arm
from ddarm.tuning.search import omega_starts, search_gains


def throughput(sizes, threads) -> dict:
    """Batch episodes/s of the reference case at each B (the best of three calls)."""
    rates = {}
    for size in sizes:
        kp, kv = perturbed_gains(REFERENCE, size, seed=1)
        best = np.inf
        for _ in range(3):
            started = time.perf_counter()
            simulate_batch(REFERENCE, kp, kv, threads=threads)
            best = min(best, time.perf_counter() - started)
        rates[size] = size / best
    return rates


def pinocchio_pool_stage(size: int = 1000, calls: int = 200) -> dict:
    """abaInParallel over column-stacked states: one RK4 stage of `size` members, and the episode rate it caps."""
    model = load_arm(None).model
    threads = len(os.sched_getaffinity(0))
    pool = pin.ModelPool(model, threads)
    rng = np.random.default_rng(0)
    q, v, tau = (np.asfortranarray(rng.standard_normal((model.nq, size))) for _ in range(3))
    a = np.zeros((model.nv, size), order='F')
    pin.abaInParallel(threads, pool, q, v, tau, a)
    started = time.perf_counter()
    for _ in range(calls):
        pin.abaInParallel(threads, pool, q, v, tau, a)
    stage = (time.perf_counter() - started) / calls
    stages = (REFERENCE.duration / REFERENCE.period) * REFERENCE.substeps * 4
    return {'stage_s': stage, 'stages_per_episode': stages, 'episodes_per_s_cap': size / (stage * stages)}


def memory(batches: int, size: int = 1000) -> dict:
    """Peak RSS after one batch of `size` and after `batches` more: flat if the engine keeps nothing."""
    kp, kv = perturbed_gains(REFERENCE, size, seed=2)
    simulate_batch(REFERENCE, kp, kv)
    before = peak_rss_mib()
    started = time.perf_counter()
    for _ in range(batches):
        simulate_batch(REFERENCE, kp, kv)
    return {'batches': batches, 'size': size, 'peak_rss_before_mib': before, 'peak_rss_after_mib': peak_rss_mib(),
            'episodes_per_s': batches * size / (time.perf_counter() - started)}


def searches(budget: int = 1000) -> dict:
    """Wall time of I (3.2) searches of computed torque from the ω = 5, 10, 15, 20 rules."""
    template = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, delay=1)
    kp, kv = omega_starts(template, [5.0, 10.0, 15.0, 20.0])
    figures = {}
    for method in ('cma', 'nelder-mead'):
        started = time.perf_counter()
        result = search_gains(template, index='I', start_kp=kp, start_kv=kv, budget=budget, method=method, seed=0)
        figures[method] = {'wall_s': time.perf_counter() - started, 'episodes': result.episodes,
                           'batches': result.batches, 'index': result.index,
                           'best_start': float(np.min(simulate_batch(template, kp, kv).I))}
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--memory-batches', type=int, default=100)
    parser.add_argument('--json', action='store_true')
    args = parser.parse_args()
    figures = {'bench': run_bench(1000)}
    figures['batch_episodes_per_s'] = throughput([1, 10, 100, 1000, 4000], threads=None)
    figures['batch_episodes_per_s_one_thread'] = throughput([1, 100, 1000], threads=1)
    figures['pinocchio_pool'] = pinocchio_pool_stage()
    figures['memory'] = memory(args.memory_batches)
    figures['searches'] = searches()
    if args.json:
        print(json.dumps(figures))
        return
    bench = figures['bench']
    print(f"reference case, {bench['substeps']} substeps, {len(os.sched_getaffinity(0))} cores")
    print('batch episodes/s by B (all cores): '
          + ', '.join(f'B={size}: {rate:.0f}' for size, rate in figures['batch_episodes_per_s'].items()))
    print('batch episodes/s by B (1 thread) : '
          + ', '.join(f'B={size}: {rate:.0f}' for size, rate in figures['batch_episodes_per_s_one_thread'].items()))
    print(f"ddarm bench: batch {bench['batch_episodes_per_s']:.0f}/s, scalar {bench['scalar_episodes_per_s']:.1f}/s "
          f"({bench['scalar_episodes']} episodes), ratio {bench['ratio']:.1f}, "
          f"max rel index diff {bench['max_rel_index_diff']:.1e}, first call {bench['warmup_s']:.2f} s")
    pool = figures['pinocchio_pool']
    print(f"abaInParallel, 1000 states: {pool['stage_s'] * 1e3:.2f} ms a stage x {pool['stages_per_episode']:.0f} "
          f"stages = at most {pool['episodes_per_s_cap']:.0f} episodes/s before any other work")
    mem = figures['memory']
    print(f"memory: peak RSS {mem['peak_rss_before_mib']:.0f} MiB after one batch of {mem['size']}, "
          f"{mem['peak_rss_after_mib']:.0f} MiB after {mem['batches']} more ({mem['episodes_per_s']:.0f} episodes/s)")
    for method, search in figures['searches'].items():
        print(f"search {method}: {search['episodes']} episodes in {search['batches']} batches, "
              f"{search['wall_s']:.1f} s; I {search['best_start']:.4f} at the best start -> {search['index']:.4f}")


if __name__ == '__main__':
    main()
