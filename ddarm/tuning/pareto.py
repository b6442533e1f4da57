"""The Pareto front of the indices I1 (2.5, tracking error) and I2 (torque deviation from nominal) over the
diagonal gains, through the batch engine: the gains for which neither index can be lowered without raising
the other, from the I1 optimum at one end to the I2 optimum at the other, with the I = I1 + I2 (3.2)
optimum on it.

The search space is that of ddarm.tuning.search, x = (log k_p, log k_v) within GAIN_RANGE, and every step
below is one batch call of the engine. The caller's seeds (the single-index optima) are evaluated first,
as given. Then two phases:

1. NSGA-II (pymoo) explores, one generation's offspring one batch. NSGA-II rather than SMS-EMOA, whose
   hypervolume selection is designed steady-state (one offspring per step: one episode per batch) and,
   run generationally to fill a batch, keeps only its advantage of a well-spread final population, which
   the archive and the refinement below give here; or NSGA-III, whose reference directions are for three
   or more objectives (with two it is NSGA-II with a niching that needs the objectives normalised); or
   MOEA/D, which pymoo runs one offspring at a time and without constraints. Its objectives are log I1 and
   log I2, so its crowding distance spreads the population over the orders of magnitude the front spans
   (non-domination is the same in either scale). A diverged episode is infeasible: pymoo ranks it below
   every bounded one, by how early it diverged, never by the indices of its few scored samples. The first
   population holds the seeds, the ω-rule gains at each ω of `omegas`, and log-normal perturbations of them.
2. Scalarised CMA-ES searches refine: `searches` points spread along the front so far (its two ends, its
   point of least I, and points between) each start a CMA-ES search of one scalarisation, and the
   populations of all searches are one batch per generation. The end at least I1 minimises I1, the end at
   least I2 minimises I2, the least-I point minimises I1 + I2 (3.2), and each point between minimises the
   augmented Chebyshev distance, in (log I1, log I2) scaled to the front's extent, from a point beyond both
   ideal values along the ray through it: unlike weighted sums, these reach the parts of a front that are
   not convex too. A search converges (cma's own tolerances, its step below SEARCH_XTOL in log gain) or
   stops before a batch that would exceed the budget.

Every evaluated episode that did not diverge goes into an archive, and the front reported is the archive's
non-dominated set: an episode evaluated, a seed's among them, is never lost to the algorithms' selection.
It is then thinned to `points` points spread along it (farthest-point selection in the scaled log plane),
always keeping both ends and the point of least I. The reported indices are those of the episodes the
engine ran with the reported gains, which run_episode reproduces exactly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pymoo.algorithms.moo.nsga2 import NSGA2
from pymoo.config import Config
from pymoo.core.evaluator import Evaluator
from pymoo.core.problem import Problem
from pymoo.problems.static import StaticProblem
from pymoo.util.nds.non_dominated_sorting import NonDominatedSorting

from ddarm.episodes.engine import BatchRunner
from ddarm.episodes.spec import EpisodeSpec, plan_episode
from ddarm.interrupts import check_stop
from ddarm.tuning.methods import DEFAULT_BUDGET, DEFAULT_POINTS, DEFAULT_POPULATION, DEFAULT_SEARCHES, ParetoError
from ddarm.tuning.search import DIVERGED_PENALTY, GAIN_RANGE, cma_options, omega_starts

# pymoo prints a hint to stdout when its compiled modules are missing; the core prints nothing.
Config.warnings['not_compiled'] = False

METHOD = 'NSGA-II (pymoo) + scalarised CMA-ES refinement, over log gains, on an archive of every episode'
# ω of the ω-rule gains in the first population: from barely any feedback to beyond the stability
# limit of the paper's arm, so both ends of the front have a start near them.
START_OMEGAS = (1.0, 2.0, 4.0, 8.0, 12.0, 15.0, 20.0, 30.0, 40.0, 60.0)
# Spread, in log gain, of the perturbed starts that fill the first population.
START_SPREAD = 1.0
# Part of the budget the seeds and NSGA-II may spend; the refinement spends the rest. On the paper's arm, more
# refinement gave fronts closer to the best known than an even split or NSGA-II alone, at the same budget.
EXPLORATION_SHARE = 0.3
# σ0 of each refining CMA-ES search, in log gain: it starts on the front, so it looks close by.
SEARCH_STEP = 0.1
# A refining search has converged once its steps are below this in log gain (0.01 %).
SEARCH_XTOL = 1e-4
# The Chebyshev searches' reference lies this far (in the scaled log plane, where the front spans 1)
# beyond the ideal values, and their augmentation weighs the sum of the two distances this much.
CHEBYSHEV_MARGIN = 0.1
CHEBYSHEV_AUGMENTATION = 1e-3
# The logarithm's floor, for an index that is exactly 0.
SMALLEST_INDEX = 1e-300



@dataclass(frozen=True)
class FrontPoint:
    """One point of the front: its gains (N m/rad, N m s/rad for revolute joints) and their episode's indices."""

    I1: float
    I2: float
    kp: np.ndarray
    kv: np.ndarray

    @property
    def I(self) -> float:  # noqa: E743 — the paper's name for (3.2)
        return self.I1 + self.I2


