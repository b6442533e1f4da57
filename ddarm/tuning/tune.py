"""`ddarm tune`: gains optimised in-process through the batch engine, then checked once through the ROS graph."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning.search import SearchResult, omega_starts, search_gains


@dataclass(frozen=True)
class Tuning:
    """A finished search: its result, where it started, how long it took, and the best gains re-run alone."""

    search: SearchResult
    start_omegas: tuple
    start_indices: list  # the index of each ω-rule start
    wall_time_s: float
    best: dict  # the indices of the best gains, re-run as one episode
    warnings: tuple[str, ...] = ()  # the motion against the URDF's limits

    @property
    def episodes_per_s(self) -> float:
        return self.search.episodes / self.wall_time_s


def tune(template: EpisodeSpec, index: str, method: str, budget: int, omegas=SEARCH_START_OMEGAS,
         seed: int = 0) -> Tuning:
    """Minimise `index` (I1, I2 or I) from the ω-rule gains at each ω of `omegas`; the best gains re-run alone."""
    start_kp, start_kv = omega_starts(template, omegas)
    start_indices = [run_episode(with_gains(template, kp, kv)).indices()[index]
                     for kp, kv in zip(start_kp, start_kv)]
    started = time.perf_counter()
    result = search_gains(template, index=index, start_kp=start_kp, start_kv=start_kv, budget=budget,
                          method=method, seed=seed)
    wall = time.perf_counter() - started
    episode = run_episode(with_gains(template, result.kp, result.kv))
    return Tuning(result, tuple(float(w) for w in omegas), start_indices, wall, episode.indices(),
                  episode.plan.warnings)


def with_gains(template: EpisodeSpec, kp, kv) -> EpisodeSpec:
    """The template with these gains."""
    return replace(template, kp=tuple(np.asarray(kp, dtype=float)), kv=tuple(np.asarray(kv, dtype=float)))
