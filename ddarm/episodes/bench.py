"""`ddarm bench`: the batch engine at B episodes per call against one per call (`run_episode`), in episodes/s."""

from __future__ import annotations

import dataclasses
import os
import resource
import time

import numpy as np

from ddarm.episodes.engine import run_episode, simulate_batch
from ddarm.episodes.spec import EpisodeSpec, check_episode, gains_from_omega

# Issue 5's reference case: computed torque with the ω = 15 rule, trajectory 1, T = 1 s, Δ = 0.01 s, delay 1.
REFERENCE = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, trajectory=1,
                        duration=1.0, period=0.01, delay=1)
# Each episode's gains are the reference's times exp(σ N(0, 1)), per gain.
GAIN_SPREAD = 0.2
# `ddarm bench`'s batch by default: the rate a search's episodes/s is read against.
BENCH_EPISODES = 1000
# One episode per call pays the per-call costs B times over: a sample of them is enough for its rate.
SCALAR_EPISODES = 50
# A CMA-ES population, a DE generation, a large batch.
BATCH_SIZES = (8, 64, 1000)
# The arm of many joints `ddarm bench` also runs: Franka Panda's 7 (config/arms/panda).
MANY_JOINT_ARM = ('arms', 'panda', 'panda.urdf'), ('arms', 'panda', 'panda-motion.yaml')


def reference_case(urdf: str | None = None, motion: str | None = None) -> EpisodeSpec:
    """The reference case on another arm and motion: computed torque with the ω = 15 rule, delay 1, Δ = 0.01 s,
    T the motion's."""
    if urdf is None and motion is None:
        return REFERENCE
    spec = dataclasses.replace(REFERENCE, urdf=urdf, motion=motion, duration=None)
    return dataclasses.replace(spec, **dict(zip(('kp', 'kv'), gains_from_omega(spec, 15.0))))


def perturbed_gains(template: EpisodeSpec, episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The template's gains perturbed per episode (log-normal, seeded): kp and kv of shape (episodes, n)."""
    rng = np.random.default_rng(seed)
    factors = np.exp(GAIN_SPREAD * rng.standard_normal((2, episodes, len(template.kp))))
    return np.array(template.kp) * factors[0], np.array(template.kv) * factors[1]


def peak_rss_mib() -> float:
    """This process's peak resident set size so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_bench(episodes: int, seed: int = 0, scalar_episodes: int = SCALAR_EPISODES,
              threads: int | None = None, template: EpisodeSpec = REFERENCE) -> dict:
    """Time `episodes` perturbed `template` episodes in one batch call and the first `scalar_episodes` one by one.

    The first batch call of a process compiles the engine (or loads it from numba's cache): it
    runs on one episode before the timing and is reported as warmup_s.
    """
    kp, kv = perturbed_gains(template, episodes, seed)
    plan = check_episode(template)
    threads = min(threads if threads is not None else len(os.sched_getaffinity(0)), episodes)
    started = time.perf_counter()
    simulate_batch(template, kp[:1], kv[:1], plan=plan, threads=threads)
    warmup = time.perf_counter() - started
    started = time.perf_counter()
    batch = simulate_batch(template, kp, kv, plan=plan, threads=threads)
    batch_time = time.perf_counter() - started
    compared = min(episodes, scalar_episodes)
    started = time.perf_counter()
    alone = [run_episode(dataclasses.replace(template, kp=kp[member], kv=kv[member]), plan)
             for member in range(compared)]
    alone_time = time.perf_counter() - started
    largest, disagreements = 0.0, 0
    for member, result in enumerate(alone):
        for key, value in result.indices().items():
            largest = max(largest, abs(batch.indices(member)[key] - value) / abs(value))
        disagreements += int(bool(batch.diverged[member]) != bool(result.diverged[0]))
    return {
        'case': (f'computed_torque, kp = 225, kv = 30, {template.motion or f"trajectory {template.trajectory}"}, '
                 f'T = {template.duration:g} s, period {template.period} s, delay {template.delay}'),
        'urdf': template.urdf, 'motion': template.motion, 'joints': len(template.kp),
        'gain_spread': GAIN_SPREAD, 'seed': seed, 'substeps': template.substeps,
        'B': episodes, 'threads': threads, 'diverged': int(batch.diverged.sum()),
        'batch_s': batch_time, 'batch_episodes_per_s': episodes / batch_time,
        'scalar_episodes': compared, 'scalar_s': alone_time, 'scalar_episodes_per_s': compared / alone_time,
        'ratio': (episodes / batch_time) / (compared / alone_time),
        'max_rel_index_diff': largest, 'divergence_disagreements': disagreements,
        'warmup_s': warmup, 'peak_rss_mib': peak_rss_mib(),
    }



def batch_rates(template: EpisodeSpec, sizes=BATCH_SIZES, seed: int = 0, threads: int | None = None,
                rounds: int = 3) -> list[dict]:
    """Batch episodes/s of `template` at each B (the best of `rounds` calls; the first call compiles or loads the
    compiled code and is not timed)."""
    plan = check_episode(template)
    kp, kv = perturbed_gains(template, max(sizes), seed)
    simulate_batch(template, kp[:1], kv[:1], plan=plan, threads=threads)
    rates = []
    for size in sizes:
        best = float('inf')
        for _ in range(rounds):
            started = time.perf_counter()
            simulate_batch(template, kp[:size], kv[:size], plan=plan, threads=threads)
            best = min(best, time.perf_counter() - started)
        rates.append({'B': size, 'episodes_per_s': size / best})
    return rates