@dataclass(frozen=True)
class ParetoResult:
    """A finished front: its points, sorted by I1 (so by falling I2), mutually non-dominated.

    `front` is thinned to the `points` asked for from the archive's `front_size` non-dominated points.
    `episodes` counts the episodes evaluated (`diverged` of them diverged) in `batches` batch calls, NSGA-II's
    in `generations` (its first population one); `searches` refining searches ran, `searches_converged` of
    them to their own tolerance (the others stopped at the budget, so the front near them may move with a
    larger budget). `seeds_on_front` says, for each seed, whether its episode is one of the `front_size`
    points (thinned out or not) rather than dominated by one.
    """

    method: str
    front: tuple[FrontPoint, ...]
    front_size: int
    episodes: int
    diverged: int
    batches: int
    generations: int
    searches: int
    searches_converged: int
    seeds_on_front: tuple[bool, ...]
    wall_time_s: float


class _Archive:
    """Every episode evaluated, as the non-dominated set of the bounded ones; one batch call per evaluation."""

    def __init__(self, template: EpisodeSpec, budget: int, progress) -> None:
        self.template = template
        self.plan = plan_episode(template)
        self.run_batch = BatchRunner(template, self.plan)
        self.dof = self.plan.q_ref.shape[1]
        self.budget = budget
        self.progress = progress
        self.episodes = self.diverged = self.batches = 0
        self.gains = np.empty((0, 2 * self.dof))  # the front's (kp, kv), as simulated
        self.indices = np.empty((0, 2))  # the front's (I1, I2)
        self.phase = ''

    @property
    def remaining(self) -> int:
        return self.budget - self.episodes

    def evaluate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(I1, I2, scored fraction) of log-gain points (P, 2n) in one batch (see evaluate_gains)."""
        return self.evaluate_gains(np.exp(points))

    def evaluate_gains(self, gains: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(I1, I2, scored fraction) of gains (P, 2n), (kp, kv) per row, in one batch; the fraction is 1 for a
        bounded episode and that of the samples before the divergence for a diverged one (its I1 and I2 are +inf)."""
        check_stop()
        batch = self.run_batch(gains[:, :self.dof], gains[:, self.dof:])
        bounded = ~batch.diverged
        self.episodes += len(gains)
        self.diverged += int(batch.diverged.sum())
        self.batches += 1
        self._merge(gains[bounded], np.column_stack([batch.I1, batch.I2])[bounded])
        if self.progress is not None:
            self.progress(self.episodes, self.summary())
        fraction = np.where(bounded, 1.0, batch.samples_scored / (self.plan.k_max + 1))
        return np.where(bounded, batch.I1, np.inf), np.where(bounded, batch.I2, np.inf), fraction

    def _merge(self, gains: np.ndarray, indices: np.ndarray) -> None:
        # The non-dominated set of the archive is that of (its non-dominated set so far ∪ the new episodes).
        gains, indices = np.vstack([self.gains, gains]), np.vstack([self.indices, indices])
        front = NonDominatedSorting().do(indices, only_non_dominated_front=True)
        # Equal indices do not dominate one another: keep the first episode that reached them.
        _, first = np.unique(indices[front], axis=0, return_index=True)
        front = np.sort(front[first])
        order = np.argsort(indices[front, 0], kind='stable')
        self.gains, self.indices = gains[front[order]], indices[front[order]]

    def on_front(self, gains: np.ndarray) -> bool:
        """Whether the episode of these gains (2n,) is a point of the front."""
        return bool(np.any(np.all(self.gains == gains, axis=1)))

    def summary(self) -> str:
        """The phase and the front so far, for a progress display."""
        if len(self.indices) == 0:
            return f'{self.phase}: no bounded episode yet'
        least_I = float(np.min(self.indices.sum(axis=1)))
        return (f'{self.phase}: front of {len(self.indices)} so far, least I1 {self.indices[0, 0]:.6g}, '
                f'least I2 {self.indices[-1, 1]:.6g}, least I {least_I:.6g}')


