"""`ddarm bench`: the batch engine at B episodes per call against one episode per call (`run_episode`), in episodes/s."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import time

import numpy as np

from ddarm.episodes.spec import EpisodeSpec

# Issue 5's reference case: computed torque with the ω = 15 rule, trajectory 1, T = 1 s, Δ = 0.01 s, delay 1.
REFERENCE = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, trajectory=1,
                        duration=1.0, period=0.01, delay=1)
# Each episode's gains are the reference's times exp(σ N(0, 1)), per gain.
GAIN_SPREAD = 0.2
# One episode per call pays the per-call costs B times over: a sample of them is enough for its rate.
SCALAR_EPISODES = 50


def perturbed_gains(episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The reference gains perturbed per episode (log-normal, seeded): kp and kv of shape (episodes, 3)."""
    rng = np.random.default_rng(seed)
    factors = np.exp(GAIN_SPREAD * rng.standard_normal((2, episodes, 3)))
    return np.array(REFERENCE.kp) * factors[0], np.array(REFERENCE.kv) * factors[1]


def peak_rss_mib() -> float:
    """This process's peak resident set size so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_bench(episodes: int, seed: int = 0, scalar_episodes: int = SCALAR_EPISODES,
              threads: int | None = None) -> dict:
    """Time `episodes` perturbed reference episodes in one batch call and the first `scalar_episodes` one by one.

    The first batch call of a process compiles the engine (or loads it from numba's cache): it
    runs on one episode before the timing and is reported as warmup_s.
    """
    # The engine pulls in numba: only this command pays for importing it.
    from ddarm.episodes.engine import run_episode, simulate_batch

    kp, kv = perturbed_gains(episodes, seed)
    threads = min(threads if threads is not None else len(os.sched_getaffinity(0)), episodes)
    started = time.perf_counter()
    simulate_batch(REFERENCE, kp[:1], kv[:1], threads=threads)
    warmup = time.perf_counter() - started
    started = time.perf_counter()
    batch = simulate_batch(REFERENCE, kp, kv, threads=threads)
    batch_time = time.perf_counter() - started
    compared = min(episodes, scalar_episodes)
    started = time.perf_counter()
    scalar = [run_episode(dataclasses.replace(REFERENCE, kp=kp[member], kv=kv[member])) for member in range(compared)]
    scalar_time = time.perf_counter() - started
    largest, disagreements = 0.0, 0
    for member, result in enumerate(scalar):
        for key, value in result.indices().items():
            largest = max(largest, abs(batch.indices(member)[key] - value) / abs(value))
        disagreements += int(bool(batch.diverged[member]) != bool(result.diverged[0]))
    return {
        'case': 'computed_torque, kp = 225, kv = 30, trajectory 1, T = 1 s, period 0.01 s, delay 1',
        'gain_spread': GAIN_SPREAD, 'seed': seed, 'substeps': REFERENCE.substeps,
        'B': episodes, 'threads': threads, 'diverged': int(batch.diverged.sum()),
        'batch_s': batch_time, 'batch_episodes_per_s': episodes / batch_time,
        'scalar_episodes': compared, 'scalar_s': scalar_time, 'scalar_episodes_per_s': compared / scalar_time,
        'ratio': (episodes / batch_time) / (compared / scalar_time),
        'max_rel_index_diff': largest, 'divergence_disagreements': disagreements,
        'warmup_s': warmup, 'peak_rss_mib': peak_rss_mib(),
    }


def _count(name: str):
    """An argparse type: a whole number in [1, batch.<name>]."""
    def parse(text: str) -> int:
        from ddarm.episodes import engine as batch

        largest = getattr(batch, name)
        value = int(text)
        if not 1 <= value <= largest:
            raise argparse.ArgumentTypeError(f'{value} is not in [1, {largest}]')
        return value
    return parse


def command_bench(args: argparse.Namespace) -> int:
    figures = run_bench(args.episodes, args.seed, args.scalar_episodes, args.threads)
    if args.json:
        print(json.dumps(figures))
        return 0
    print(f"ddarm bench: {figures['case']}; gains x exp({GAIN_SPREAD} N(0, 1)) per episode (seed "
          f"{figures['seed']}); {figures['substeps']} RK4 substeps")
    print(f"  batch engine : {figures['B']:6d} episodes in {figures['batch_s']:7.3f} s = "
          f"{figures['batch_episodes_per_s']:8.1f} episodes/s (one call; the first call, "
          f"{figures['warmup_s']:.2f} s of compiling or cache loading, not counted)")
    print(f"  scalar runner: {figures['scalar_episodes']:6d} episodes in {figures['scalar_s']:7.3f} s = "
          f"{figures['scalar_episodes_per_s']:8.1f} episodes/s (the first {figures['scalar_episodes']} "
          f"of the batch's episodes)")
    print(f"  ratio        : {figures['ratio']:.1f} x")
    print(f"  largest relative difference of I1, I2, I on the {figures['scalar_episodes']} episodes both ran: "
          f"{figures['max_rel_index_diff']:.2e}; divergence flags disagree on "
          f"{figures['divergence_disagreements']}")
    print(f"  peak RSS     : {figures['peak_rss_mib']:.0f} MiB")
    return 0


def add_bench_parser(commands) -> None:
    """Register `ddarm bench` on the `ddarm` command's subparsers."""
    bench = commands.add_parser('bench', help='episodes per second of the batch engine and the scalar runner')
    bench.add_argument('--episodes', type=_count('MAX_BATCH'), default=1000, metavar='N',
                       help='episodes in the batch (1000)')
    bench.add_argument('--scalar-episodes', type=_count('MAX_BATCH'), default=SCALAR_EPISODES, metavar='M',
                       help=f'of them, how many the scalar runner also runs ({SCALAR_EPISODES})')
    bench.add_argument('--seed', type=int, default=0, help='seed of the gain perturbation (0)')
    bench.add_argument('--threads', type=_count('MAX_THREADS'), metavar='T',
                       help='threads of the batch engine (the cores available)')
    bench.add_argument('--json', action='store_true', help='print one JSON object')
    bench.set_defaults(handler=command_bench)
