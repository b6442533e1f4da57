"""Optimisation of the indices I1 (2.5), I2 or I (3.2) over the 2n diagonal gains (spec §9), through the batch engine.

Every method searches x = (log k_p, log k_v), so every point is a valid positive gain and a
step means the same relative change for a large and a small gain. Every evaluation of an
iteration (a CMA-ES population; the moves of all Nelder-Mead starts) is one batch call.

`global` (the default of `ddarm tune` and `ddarm reproduce`) is differential evolution (scipy's)
over a box around the ω-rule gains, its population one batch per generation, then local CMA-ES
runs (the `cma` package) from its best distinct members, side by side in one batch. Each local
run's best index is kept, so a user can read how many of them reached the reported minimum
(`restarts_within`): a confidence figure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ddarm.errors import DdarmError
from ddarm.episodes.indices import INDICES
from ddarm.episodes.spec import EpisodeSpec, arm_joints, gains_from_omega
from ddarm.interrupts import check_stop
from ddarm.tuning.methods import METHODS
from ddarm.tuning.robust import AGGREGATES, scenario_batches

# A diverged episode is scored on the samples before its divergence, which can be few and
# score low: an optimiser sees DIVERGED_PENALTY x (2 - scored fraction) instead, far beyond
# any index of an episode whose state stayed within the plant's bounds, and worse the earlier
# it diverged (so CMA-ES still ranks diverged points among themselves).
DIVERGED_PENALTY = 1e100
# Gains searched, in the units of k_p and k_v; a Nelder-Mead point outside is not simulated
# and scores 3 x DIVERGED_PENALTY, CMA-ES is kept inside by its own bound handling.
GAIN_RANGE = (1e-3, 1e9)
# Nelder-Mead stops a start once its simplex spans less than this in log gain (0.01 %) and
# its values agree to this relative tolerance.
NM_XTOL = 1e-4
NM_FTOL = 1e-10
# The global search's DE samples the box between the ω-rule gains at the smallest start ω divided by OMEGA_SPAN
# and at the largest times OMEGA_SPAN, each gain then spread by a factor e^{±GAIN_SPREAD}: every gain an ω rule
# could suggest, and off-rule ratios between k_p and k_v and between joints. Its local runs may leave the box.
OMEGA_SPAN = 2.0
GAIN_SPREAD = 1.5
# DE's population per dimension (scipy's popsize): 15 × 2n members, one batch call per generation. It stops
# early once its members' values agree within DE_TOL relative (scipy's tol), the rest going to the local runs.
DE_POPSIZE = 15
DE_TOL = 1e-3
# The global search's local CMA-ES runs: how many, from the best points seen at least DISTINCT apart in some log
# gain; their σ0, population and end (CMA_XTOL in log gain, or cma's own criteria); the share of the budget they
# get.
LOCAL_RUNS = 4
DISTINCT = 0.3
LOCAL_SIGMA = 0.01
LOCAL_POPSIZE = 16
CMA_XTOL = 1e-6
LOCAL_SHARE = 0.4
# A run counts as having found the best basin when its best index is within this fraction of the best.
SAME_BASIN = 0.01

class SearchError(DdarmError, ValueError):
    """A search specification that cannot be run."""


@dataclass(frozen=True)
class Restart:
    """One local CMA-ES run of the global search: where it started, its population, what it found, why it stopped."""

    start: str  # the point it started from: its rank among the points seen and its value
    popsize: int
    episodes: int
    index: float  # its best index, +inf if all its episodes diverged
    stopped_by: tuple[str, ...]  # cma's stop criteria, or ('budget',)


@dataclass(frozen=True)
class SearchResult:
    """The best gains found, and every episode evaluated on the way (in evaluation order).

    `index` is the best gains' value of the index named `index_name`, +inf if every episode diverged;
    history_index holds +inf for the diverged episodes. `batches` counts the batch calls. `restarts`
    are the global search's local CMA-ES runs (empty for the other methods).
    """

    method: str
    index_name: str
    kp: np.ndarray
    kv: np.ndarray
    index: float
    episodes: int
    batches: int
    history_kp: np.ndarray
    history_kv: np.ndarray
    history_index: np.ndarray
    history_batch: np.ndarray
    restarts: tuple[Restart, ...] = ()
    evolution_generations: int = 0  # the global search's DE generations; 0: the budget left no room for DE

    def best_so_far(self) -> np.ndarray:
        """The best index after each episode: the optimiser's progress."""
        return np.minimum.accumulate(self.history_index)

    def restarts_within(self, fraction: float = SAME_BASIN) -> int:
        """How many local runs reached within `fraction` of the best index: a confidence figure (0 without them)."""
        return sum(1 for restart in self.restarts if restart.index <= (1.0 + fraction) * self.index)