def _log_indices(indices: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(indices, SMALLEST_INDEX))


def _scaled(log_indices: np.ndarray, front_log: np.ndarray) -> np.ndarray:
    """log_indices in the plane where the front `front_log` runs from 0 to 1 on each axis."""
    low = front_log.min(axis=0)
    extent = front_log.max(axis=0) - low
    return (log_indices - low) / np.where(extent > 0, extent, 1.0)


def spread_points(indices: np.ndarray, count: int) -> np.ndarray:
    """The positions of at most `count` points of a front (M, 2) of (I1, I2), sorted by I1, spread along it.

    Both ends and the point of least I1 + I2 are always kept; the others are added one by one, each the
    point farthest from those already kept, in (log I1, log I2) scaled to the front's extent. Returns
    sorted positions.
    """
    if len(indices) <= count:
        return np.arange(len(indices))
    plane = _scaled(_log_indices(indices), _log_indices(indices))
    kept = sorted({0, len(indices) - 1, int(np.argmin(indices.sum(axis=1)))})
    distance = np.min(np.linalg.norm(plane[:, None, :] - plane[None, kept, :], axis=2), axis=1)
    while len(kept) < count:
        farthest = int(np.argmax(distance))
        kept.append(farthest)
        distance = np.minimum(distance, np.linalg.norm(plane - plane[farthest], axis=1))
    return np.sort(np.array(kept))


def _seed_gains(seeds, dof: int) -> np.ndarray:
    """The seeds as rows of (kp, kv), (S, 2n), checked."""
    rows = []
    for index, (seed_kp, seed_kv) in enumerate(seeds):
        gains = np.concatenate([np.asarray(seed_kp, dtype=float).ravel(), np.asarray(seed_kv, dtype=float).ravel()])
        if gains.shape != (2 * dof,) or not np.all(np.isfinite(gains)) or np.any(gains <= 0):
            raise ParetoError(f'seed {index} must be {dof} finite positive kp and as many kv')
        if np.any(gains < GAIN_RANGE[0]) or np.any(gains > GAIN_RANGE[1]):
            raise ParetoError(f'seed {index} must lie within GAIN_RANGE {GAIN_RANGE}')
        rows.append(gains)
    return np.array(rows).reshape(len(rows), 2 * dof)


def _first_population(template: EpisodeSpec, seed_gains: np.ndarray, omegas, population: int, rng) -> np.ndarray:
    """The seeds, the ω-rule gains at each of `omegas`, and log-normal perturbations of them, in log gain:
    (population, 2n)."""
    low, high = np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])
    kp, kv = omega_starts(template, omegas)
    starts = np.unique(np.log(np.vstack([np.concatenate([kp, kv], axis=1), seed_gains])), axis=0)
    if len(starts) > population:
        raise ParetoError(f'population must hold the {len(starts)} seeds and ω-rule starts, got {population}')
    perturbed = (starts[rng.integers(len(starts), size=population - len(starts))]
                 + START_SPREAD * rng.standard_normal((population - len(starts), starts.shape[1])))
    return np.clip(np.vstack([starts, perturbed]), low, high)


