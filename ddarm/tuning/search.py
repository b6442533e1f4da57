"""Optimisation of the indices I1 (2.5), I2 or I (3.2) over the six diagonal gains (spec §9), through the batch engine.

Both methods search x = (log k_p, log k_v), so every point is a valid positive gain and a
step means the same relative change for a large and a small gain. Every evaluation of an
iteration (a CMA-ES population; the moves of all Nelder-Mead starts) is one batch call.
"""

from __future__ import annotations

from dataclasses import dataclass

import cma
import numpy as np

from ddarm.errors import DdarmError
from ddarm.episodes.engine import simulate_batch
from ddarm.episodes.indices import INDICES
from ddarm.episodes.spec import EpisodeSpec, gains_from_omega, plan_episode
from ddarm.interrupts import check_stop

METHODS = ('nelder-mead', 'cma')
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


class SearchError(DdarmError, ValueError):
    """A search specification that cannot be run."""


@dataclass(frozen=True)
class SearchResult:
    """The best gains found, and every episode evaluated on the way (in evaluation order).

    `index` is the best gains' value of the index named `index_name`, +inf if every episode diverged;
    history_index holds +inf for the diverged episodes. `batches` counts the batch calls.
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

    def best_so_far(self) -> np.ndarray:
        """The best index after each episode: the optimiser's progress."""
        return np.minimum.accumulate(self.history_index)


class _Objective:
    """The index of a batch of log-gain points; keeps the history and the best point."""

    def __init__(self, template: EpisodeSpec, index_name: str, budget: int) -> None:
        self.template = template
        self.field = index_name
        self.plan = plan_episode(template)
        self.budget = budget
        self.evaluations = 0
        self.records: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self.best_value, self.best_point = np.inf, None

    @property
    def remaining(self) -> int:
        return self.budget - self.evaluations

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Objective values of points (P, 2n), one batch call for those inside GAIN_RANGE."""
        check_stop()
        points = np.asarray(points, dtype=float)
        dof = points.shape[1] // 2
        values = np.full(len(points), 3 * DIVERGED_PENALTY)
        low, high = np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])
        inside = np.all((points >= low) & (points <= high), axis=1)
        if inside.any():
            gains = np.exp(points[inside])
            batch = simulate_batch(self.template, gains[:, :dof], gains[:, dof:], plan=self.plan)
            index = getattr(batch, self.field)
            scored_fraction = batch.samples_scored / (self.plan.k_max + 1)
            values[inside] = np.where(batch.diverged, DIVERGED_PENALTY * (2.0 - scored_fraction), index)
            self.records.append((gains[:, :dof], gains[:, dof:], np.where(batch.diverged, np.inf, index),
                                 len(self.records)))
        self.evaluations += len(points)
        best = int(np.argmin(values))
        if values[best] < self.best_value:
            self.best_value, self.best_point = float(values[best]), points[best].copy()
        return values

    def result(self, method: str, index_name: str) -> SearchResult:
        dof = len(self.best_point) // 2
        gains = np.exp(self.best_point)
        kp_history = np.concatenate([record[0] for record in self.records])
        return SearchResult(
            method=method, index_name=index_name, kp=gains[:dof], kv=gains[dof:],
            index=self.best_value if self.best_value < DIVERGED_PENALTY else np.inf,
            episodes=len(kp_history), batches=len(self.records), history_kp=kp_history,
            history_kv=np.concatenate([record[1] for record in self.records]),
            history_index=np.concatenate([record[2] for record in self.records]),
            history_batch=np.concatenate([np.full(len(record[0]), record[3]) for record in self.records]))


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
                 popsize: int | None = None) -> SearchResult:
    """Minimise the index I1 (2.5), I2 or I (3.2) of `template`'s episode over its diagonal gains (spec §9).

    Args:
        template: the episode (controller, trajectory, T, Δ, delay, τ, limits, plant); its own
            kp and kv are not used.
        index: 'I1', 'I2' or 'I' (= I1 + I2).
        start_kp, start_kv: start gains, shape (S, n) each (e.g. omega_starts).
        budget: the most points evaluated (episodes, plus Nelder-Mead points outside GAIN_RANGE,
            which are not simulated); the search stops before a batch that would exceed it.
        method: 'nelder-mead' (one simplex per start, advanced together) or 'cma' (CMA-ES from
            the best start).
        seed: CMA-ES's random draws; Nelder-Mead is deterministic.
        step: the initial spread in log gain: Nelder-Mead's simplex edge, CMA-ES's σ0.
        popsize: CMA-ES's population per batch (default: cma's, 4 + 3 ln 2n).

    The result is a pure function of the arguments. Raises SearchError for a bad specification.
    """
    if index not in INDICES:
        raise SearchError(f'index must be one of {list(INDICES)}, got {index!r}')
    if method not in METHODS:
        raise SearchError(f'method must be one of {METHODS}, got {method!r}')
    if not (np.isfinite(step) and step > 0):
        raise SearchError(f'step must be finite and positive, got {step!r}')
    if popsize is not None and (isinstance(popsize, bool) or not isinstance(popsize, (int, np.integer))
                                or popsize < 2):
        raise SearchError(f'popsize must be a whole number of at least 2, got {popsize!r}')
    starts = _start_points(start_kp, start_kv)
    minimum = len(starts) * (starts.shape[1] + 1) if method == 'nelder-mead' else len(starts)
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < minimum:
        raise SearchError(f'budget must be a whole number of at least {minimum} episodes '
                          f'(the starts{" and their simplices" if method == "nelder-mead" else ""}), '
                          f'got {budget!r}')
    objective = _Objective(template, index, int(budget))
    if method == 'nelder-mead':
        _nelder_mead(objective, starts, step)
    else:
        _cma(objective, starts, step, seed, popsize)
    return objective.result(method, index)


def _cma(objective: _Objective, starts: np.ndarray, step: float, seed: int, popsize: int | None) -> None:
    """CMA-ES (the `cma` package) from the best start, one batch call per population."""
    values = objective(starts)
    rng = np.random.default_rng(seed)
    options = {
        'bounds': [np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])],
        # Draws from a private generator: NaN keeps cma from seeding NumPy's global one.
        'randn': lambda *shape: rng.standard_normal(shape), 'seed': np.nan,
        'verbose': -9, 'verb_log': 0, 'verb_disp': 0,
    }
    if popsize is not None:
        options['popsize'] = int(popsize)
    strategy = cma.CMAEvolutionStrategy(starts[int(np.argmin(values))], step, options)
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