class _Objective:
    """The index of a batch of log-gain points, aggregated over the scenarios; keeps the history and the best point.

    Each point is evaluated on every scenario: the scenarios that differ only in τ and plant mass scale share
    one batch call (the engine varies both per member), the others (another P^z, say) one call each. A point's
    value is the worst (max) or the mean of its scenarios' indices, or, if it diverged in any scenario, the
    divergence penalty of its worst one.

    `evaluations` counts episodes (points x scenarios), the search's budget; `budget` and `remaining` count
    points, which is what the methods size their batches with.
    """

    def __init__(self, template: EpisodeSpec, index_name: str, budget: int, progress=None,
                 scenarios: tuple[EpisodeSpec, ...] | None = None, aggregate: str = 'worst') -> None:
        self.field = index_name
        self.scenarios = (template,) if scenarios is None else tuple(scenarios)
        self.aggregate = aggregate
        self.groups = scenario_batches(self.scenarios)
        self.budget = budget // len(self.scenarios)
        self.progress = progress
        self.evaluations = 0
        self.batch_calls = 0
        self.records: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self.best_value, self.best_point = np.inf, None

    @property
    def remaining(self) -> int:
        return self.budget - self.evaluations // len(self.scenarios)

    def _scenario_values(self, kp: np.ndarray, kv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's value (the index, or the divergence penalty) and divergence in each scenario: (P, S) each."""
        count = len(kp)
        values = np.empty((count, len(self.scenarios)))
        diverged = np.empty((count, len(self.scenarios)), dtype=bool)
        for group in self.groups:
            repeats = len(group.members)
            varied = {} if repeats == 1 else {'tau': np.repeat(group.taus, count),
                                              'mass_scale': np.repeat(group.mass_scales, count, axis=0)}
            batch = group.runner(np.tile(kp, (repeats, 1)), np.tile(kv, (repeats, 1)), **varied)
            self.batch_calls += 1
            scored_fraction = batch.samples_scored / (group.runner.plan.k_max + 1)
            value = np.where(batch.diverged, DIVERGED_PENALTY * (2.0 - scored_fraction), getattr(batch, self.field))
            values[:, group.members] = value.reshape(repeats, count).T
            diverged[:, group.members] = batch.diverged.reshape(repeats, count).T
        return values, diverged

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Objective values of points (P, 2n): the batch calls of the scenarios for those inside GAIN_RANGE."""
        check_stop()
        points = np.asarray(points, dtype=float)
        dof = points.shape[1] // 2
        values = np.full(len(points), 3 * DIVERGED_PENALTY)
        low, high = np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])
        inside = np.all((points >= low) & (points <= high), axis=1)
        if inside.any():
            gains = np.exp(points[inside])
            scenario_values, diverged = self._scenario_values(gains[:, :dof], gains[:, dof:])
            # Every penalty exceeds every index, so the largest value is the worst scenario's penalty.
            worst = scenario_values.max(axis=1)
            aggregated = worst if self.aggregate == 'worst' else scenario_values.mean(axis=1)
            values[inside] = np.where(diverged.any(axis=1), worst, aggregated)
            self.records.append((gains[:, :dof], gains[:, dof:], np.where(diverged.any(axis=1), np.inf, aggregated),
                                 len(self.records)))
        self.evaluations += len(points) * len(self.scenarios)
        best = int(np.argmin(values))
        if values[best] < self.best_value:
            self.best_value, self.best_point = float(values[best]), points[best].copy()
        if self.progress is not None:
            self.progress(self.evaluations, self.best_value if self.best_value < DIVERGED_PENALTY else None)
        return values

    def history_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Every point simulated so far, in log gain (P, 2n), and its index (+inf if it diverged)."""
        if not self.records:
            return np.empty((0, 0)), np.empty(0)
        points = np.log(np.concatenate([np.concatenate([record[0], record[1]], axis=1) for record in self.records]))
        return points, np.concatenate([record[2] for record in self.records])

    def result(self, method: str, index_name: str, restarts: tuple[Restart, ...] = (),
               evolution_generations: int = 0) -> SearchResult:
        dof = len(self.best_point) // 2
        gains = np.exp(self.best_point)
        kp_history = np.concatenate([record[0] for record in self.records])
        return SearchResult(
            method=method, index_name=index_name, kp=gains[:dof], kv=gains[dof:],
            index=self.best_value if self.best_value < DIVERGED_PENALTY else np.inf,
            episodes=len(kp_history) * len(self.scenarios), batches=self.batch_calls, history_kp=kp_history,
            history_kv=np.concatenate([record[1] for record in self.records]),
            history_index=np.concatenate([record[2] for record in self.records]),
            history_batch=np.concatenate([np.full(len(record[0]), record[3]) for record in self.records]),
            restarts=restarts, evolution_generations=evolution_generations)


def omega_starts(template: EpisodeSpec, omegas) -> tuple[np.ndarray, np.ndarray]:
    """Start gains from section 2's ω rules for the template's controller at each ω: (kp, kv), each (S, n)."""
    pairs = [gains_from_omega(template, float(omega)) for omega in omegas]
    return np.array([kp for kp, _ in pairs]), np.array([kv for _, kv in pairs])


def _start_points(start_kp, start_kv) -> np.ndarray:
    kp, kv = np.array(start_kp, dtype=float), np.array(start_kv, dtype=float)
    if kp.ndim != 2 or kp.shape != kv.shape or len(kp) == 0:
        raise SearchError(f'start_kp and start_kv must both have shape (S, n) with S >= 1, '
                          f'got {kp.shape} and {kv.shape}')
    if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(kv)) and np.all(kp > 0) and np.all(kv > 0)):
        raise SearchError('start gains must be finite and positive')
    if np.any(np.minimum(kp, kv) < GAIN_RANGE[0]) or np.any(np.maximum(kp, kv) > GAIN_RANGE[1]):
        raise SearchError(f'start gains must lie within GAIN_RANGE {GAIN_RANGE}')
    return np.log(np.concatenate([kp, kv], axis=1))