def _explore(archive: _Archive, first: np.ndarray, budget: int, seed: int) -> int:
    """NSGA-II from the population `first` until its next generation would take the episodes beyond `budget`.

    Returns the generations run (the first population counts as one)."""
    low, high = np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])
    dimension = first.shape[1]
    problem = Problem(n_var=dimension, n_obj=2, n_ieq_constr=1, xl=np.full(dimension, low),
                      xu=np.full(dimension, high))
    algorithm = NSGA2(pop_size=len(first), sampling=first)
    algorithm.setup(problem, seed=seed, termination=('n_gen', np.iinfo(np.int64).max))
    generations = 0
    while True:
        offspring = algorithm.ask()
        if archive.episodes + len(offspring) > budget:
            return generations
        I1, I2, fraction = archive.evaluate(offspring.get('X'))
        bounded = np.isfinite(I1)
        objectives = np.where(bounded[:, None], _log_indices(np.column_stack([I1, I2])), np.log(DIVERGED_PENALTY))
        # Bounded: -1 (feasible). Diverged: the earlier, the more infeasible.
        violation = np.where(bounded, -1.0, 2.0 - fraction)[:, None]
        Evaluator().eval(StaticProblem(problem, F=objectives, G=violation), offspring)
        algorithm.tell(infills=offspring)
        generations += 1


class _Scalarisation:
    """The value one refining search minimises, from a batch's (I1, I2)."""

    def __init__(self, kind: str, target: np.ndarray | None = None, front_log: np.ndarray | None = None) -> None:
        self.kind = kind
        if kind == 'chebyshev':
            self.front_log = front_log
            self.reference = np.full(2, -CHEBYSHEV_MARGIN)
            self.weight = 1.0 / (_scaled(_log_indices(target), front_log) - self.reference)

    def __call__(self, I1: np.ndarray, I2: np.ndarray) -> np.ndarray:
        if self.kind == 'I1':
            return I1
        if self.kind == 'I2':
            return I2
        if self.kind == 'I':
            return I1 + I2
        distance = self.weight * (_scaled(_log_indices(np.column_stack([I1, I2])), self.front_log) - self.reference)
        return distance.max(axis=1) + CHEBYSHEV_AUGMENTATION * distance.sum(axis=1)


def _refine(archive: _Archive, searches: int, seed: int) -> tuple[int, int]:
    """Scalarised CMA-ES searches from `searches` points spread along the archive's front, advanced together
    until all converge or the next generation would exceed the budget. Returns (searches run, converged)."""
    import cma  # see ddarm.tuning.search._cma

    front_log = _log_indices(archive.indices)
    least_I = int(np.argmin(archive.indices.sum(axis=1)))
    rng = np.random.default_rng(seed)
    options = cma_options(rng, tolx=SEARCH_XTOL)
    last = len(archive.indices) - 1
    # The ends and the least-I point minimise the single indices; the others their Chebyshev distance.
    searched = [(0, _Scalarisation('I1')), (last, _Scalarisation('I2')), (least_I, _Scalarisation('I'))]
    searched += [(position, _Scalarisation('chebyshev', archive.indices[position], front_log))
                 for position in spread_points(archive.indices, searches - 3 + len({0, last, least_I}))
                 if position not in {0, last, least_I}]
    strategies = [cma.CMAEvolutionStrategy(np.log(archive.gains[position]), SEARCH_STEP, options)
                  for position, _ in searched]
    scalarisations = [scalarisation for _, scalarisation in searched]
    while True:
        active = [k for k, strategy in enumerate(strategies) if not strategy.stop()]
        if not active or sum(strategies[k].popsize for k in active) > archive.remaining:
            break
        asked = [np.array(strategies[k].ask()) for k in active]
        I1, I2, fraction = archive.evaluate(np.vstack(asked))
        first = 0
        for k, population in zip(active, asked):
            rows = slice(first, first + len(population))
            first += len(population)
            values = np.where(np.isfinite(I1[rows]), scalarisations[k](I1[rows], I2[rows]),
                              DIVERGED_PENALTY * (2.0 - fraction[rows]))
            strategies[k].tell(list(population), values.tolist())
    converged = sum(1 for strategy in strategies if strategy.stop())
    return len(strategies), converged


