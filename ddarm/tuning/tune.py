"""`ddarm tune`: gains optimised in-process through the batch engine, then checked once through the ROS graph."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.episodes.bench import BENCH_EPISODES, batch_rates
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning.robust import ScenarioScores, scenario_record, scenario_scores
from ddarm.tuning.search import SearchError, SearchResult, check_search, omega_starts, search_gains


@dataclass(frozen=True)
class Robustness:
    """A robust search set beside the nominal one: both searches' gains scored on every scenario.

    `chosen` are the robust search's gains, `nominal_optimum` those of the same search on the template alone
    (`nominal_search`, which took `nominal_wall_time_s` seconds).
    """

    scenarios: tuple[EpisodeSpec, ...]
    aggregate: str  # 'worst' or 'mean'
    chosen: ScenarioScores
    nominal_optimum: ScenarioScores
    nominal_search: SearchResult
    nominal_wall_time_s: float

    def to_dict(self) -> dict:
        """The JSON of `ddarm tune`'s `robust`: the objective, the scenarios, both gain sets on each."""
        dof = len(self.chosen.kp)
        index = self.nominal_search.index
        return {'objective': self.aggregate, 'scenarios': [scenario_record(s, dof) for s in self.scenarios],
                'chosen': self.chosen.to_dict(), 'nominal_optimum': self.nominal_optimum.to_dict(),
                'nominal_search': {'episodes': self.nominal_search.episodes, 'batches': self.nominal_search.batches,
                                   'wall_time_s': self.nominal_wall_time_s,
                                   'index': float(index) if np.isfinite(index) else None,
                                   **self.nominal_search.certainty_fields()}}


@dataclass(frozen=True)
class Tuning:
    """A finished search: its result, where it started, how long it took, and the best gains re-run alone.

    With scenarios, `search` is the robust search and `best` its gains' nominal episode (the template's).
    """

    search: SearchResult
    start_omegas: tuple
    start_indices: list  # the index of each ω-rule start
    wall_time_s: float
    best: dict  # the indices of the best gains, re-run as one episode
    warnings: tuple[str, ...] = ()  # the motion against the URDF's limits
    robust: Robustness | None = None
    batch_episodes_per_s: float | None = None  # `ddarm bench`'s batch rate on the same episode, if measured

    @property
    def episodes_per_s(self) -> float:
        return self.search.episodes / self.wall_time_s


def tune(template: EpisodeSpec, index: str, method: str, budget: int, omegas=SEARCH_START_OMEGAS,
         seed: int = 0, progress=None, scenarios: tuple[EpisodeSpec, ...] | None = None,
         aggregate: str = 'worst', measure_batch_rate: bool = False) -> Tuning:
    """Minimise `index` (I1, I2 or I) from the ω-rule gains at each ω of `omegas`; the best gains re-run alone.

    With `scenarios` (ddarm.tuning.robust.scenario_grid), the `aggregate` ('worst' or 'mean') of the index over
    them is minimised, within `budget` episodes, after the same search (method, budget, seed) on the template
    alone: its optimum is one more start of the robust search, so the robust gains' aggregate is never worse
    than the nominal optimum's. `progress(episodes so far, best index so far or None)` is called after each
    batch of the search that `search` holds (the robust one, with scenarios). `measure_batch_rate` also times
    `ddarm bench`'s batch (1000 episodes around the best gains) after the search, for its episodes/s to be read
    against.
    """
    check_tune(template, index, method, budget, omegas, scenarios, aggregate)
    start_kp, start_kv = omega_starts(template, omegas)
    search = dict(index=index, budget=budget, method=method)
    start_indices = [run_episode(template.with_gains(kp, kv)).indices()[index]
                     for kp, kv in zip(start_kp, start_kv)]
    if scenarios is not None:
        nominal, nominal_wall = _timed_search(template, start_kp=start_kp, start_kv=start_kv, seed=seed, **search)
        start_kp, start_kv = np.vstack([start_kp, nominal.kp]), np.vstack([start_kv, nominal.kv])
    result, wall = _timed_search(template, start_kp=start_kp, start_kv=start_kv, seed=seed, progress=progress,
                                 scenarios=scenarios, aggregate=aggregate, **search)
    if not np.isfinite(result.index):
        raise SearchError(f'every gain set the search evaluated diverged{" in some scenario" if scenarios else ""} '
                          f'({result.episodes} episodes): no gains to report; check the episode (limits, '
                          'disturbances) or give start gains nearer a stable loop (--omegas)')
    robust = None if scenarios is None else Robustness(
        tuple(scenarios), aggregate, scenario_scores(scenarios, result.kp, result.kv, index),
        scenario_scores(scenarios, nominal.kp, nominal.kv, index), nominal, nominal_wall)
    best = template.with_gains(result.kp, result.kv)
    episode = run_episode(best)
    warnings = episode.plan.warnings
    if method == 'global' and result.evolution_generations == 0:
        warnings += (f'the budget ({budget} episodes{f" over {len(scenarios)} scenarios" if scenarios else ""}) left '
                     'no room for differential evolution: only local runs from the starts searched, so better '
                     'basins may have been missed; raise --budget',)
    rate = None
    if measure_batch_rate:
        rate = batch_rates(best, (BENCH_EPISODES,), rounds=1)[0]['episodes_per_s']
    return Tuning(result, tuple(float(w) for w in omegas), start_indices, wall, episode.indices(), warnings, robust,
                  rate)


def check_tune(template: EpisodeSpec, index: str, method: str, budget: int, omegas=SEARCH_START_OMEGAS,
               scenarios: tuple[EpisodeSpec, ...] | None = None, aggregate: str = 'worst') -> None:
    """Refuse, with SearchError naming the argument, a tuning that tune (same arguments) cannot run; no episode run."""
    start_kp, start_kv = omega_starts(template, omegas)
    if scenarios is not None:
        # The robust search's starts: the first stands in for the nominal optimum, not known yet.
        start_kp, start_kv = np.vstack([start_kp, start_kp[:1]]), np.vstack([start_kv, start_kv[:1]])
    check_search(template, index=index, start_kp=start_kp, start_kv=start_kv, budget=budget, method=method,
                 scenarios=scenarios, aggregate=aggregate)


def _timed_search(template: EpisodeSpec, **arguments) -> tuple[SearchResult, float]:
    """search_gains and its wall time in s."""
    started = time.perf_counter()
    result = search_gains(template, **arguments)
    return result, time.perf_counter() - started