def search_gains(template: EpisodeSpec, *, index: str, start_kp, start_kv, budget: int,
                 method: str = 'nelder-mead', seed: int = 0, step: float = 0.5,
                 popsize: int | None = None, progress=None, scenarios: tuple[EpisodeSpec, ...] | None = None,
                 aggregate: str = 'worst') -> SearchResult:
    """Minimise the index I1 (2.5), I2 or I (3.2) of `template`'s episode over its diagonal gains (spec §9),
    or its worst case or mean over `scenarios`.

    Args:
        template: the episode (controller, trajectory, T, Δ, delay, τ, limits, plant); its own
            kp and kv are not used.
        index: 'I1', 'I2' or 'I' (= I1 + I2).
        start_kp, start_kv: start gains, shape (S, n) each (e.g. omega_starts).
        budget: the most episodes evaluated: points x scenarios, a Nelder-Mead point outside GAIN_RANGE
            (not simulated) counted as if it were; the search stops before a batch that would exceed it.
        method: 'global' (differential evolution, then local CMA-ES runs; see the module and _global),
            'nelder-mead' (one simplex per start, advanced together) or 'cma' (CMA-ES from the
            best start).
        seed: the random draws of CMA-ES and of DE; Nelder-Mead is deterministic.
        step: the initial spread in log gain: Nelder-Mead's simplex edge, CMA-ES's σ0 (not used by
            'global', whose DE spans its box and whose local runs start at LOCAL_SIGMA).
        popsize: CMA-ES's population per batch (default: cma's, 4 + 3 ln 2n); for 'global', DE's
            population per dimension (default DE_POPSIZE).
        progress: called as progress(episodes so far, best index so far or None) after each batch.
        scenarios: the episodes each point is evaluated on (e.g. ddarm.tuning.robust.scenario_grid), all on
            the template's joints; None: the template alone. The template then serves only for its joints.
        aggregate: what a point scores over the scenarios: 'worst' (the largest index) or 'mean'; a point
            that diverged in any scenario scores the divergence penalty of its worst one.

    With scenarios, the history has one row per point, its aggregated index (+inf if it diverged in any
    scenario), `index` is the best aggregated index, and `episodes` counts the points simulated x scenarios.
    The result is a pure function of the arguments. Raises SearchError for a bad specification (check_search).
    """
    starts = check_search(template, index=index, start_kp=start_kp, start_kv=start_kv, budget=budget,
                          method=method, step=step, popsize=popsize, scenarios=scenarios, aggregate=aggregate,
                          seed=seed)
    objective = _Objective(template, index, int(budget), progress, None if scenarios is None else tuple(scenarios),
                           aggregate)
    if method == 'global':
        restarts, generations = _global(objective, starts, seed, DE_POPSIZE if popsize is None else int(popsize))
        return objective.result(method, index, restarts, generations)
    if method == 'nelder-mead':
        _nelder_mead(objective, starts, step)
    else:
        _cma(objective, starts, step, seed, popsize)
    return objective.result(method, index)