def pareto_front(template: EpisodeSpec, *, budget: int = DEFAULT_BUDGET, seed: int = 0, seeds=(),
                 omegas=START_OMEGAS, population: int = DEFAULT_POPULATION, searches: int = DEFAULT_SEARCHES,
                 points: int = DEFAULT_POINTS, progress=None) -> ParetoResult:
    """The I1–I2 Pareto front of `template`'s episode over its diagonal gains (module docstring: the method).

    Args:
        template: the episode (controller, motion, T, Δ, delay, τ, limits, plant); its own kp and kv are
            not used.
        budget: the most episodes evaluated, at least the seeds and the first population; EXPLORATION_SHARE
            of it goes to the seeds and NSGA-II, the rest (and what NSGA-II left) to the refining searches.
        seed: the random draws of the first population, NSGA-II and CMA-ES; the result is a pure function
            of the arguments.
        seeds: start gains that the front must not lose, such as the single-index optima (the gains of
            least I1 and of least I): (kp, kv) pairs of n gains each, evaluated first as given.
        omegas: ω of the ω-rule gains in the first population.
        population: NSGA-II's population, the episodes of each of its batches.
        searches: the most refining CMA-ES searches (fewer when the front after NSGA-II has fewer points).
        points: the most points reported, spread along the front.
        progress: None, or a callable progress(episodes_done, text) called after every batch, `text`
            saying the phase and the front so far.

    Raises ParetoError for a bad specification, or when every episode evaluated diverged.
    """
    for name, value, least in (('budget', budget, 1), ('population', population, 4), ('searches', searches, 0),
                               ('points', points, 3)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ParetoError(f'{name} must be a whole number of at least {least}, got {value!r}')
    if searches in (1, 2):
        raise ParetoError(f'searches must be 0 (no refinement) or at least 3 (the two ends and the least-I point), '
                          f'got {searches!r}')
    started = time.perf_counter()
    archive = _Archive(template, int(budget), progress)
    seed_gains = _seed_gains(seeds, archive.dof)
    if budget < len(seed_gains) + population:
        raise ParetoError(f'budget must be at least the seeds and the first population ({len(seed_gains)} + '
                          f'{population} episodes), got {budget!r}')
    if len(seed_gains):
        # As given: through log gains, NSGA-II would evaluate gains a rounding away from the seeds.
        archive.phase = 'seeds'
        archive.evaluate_gains(seed_gains)
    first = _first_population(template, seed_gains, omegas, int(population), np.random.default_rng(seed))
    archive.phase = 'NSGA-II'
    generations = _explore(archive, first, max(int(EXPLORATION_SHARE * budget), archive.episodes + population), seed)
    if len(archive.indices) == 0:
        raise ParetoError(f'all {archive.episodes} episodes evaluated diverged: no front')
    archive.phase = 'refining'
    run, converged = _refine(archive, int(searches), seed) if searches else (0, 0)
    kept = spread_points(archive.indices, int(points))
    dof = archive.dof
    front = tuple(FrontPoint(I1=float(I1), I2=float(I2), kp=gains[:dof].copy(), kv=gains[dof:].copy())
                  for (I1, I2), gains in zip(archive.indices[kept], archive.gains[kept]))
    return ParetoResult(method=METHOD, front=front, front_size=len(archive.indices), episodes=archive.episodes,
                        diverged=archive.diverged, batches=archive.batches, generations=generations,
                        searches=run, searches_converged=converged,
                        seeds_on_front=tuple(archive.on_front(gains) for gains in seed_gains),
                        wall_time_s=time.perf_counter() - started)