def check_search(template: EpisodeSpec, *, index: str, start_kp, start_kv, budget: int,
                 method: str = 'nelder-mead', step: float = 0.5, popsize: int | None = None,
                 scenarios: tuple[EpisodeSpec, ...] | None = None, aggregate: str = 'worst',
                 seed: int = 0) -> np.ndarray:
    """Refuse, with SearchError naming the argument, a search that search_gains (same arguments) cannot run.

    Returns the start points, (S, 2n) in log gain. No episode is run.
    """
    if index not in INDICES:
        raise SearchError(f'index must be one of {list(INDICES)}, got {index!r}')
    if method not in METHODS:
        raise SearchError(f'method must be one of {METHODS}, got {method!r}')
    if not (np.isfinite(step) and step > 0):
        raise SearchError(f'step must be finite and positive, got {step!r}')
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SearchError(f'seed must be a whole number >= 0, got {seed!r}')
    if popsize is not None and (isinstance(popsize, bool) or not isinstance(popsize, (int, np.integer))
                                or popsize < 2):
        raise SearchError(f'popsize must be a whole number of at least 2, got {popsize!r}')
    if aggregate not in AGGREGATES:
        raise SearchError(f'aggregate must be one of {AGGREGATES}, got {aggregate!r}')
    if scenarios is not None:
        scenarios = tuple(scenarios)
        if not scenarios or not all(isinstance(scenario, EpisodeSpec) for scenario in scenarios):
            raise SearchError('scenarios must be None or at least one EpisodeSpec')
        joints = arm_joints(template)[0]
        for scenario in scenarios:
            if arm_joints(scenario)[0] != joints:
                raise SearchError(f'every scenario must control the template\'s joints {list(joints)}, '
                                  f'got {list(arm_joints(scenario)[0])}')
    count = 1 if scenarios is None else len(scenarios)
    starts = _start_points(start_kp, start_kv)
    minimum = len(starts) * (starts.shape[1] + 1) if method == 'nelder-mead' else len(starts)
    if method == 'global':  # the starts and one local population
        minimum = len(starts) + LOCAL_POPSIZE
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < minimum * count:
        raise SearchError(f'budget must be a whole number of at least {minimum * count} episodes '
                          f'(the starts{" and their simplices" if method == "nelder-mead" else ""}'
                          f'{" and one local population" if method == "global" else ""}'
                          f'{f", each on {count} scenarios" if count > 1 else ""}), got {budget!r}')
    return starts


def search_box(starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box (low, high) in log gain that the global search's differential evolution samples.

    The starts' own span widened by OMEGA_SPAN in ω (so OMEGA_SPAN² in k_p, which the ω rules
    make grow as ω², and OMEGA_SPAN in k_v, as ω) and by GAIN_SPREAD in every gain.
    """
    dof = starts.shape[1] // 2
    widening = np.concatenate([np.full(dof, 2.0), np.ones(dof)]) * np.log(OMEGA_SPAN) + GAIN_SPREAD
    low = np.maximum(starts.min(axis=0) - widening, np.log(GAIN_RANGE[0]))
    return low, np.minimum(starts.max(axis=0) + widening, np.log(GAIN_RANGE[1]))


def cma_options(rng, popsize: int | None = None, tolx: float | None = None) -> dict:
    """cma's options for a search over log gains: GAIN_RANGE, draws from `rng`, silent; cma's defaults unless given."""
    options = {
        'bounds': [np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])],
        # Draws from a private generator: NaN keeps cma from seeding NumPy's global one.
        'randn': lambda *shape: rng.standard_normal(shape), 'seed': np.nan,
        'verbose': -9, 'verb_log': 0, 'verb_disp': 0,
    }
    if popsize is not None:
        options['popsize'] = int(popsize)
    if tolx is not None:
        options['tolx'] = tolx
    return options


class _Run:
    """One local CMA-ES run of the global search under way: its strategy, where it started, what it found so far."""

    def __init__(self, origin: str, start: np.ndarray, popsize: int, rng) -> None:
        # Imported here, not at the top: cma (with scipy.stats) takes 1.5 to 2 s that most commands need not wait.
        import cma

        self.origin = origin
        self.strategy = cma.CMAEvolutionStrategy(start, LOCAL_SIGMA, cma_options(rng, popsize, CMA_XTOL))
        self.episodes, self.index = 0, np.inf

    def tell(self, population, values: np.ndarray, episodes: int) -> None:
        self.strategy.tell(population, values.tolist())
        self.episodes += episodes
        best = float(values.min())
        self.index = min(self.index, best if best < DIVERGED_PENALTY else np.inf)

    def restart(self, stopped_by: tuple[str, ...]) -> Restart:
        return Restart(self.origin, self.strategy.popsize, self.episodes, self.index, stopped_by)


def _global(objective: _Objective, starts: np.ndarray, seed: int, popsize: int) -> tuple[tuple[Restart, ...], int]:
    """Differential evolution over `search_box`, then local CMA-ES runs from its LOCAL_RUNS best distinct members.

    DE (scipy's: best1bin, Latin hypercube initialisation, the best start among its members) gets 1 - LOCAL_SHARE of
    the budget; its whole population (popsize × 2n members) is one batch call per generation. The indices
    sum |e| and |P - P^nom| over the samples, so they have a kink wherever a sample's error or torque
    deviation changes sign: their landscape is rough, with local minima close together, and a population
    method that keeps sampling the whole box finds the deep ones where restarted CMA-ES runs settle in the
    first they meet. The local runs (σ0 = LOCAL_SIGMA) share the rest of the budget, their populations one
    batch call, until cma stops them or the budget ends; each is a `Restart` of the result.
    """
    rng = np.random.default_rng(seed)
    values = objective(starts)
    low, high = search_box(starts)
    dimension = starts.shape[1]
    members = max(5, popsize * dimension)  # scipy's own population size
    generations = int((1.0 - LOCAL_SHARE) * objective.remaining) // members - 1
    evolution_generations = 0
    if generations >= 1:
        evolution = scipy.optimize.differential_evolution(
            lambda population: objective(population.T), list(zip(low, high)), vectorized=True,
            updating='deferred', popsize=popsize, maxiter=generations, tol=DE_TOL, polish=False,
            x0=starts[int(np.argmin(values))], rng=rng)
        evolution_generations = int(evolution.nit)
    # The local runs start from the best points seen, DISTINCT apart: DE's last population often sits in one
    # basin, where the points it passed on the way may mark deeper ones close by.
    points, energies = objective.history_points()
    chosen: list[int] = []
    for member in np.argsort(energies, kind='stable'):
        if not np.isfinite(energies[member]):
            break
        if all(np.max(np.abs(points[member] - points[other])) > DISTINCT for other in chosen):
            chosen.append(int(member))
        if len(chosen) == LOCAL_RUNS:
            break
    origins = [f'point {rank + 1} seen ({energies[member]:.6g})' for rank, member in enumerate(chosen)]
    # As many runs as the budget has room for a population of each: a run that never ran is no confidence figure.
    room = max(1, objective.remaining // LOCAL_POPSIZE)
    origins, chosen = origins[:room], chosen[:room]
    runs = [_Run(origin, points[member], LOCAL_POPSIZE, rng) for origin, member in zip(origins, chosen)]
    finished = []
    while runs:
        while runs and sum(run.strategy.popsize for run in runs) > objective.remaining:
            run = runs.pop()
            finished.append(run.restart(('budget',)))
        if not runs:
            break
        populations = [run.strategy.ask() for run in runs]
        values = objective(np.concatenate([np.array(population) for population in populations]))
        ends = np.cumsum([len(population) for population in populations])
        for run, population, run_values in zip(list(runs), populations, np.split(values, ends[:-1])):
            run.tell(population, run_values, len(population) * len(objective.scenarios))
            if run.strategy.stop():
                finished.append(run.restart(tuple(run.strategy.stop())))
                runs.remove(run)
    ran = [restart for restart in finished if restart.episodes > 0]
    return tuple(sorted(ran, key=lambda restart: origins.index(restart.start))), evolution_generations


def _cma(objective: _Objective, starts: np.ndarray, step: float, seed: int, popsize: int | None) -> None:
    """CMA-ES (the `cma` package) from the best start, one batch call per population."""
    import cma  # see _Run

    values = objective(starts)
    rng = np.random.default_rng(seed)
    strategy = cma.CMAEvolutionStrategy(starts[int(np.argmin(values))], step, cma_options(rng, popsize))
    while not strategy.stop() and strategy.popsize <= objective.remaining:
        population = strategy.ask()
        strategy.tell(population, objective(np.array(population)).tolist())


def _nelder_mead(objective: _Objective, starts: np.ndarray, step: float) -> None:
    """Nelder-Mead (standard coefficients 1, 2, 1/2, 1/2) from every start at once.

    scipy's Nelder-Mead asks for one point at a time, so it cannot batch the starts; here
    each phase of an iteration (the reflections; the expansions and contractions; the shrinks)
    is one batch call over all starts that need it. Evaluating all four candidates at once
    would make an iteration one call but would about double the episodes.
    """
    count, dimension = starts.shape
    simplex = starts[:, None, :] + step * np.concatenate([np.zeros((1, dimension)), np.eye(dimension)])[None]
    values = objective(simplex.reshape(-1, dimension)).reshape(count, dimension + 1)
    active = np.ones(count, dtype=bool)
    while True:
        order = np.argsort(values, axis=1, kind='stable')
        simplex = np.take_along_axis(simplex, order[:, :, None], axis=1)
        values = np.take_along_axis(values, order, axis=1)
        spread = np.max(np.abs(simplex[:, 1:] - simplex[:, :1]), axis=(1, 2))
        agreement = np.max(np.abs(values[:, 1:] - values[:, :1]), axis=1) <= NM_FTOL * np.abs(values[:, 0])
        active &= ~((spread <= NM_XTOL) & agreement)
        moving = np.flatnonzero(active)
        if len(moving) == 0 or len(moving) > objective.remaining:
            return
        best, worst = values[moving, 0], values[moving, -1]
        centroid = simplex[moving, :-1].mean(axis=1)
        reflected = 2.0 * centroid - simplex[moving, -1]
        reflected_value = objective(reflected)
        expand = reflected_value < best
        accept = ~expand & (reflected_value < values[moving, -2])
        outside = ~expand & ~accept & (reflected_value < worst)
        inside = ~expand & ~accept & ~outside
        trial = np.where(expand[:, None], centroid + 2.0 * (reflected - centroid),
                         np.where(outside[:, None], centroid + 0.5 * (reflected - centroid),
                                  centroid + 0.5 * (simplex[moving, -1] - centroid)))
        tried = ~accept
        if tried.sum() > objective.remaining:
            return
        trial_value = np.full(len(moving), np.inf)
        if tried.any():
            trial_value[tried] = objective(trial[tried])
        new_vertex, new_value = reflected.copy(), reflected_value.copy()
        take_trial = ((expand & (trial_value < reflected_value)) | (outside & (trial_value <= reflected_value))
                      | (inside & (trial_value < worst)))
        new_vertex[take_trial], new_value[take_trial] = trial[take_trial], trial_value[take_trial]
        shrink = (outside & (trial_value > reflected_value)) | (inside & (trial_value >= worst))
        keep = ~shrink
        simplex[moving[keep], -1], values[moving[keep], -1] = new_vertex[keep], new_value[keep]
        shrinking = moving[shrink]
        if len(shrinking):
            if len(shrinking) * dimension > objective.remaining:
                return
            shrunk = simplex[shrinking, :1] + 0.5 * (simplex[shrinking, 1:] - simplex[shrinking, :1])
            simplex[shrinking, 1:] = shrunk
            values[shrinking, 1:] = objective(shrunk.reshape(-1, dimension)).reshape(len(shrinking), dimension)
