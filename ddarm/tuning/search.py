"""Optimisation of the indices I1 (2.5), I2 or I (3.2) over the 2n diagonal gains (spec §9), through the batch engine.

Every method searches x = (log k_p, log k_v), so every point is a valid positive gain and a
step means the same relative change for a large and a small gain. Every run asks for its points in rounds (a
CMA-ES population; a DE generation; the next move of every Nelder-Mead simplex), and the runs that go on side by
side share one batch call per round (`_side_by_side`).

`global` (the default of `ddarm tune` and `ddarm reproduce`) is a portfolio of independent runs, because each kind
finds basins the others miss (on cases outside the paper's tables, differential evolution from three seeds landed in
one basin where Nelder-Mead from the ω-rule gains found one 22-50 % deeper, and on other cases the reverse). First,
side by side: a differential evolution run (scipy's) from the best start, polished by local CMA-ES runs from its best
distinct points; Nelder-Mead from every ω-rule start, the law's own rule and the other law's, the simplices' best
distinct ends then polished the same way; and a wide CMA-ES run. Then, one at a time, further differential
evolutions over a wider box and wide CMA-ES runs of doubling population (IPOP-CMA-ES), by turns, each from its own
draws. After each run a `Certificate` says how sure the search is: every run's best, the basins they ended in, how many
agree with the best.
The search stops once the certificate holds, or when the budget, a ceiling, has no room for another run; a result
that has not converged says so. A polish stops once it falls so far behind the search's best that the budget left
could not bring it there at its pace. On arms of 4 joints or more the polishes also stop once they creep, and a final
polish of the best point, outside the certificate, refines the minimum on the budget left.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, replace

import numpy as np
import scipy.optimize

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.control.laws import CONTROLLERS
from ddarm.errors import DdarmError
from ddarm.episodes.indices import INDICES
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, arm_joints, gains_from_omega
from ddarm.interrupts import check_stop
from ddarm.tuning.methods import DEFAULT_METHOD, METHODS
from ddarm.tuning.robust import AGGREGATES, scenario_batches

# A diverged episode is scored on the samples before its divergence, which can be few and
# score low: an optimiser sees DIVERGED_PENALTY x (2 - scored fraction) instead, far beyond
# any index of an episode whose state stayed within the plant's bounds, and worse the earlier
# it diverged (so CMA-ES still ranks diverged points among themselves).
DIVERGED_PENALTY = 1e100
# Gains searched, in the units of k_p and k_v; a Nelder-Mead point outside is not simulated
# and scores 3 x DIVERGED_PENALTY, CMA-ES is kept inside by its own bound handling (the local polishes, far inside,
# need none).
GAIN_RANGE = (1e-3, 1e9)
# Nelder-Mead stops a start once its simplex spans less than this in log gain (0.1 %) and
# its values agree to this relative tolerance, or (scipy's default) once it has evaluated NM_EVALUATIONS points per
# searched gain since its (re)start: a simplex among diverged gains follows the later divergences and may never
# converge. The CMA-ES polish of the ends (σ0 = POLISH_SIGMA) takes over from there, so a tighter simplex buys
# nothing: with 0.01 % and 1e-10 the last simplices crept on, one point each per batch, for a fifth of the paper's
# arm's computed torque search, while on rough PD + gravity cases the runs beside them used the budget the ends'
# polish then lacked (the 18 searches of docs/performance.md: mean gap 2.39 % against 2.04 %).
NM_XTOL = 1e-3
NM_FTOL = 1e-4
NM_EVALUATIONS = 200
# The global search's DE samples the box between the ω-rule gains at the smallest start ω divided by OMEGA_SPAN
# and at the largest times OMEGA_SPAN, each gain then spread by a factor e^{±GAIN_SPREAD}: every gain an ω rule
# could suggest, and off-rule ratios between k_p and k_v and between joints. Its polish may leave the box. The DE runs
# after the first spread every gain by e^{±WIDE_GAIN_SPREAD}: on three of the shared cases the deepest basin lies at
# or beyond the edge of the narrower box (a joint's k_p 20 times below every rule's, damped by its k_v alone).
OMEGA_SPAN = 2.0
GAIN_SPREAD = 1.5
WIDE_GAIN_SPREAD = 3.0
# DE's population per dimension (scipy's popsize): 15 × 2n members, one batch call per generation. A run stops once
# its members' values agree within DE_TOL relative (scipy's tol), after DE_GENERATIONS generations, or once it has
# spent DE_SHARE of the budget left at its start (the rest is for its polish and the other runs).
DE_POPSIZE = 15
DE_TOL = 1e-3
DE_GENERATIONS = 300
DE_SHARE = 0.6
# Each DE run is polished by local CMA-ES runs from its FINALISTS best points at least DISTINCT apart in some log
# gain (its last population often sits in one basin, while the points it passed on the way may mark deeper ones
# close by), with σ0 LOCAL_SIGMA and population LOCAL_POPSIZE, side by side in one batch. Measured on the
# development cases, CMA-ES polish reached deeper basins than Nelder-Mead's, in batches four times as large.
FINALISTS = 4
DISTINCT = 0.3
LOCAL_SIGMA = 0.01
LOCAL_POPSIZE = 16
# On searches of STALL_GAINS gains or more, every polish but the last also stops once its best improved by less than
# POLISH_STALL (relative) over its last STALL_CALLS batch calls, and the search ends with a final polish of the best
# point to cma's own end (from the best point only: from the 4 best it cost a converged SCARA search 23,632 more
# episodes, 46 %, from the best alone 5,424, the same minimum). There a polish to cma's end takes most of the budget for
# little: on the Z1 (12 gains) the first DE run's polish took 133,760 of 200,000 episodes to go from 633.1 to 629.5,
# while a DE run over the wide box then found 536.3 in 14,352; on the Panda (14 gains) 63,200 episodes went from 0.7759
# to 0.7744, 0.1 % of it after the first 576. With the stall the Z1 came within 1 % of its best known, the Panda, the
# UR5 and the SCARA's own case as close or closer. On the paper's arm (6 gains) a polish that creeps on is often how the
# search reaches its deepest basin (shared case 1: 0.3726 with it, 0.3855 with the stall; `ddarm reproduce`'s minima up
# to 0.08 % higher), and the budget it would free went to runs that certified a shallower basin (shared case 4): it
# keeps the polish to cma's end.
STALL_GAINS = 8
POLISH_STALL = 1e-4
STALL_CALLS = 20
# On every search a polish whose best, and the best of the points it started from, lie more than SAME_BASIN above the
# search's best so far stops once, at the pace of its last STALL_CALLS batch calls, the budget left could not bring
# it down to that best: it falls behind. Its budget goes to the later runs. Measured on the 18 development searches
# of docs/performance.md (mean gap 2.60 % -> 1.98 %, none higher): on case 3 seed 2 the first DE run crept on with its
# polish for 85,000 episodes to 5.11, 4 % above a wide CMA-ES run's 4.92, and left the Nelder-Mead ends' polish 2,944;
# stopped, it left that polish 49,504, which reached 4.467. On case 4 the ends' polish crept for 42,000 episodes to
# 3.58 where the DE run had found 1.82; stopped at 4,608, it left them to a second DE run. The pace is that of its own
# points, not of the points it started from, which a polish from a narrow valley's floor takes calls to get below.
# A DE run's polish also ends each of its local runs that falls behind on its own: its finalists come from one
# population, most in basins beside the best one, and there each polished to cma's end took most of a DE run's
# episodes (29,000 of 36,000 on case 4) where the later runs could use them (the 18 searches: 1.98 % -> 1.72 %; the
# aside case seed 2 4.968 -> 4.780; one 0.05 % higher). The Nelder-Mead ends' polish keeps its runs: its finalists
# lie in different valleys, and one far behind may be the one that creeps down to the deepest basin (dropped, case 2
# ended up to 0.5 % higher and the aside case seed 0 0.8 %).
# Nelder-Mead from the ω-rule starts: simplices of edge START_STEP in log gain, on at most START_SHARE of the budget
# (so that a small budget leaves room for the global runs). Not restarted: on the shared cases the restarts (from
# the best vertex, up to 8 while they improved) took half of the search's time and found no basin the first simplices
# had not (the deepest basins of cases 2 and 10 are found by single starts' first simplices). Most simplices on these
# rough landscapes never meet NM_XTOL and run to NM_EVALUATIONS, one point or so per batch each once the others have
# ended: the longest of the runs side by side. Half as many points made the search up to 30 % faster and as good on
# the shared cases, but on a case kept aside the polish of the shorter simplices' ends stopped 4.5 % higher (5.094
# against 4.875; PD + gravity, trajectory 2, T 1 s, Δ 0.01 s, d 1, I1).
START_STEP = 0.5
START_SHARE = 0.3
# The simplices' ends are then polished, like a DE run's: local CMA-ES runs from the phase's FINALISTS best distinct
# points, with σ0 POLISH_SIGMA, on at most POLISH_SHARE of the budget left. On the rough PD + gravity cases a
# simplex stops in a narrow valley that leads on to the deepest basin: polished, the shared cases 2 and 3 reached
# 20.73 and 4.755 (best known 21.53 and 4.900), where every DE run had stopped at 24.65 and 5.098. σ0 = 0.1 went
# further and in fewer episodes than 0.01 (20.49 in 55,000 against 20.75 in 74,000 on case 2). Such a polish creeps on
# down its valley for as long as it may: on half the budget left it ended on its share on cases 2 and 3 still
# improving, while the later DE runs it left room for ended in a basin already found. On 95 %, seeds 0, 1, 2: case 2
# 20.66, 20.57, 20.60 against 20.89, 20.83, 20.82; case 3 4.438, 4.513, 4.919 against 4.566, 4.752, 4.919; case 1
# 0.3726, 0.3777, 0.3774 against 0.3726, 0.3764, 0.3771; the others within 0.04 %; on a case not used to choose it (PD
# + gravity, trajectory 1, T 0.5 s, Δ 0.01 s, d 2, I) 14.886, 14.895 against 14.962, 15.042 (seeds 0, 1). Where a
# polish ends converged, the later runs keep the budget it leaves.
POLISH_SIGMA = 0.1
POLISH_SHARE = 0.95
# The wide CMA-ES runs: σ0 in log gain (a factor e^2 in every gain, so they reach basins far off the ω rules), and
# their end: CMA_XTOL in log gain, cma's own criteria, or WIDE_EVALUATIONS points per searched gain and per member
# of cma's default population (a run of twice the population may take twice as many). CMA_XTOL ends the local
# polishes too: 10⁻⁵ (0.001 % in every gain) is far finer than the certificate's 0.5 %, and with 10⁻⁶ the converged
# polishes of the paper's arm spent a sixth of its default computed torque search on the last digits.
WIDE_SIGMA = 2.0
CMA_XTOL = 1e-5
WIDE_EVALUATIONS = 100
# The certificate. A run reached the best when its best index is within SAME_BASIN of it; the search has converged
# once AGREEING_RUNS runs, and at least AGREEING_SHARE of all runs, are within AGREEMENT of the best, after at least
# MIN_GLOBAL_RUNS DE and wide CMA-ES runs, and the runs since the best was first reached have spent as much as those
# before (Certificate.settled). On a rough landscape three of fifteen runs agreed on a basin 4 % above one that
# other runs found: a best that few runs reach has a small basin, and deeper small ones may remain unseen. Runs
# whose bests lie within AGREEMENT of each other are counted as one basin.
# Among the runs that agree there must be one from the ω-rule starts (a Nelder-Mead run, or the polish of their
# ends) and one global run: runs of one family share their biases (the DE runs their boxes, the wide CMA-ES runs their
# centre), and their agreement alone is weaker evidence. Measured on every converged search logged while choosing
# the settings (186 searches of 14 cases, several settings each): 174 ended within 0.5 % of the deepest any search
# found on their case, all with both families agreeing; 12 ended on shared case 4 in a basin 2.8 % above the needle
# an independent search found, 10 of them with only DE and wide CMA-ES runs agreeing (the current settings with
# --budget 200000 on every seed among them) and 2 with the polish of the Nelder-Mead ends there too. The rule stops
# the 10 and no other; it is no proof either (see docs/tuning.md).
SAME_BASIN = 0.01
AGREEMENT = 0.005
AGREEING_RUNS = 3
AGREEING_SHARE = 1 / 3
MIN_GLOBAL_RUNS = 2

class SearchError(DdarmError, ValueError):
    """A search specification that cannot be run."""


@dataclass(frozen=True)
class Restart:
    """One independent run of the global search: where it started, its population, what it found, why it stopped.

    A Nelder-Mead run from an ω-rule start has popsize 1 (one simplex); a DE run's population is DE's, its
    episodes and best include its polish.
    """

    start: str  # the run: its ω-rule start, or its DE or CMA-ES run's number
    popsize: int
    episodes: int
    index: float  # its best index, +inf if all its episodes diverged
    # Nelder-Mead's ('converged',) or ('budget',); DE's ('tol',) when its population agreed, else ('generations',);
    # cma's own stop criteria, or ('budget',); a polish's ('converged',), ('budget',), ('stalled',) or ('behind',)
    # (see _polish).
    stopped_by: tuple[str, ...]
    from_rule_starts: bool = False  # a Nelder-Mead run from an ω-rule start, or the polish of their ends


@dataclass(frozen=True)
class Certificate:
    """How sure the global search is of its minimum: every independent run's best and whether enough agree.

    `runs` are the runs' bests (+inf for a run that only diverged), `budget` the ceiling and `episodes` the spent,
    `global_runs` the DE and wide CMA-ES runs among them.
    """

    runs: tuple[Restart, ...]
    global_runs: int
    budget: int
    episodes: int
    # On searches of STALL_GAINS gains or more, the polish of the best point after the runs (not a run of its own,
    # so not counted in the agreement); None otherwise.
    final_polish: Restart | None = None

    @property
    def best(self) -> float:
        return min((run.index for run in self.runs), default=np.inf)

    def within(self, fraction: float, from_rule_starts: bool | None = None) -> int:
        """How many runs reached within `fraction` of the best (given `from_rule_starts`, of the runs from the ω-rule
        starts, or of the global runs)."""
        best = self.best
        return sum(1 for run in self.runs if np.isfinite(best) and run.index <= (1.0 + fraction) * best
                   and from_rule_starts in (None, run.from_rule_starts))

    @property
    def both_families(self) -> bool:
        """Whether the runs within AGREEMENT of the best include one from the ω-rule starts and one global run."""
        return self.within(AGREEMENT, from_rule_starts=True) > 0 and self.within(AGREEMENT, from_rule_starts=False) > 0

    @property
    def settled(self) -> bool:
        """Whether the runs since the first that reached the best (within AGREEMENT) spent at least as many episodes
        as it and those before it: the search doubled its effort without finding a deeper basin."""
        best = self.best
        if not np.isfinite(best):
            return False
        first = next(number for number, run in enumerate(self.runs) if run.index <= (1.0 + AGREEMENT) * best)
        return (sum(run.episodes for run in self.runs[first + 1:])
                >= sum(run.episodes for run in self.runs[:first + 1]))

    @property
    def required_runs(self) -> int:
        """How many runs must agree: AGREEING_RUNS, and at least AGREEING_SHARE of the runs."""
        return max(AGREEING_RUNS, int(np.ceil(AGREEING_SHARE * len(self.runs))))

    @property
    def converged(self) -> bool:
        return (self.global_runs >= MIN_GLOBAL_RUNS and self.within(AGREEMENT) >= self.required_runs
                and self.both_families and self.settled)

    def basins(self) -> list[tuple[float, int]]:
        """The runs' bests grouped, deepest first: (the group's best index, how many runs ended in it); a run
        within AGREEMENT of a group's best joins it."""
        groups: list[list] = []
        for index in sorted(run.index for run in self.runs if np.isfinite(run.index)):
            if groups and index <= (1.0 + AGREEMENT) * groups[-1][0]:
                groups[-1][1] += 1
            else:
                groups.append([index, 1])
        return [(index, count) for index, count in groups]

    def summary(self, hint: bool = True) -> str:
        """One line: converged, or not and (given `hint`) the `--budget` to try."""
        runs = f'{self.within(SAME_BASIN)} of {len(self.runs)} runs within 1 %'
        if self.converged:
            return (f'converged: {runs}, {self.within(AGREEMENT)} within 0.5 % of the best; '
                    f'{len(self.basins())} basins found')
        unsettled = '' if self.settled else '; the runs since the best was first reached spent less than those before'
        # The best run is within AGREEMENT of itself, so at most one family can be missing.
        family = ''.join(f'; no {name} within 0.5 %' for name, from_rule_starts in (
            ('run from the ω-rule starts', True), ('global run', False))
            if self.within(AGREEMENT) and not self.within(AGREEMENT, from_rule_starts))
        return (f'not converged: {runs} ({self.within(AGREEMENT)} within 0.5 %, {self.required_runs} needed, after '
                f'{self.global_runs} of at least {MIN_GLOBAL_RUNS} global runs{family}{unsettled})'
                + (f'; try --budget {2 * max(self.budget, self.episodes)}' if hint else ''))

    def to_dict(self) -> dict:
        """The JSON of `certificate`."""
        def entry(run: Restart) -> dict:
            return {'run': run.start, 'index': float(run.index) if np.isfinite(run.index) else None,
                    'episodes': run.episodes}
        return {
            'converged': self.converged, 'settled': self.settled, 'summary': self.summary(),
            'runs': [entry(run) for run in self.runs],
            'runs_within_1_percent': self.within(SAME_BASIN), 'runs_within_0_5_percent': self.within(AGREEMENT),
            'rule_start_runs_within_0_5_percent': self.within(AGREEMENT, from_rule_starts=True),
            'global_runs_within_0_5_percent': self.within(AGREEMENT, from_rule_starts=False),
            'required_runs': self.required_runs, 'global_runs': self.global_runs,
            'required_global_runs': MIN_GLOBAL_RUNS,
            'basins': [{'index': index, 'runs': count} for index, count in self.basins()],
            'final_polish': None if self.final_polish is None else entry(self.final_polish),
            'episodes': self.episodes, 'budget': self.budget,
        }


@dataclass(frozen=True)
class SearchResult:
    """The best gains found, and every episode evaluated on the way (in evaluation order).

    `index` is the best gains' value of the index named `index_name`, +inf if every episode diverged;
    history_index holds +inf for the diverged episodes. `batches` counts the batch calls. `restarts`
    are the global search's independent runs (empty for the other methods), `certificate` its verdict on them.
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
    certificate: Certificate | None = None  # the global search's

    @property
    def converged(self) -> bool | None:
        """Whether the global search's certificate holds; None for the other methods, which give none."""
        return None if self.certificate is None else self.certificate.converged

    def certainty(self, hint: bool = True) -> str:
        """One line on how sure the search is of its minimum, for every output that prints or writes it: the
        certificate's summary (`hint`: with the `--budget` to try, for a command that has that option), or, for the
        methods that give none, that the minimum is not certified."""
        if self.certificate is not None:
            return self.certificate.summary(hint)
        return (f'not certified: --method {self.method} runs no independent global runs to compare its minimum '
                'with, so a deeper basin may remain unseen; the default global search says how sure it is')

    def certainty_fields(self, hint: bool = True) -> dict:
        """`converged` and `certainty` (with `hint`, see certainty), as every JSON that reports a search gives them."""
        return {'converged': self.converged, 'certainty': self.certainty(hint)}

    def best_so_far(self) -> np.ndarray:
        """The best index after each episode: the optimiser's progress."""
        return np.minimum.accumulate(self.history_index)

    def restarts_within(self, fraction: float = SAME_BASIN) -> int:
        """How many independent runs reached within `fraction` of the best index: a confidence figure (0 without
        them)."""
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

    def history_points(self, since: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Every point simulated from batch `since` on, in log gain (P, 2n), and its index (+inf if it diverged)."""
        records = self.records[since:]
        if not records:
            return np.empty((0, 0)), np.empty(0)
        points = np.log(np.concatenate([np.concatenate([record[0], record[1]], axis=1) for record in records]))
        return points, np.concatenate([record[2] for record in records])

    def result(self, method: str, index_name: str, restarts: tuple[Restart, ...] = (),
               evolution_generations: int = 0, certificate: Certificate | None = None) -> SearchResult:
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
            restarts=restarts, evolution_generations=evolution_generations, certificate=certificate)


def omega_starts(template: EpisodeSpec, omegas) -> tuple[np.ndarray, np.ndarray]:
    """Start gains from section 2's ω rules for the template's controller at each ω: (kp, kv), each (S, n)."""
    pairs = [gains_from_omega(template, float(omega)) for omega in omegas]
    return np.array([kp for kp, _ in pairs]), np.array([kv for _, kv in pairs])


def other_law_starts(template: EpisodeSpec) -> np.ndarray:
    """The global search's further starts, in log gain: the other laws' ω rules at SEARCH_START_OMEGAS, applied to
    this template's arm (the rule of PD + gravity scales each joint by its inertia, that of computed torque does
    not; on some cases one law's optimum lies near the other's rule). A rule that gives gains outside GAIN_RANGE
    is left out."""
    points = []
    for controller in CONTROLLERS:
        if controller == template.controller:
            continue
        for omega in SEARCH_START_OMEGAS:
            try:
                kp, kv = gains_from_omega(replace(template, controller=controller), omega)
            except EpisodeError:
                continue
            gains = np.concatenate([kp, kv])
            if np.all((gains >= GAIN_RANGE[0]) & (gains <= GAIN_RANGE[1])):
                points.append(np.log(gains))
    return np.array(points).reshape(-1, 2 * len(arm_joints(template)[0]))


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
                 method: str = DEFAULT_METHOD, seed: int = 0, step: float = 0.5,
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
        method: 'global' (the default, DEFAULT_METHOD: independent runs of differential evolution, Nelder-Mead and
            CMA-ES until its certificate holds; see the module and _global), 'nelder-mead' (one simplex per start,
            advanced together) or 'cma' (CMA-ES from the best start).
        seed: the random draws of CMA-ES and of DE; Nelder-Mead is deterministic.
        step: the initial spread in log gain: Nelder-Mead's simplex edge, CMA-ES's σ0 (not used by
            'global': its Nelder-Mead takes START_STEP, its CMA-ES runs LOCAL_SIGMA and WIDE_SIGMA).
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
        restarts, generations, certificate = _global(objective, starts, other_law_starts(template), seed,
                                                     DE_POPSIZE if popsize is None else int(popsize))
        return objective.result(method, index, restarts, generations, certificate)
    if method == 'nelder-mead':
        _run_alone(objective, _nelder_mead(_Allowance(objective), starts, step))
    else:
        _run_alone(objective, _cma(_Allowance(objective), starts, step, seed, popsize))
    return objective.result(method, index)


def check_search(template: EpisodeSpec, *, index: str, start_kp, start_kv, budget: int,
                 method: str = DEFAULT_METHOD, step: float = 0.5, popsize: int | None = None,
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
    minimum = least_budget(method, len(starts), starts.shape[1])
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < minimum * count:
        raise SearchError(f'budget must be a whole number of at least {minimum * count} episodes '
                          f'(the starts{" and their simplices" if method == "nelder-mead" else ""}'
                          f'{" and the other law’s ω-rule starts" if method == "global" else ""}'
                          f'{f", each on {count} scenarios" if count > 1 else ""}), got {budget!r}')
    return starts


def least_budget(method: str, starts: int, dimension: int) -> int:
    """The fewest episodes (per scenario) a search of `method` from `starts` starts over `dimension` log gains runs:
    the starts, and for Nelder-Mead their simplices; the global search adds the other laws' ω-rule starts (and does
    what the rest allows, its certificate saying whether that was enough)."""
    if method == 'nelder-mead':
        return starts * (dimension + 1)
    if method == 'global':
        return starts + len(SEARCH_START_OMEGAS) * (len(CONTROLLERS) - 1)
    return starts


def search_box(starts: np.ndarray, spread: float = GAIN_SPREAD) -> tuple[np.ndarray, np.ndarray]:
    """The box (low, high) in log gain that the global search's differential evolution samples.

    The starts' own span widened by OMEGA_SPAN in ω (so OMEGA_SPAN² in k_p, which the ω rules
    make grow as ω², and OMEGA_SPAN in k_v, as ω) and by a factor e^{±spread} in every gain.
    """
    dof = starts.shape[1] // 2
    widening = np.concatenate([np.full(dof, 2.0), np.ones(dof)]) * np.log(OMEGA_SPAN) + spread
    low = np.maximum(starts.min(axis=0) - widening, np.log(GAIN_RANGE[0]))
    return low, np.minimum(starts.max(axis=0) + widening, np.log(GAIN_RANGE[1]))


def cma_options(rng, popsize: int | None = None, tolx: float | None = None, bounded: bool = True) -> dict:
    """cma's options for a search over log gains: within GAIN_RANGE (unless not `bounded`), draws from `rng`, silent;
    cma's defaults unless given."""
    options = {
        # Draws from a private generator: NaN keeps cma from seeding NumPy's global one.
        'randn': lambda *shape: rng.standard_normal(shape), 'seed': np.nan,
        'verbose': -9, 'verb_log': 0, 'verb_disp': 0,
    }
    if bounded:
        options['bounds'] = [np.log(GAIN_RANGE[0]), np.log(GAIN_RANGE[1])]
    if popsize is not None:
        options['popsize'] = int(popsize)
    if tolx is not None:
        options['tolx'] = tolx
    return options


class _BudgetEnded(Exception):
    """Thrown into a run whose points the budget left has no room for: the run ends there."""


class _Allowance:
    """One run's or phase's share of the budget: at most `points` more points (None: all the objective has left),
    never more than the objective has left; keeps the points evaluated through it and their values, for a polish
    to pick its finalists from."""

    def __init__(self, objective: _Objective, points: int | None = None) -> None:
        self.objective, self.limit, self.spent = objective, points, 0
        self.points: list[np.ndarray] = []
        self.values: list[np.ndarray] = []

    @property
    def remaining(self) -> int:
        left = self.objective.remaining
        return left if self.limit is None else min(left, self.limit - self.spent)

    @property
    def episodes(self) -> int:
        return self.spent * len(self.objective.scenarios)

    def evaluate(self, points: np.ndarray):
        """Yield `points` to the scheduler (_side_by_side) and return their values."""
        values = yield points
        self.spent += len(points)
        self.points.append(points)
        self.values.append(values)
        return values

    def history(self, known: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The points evaluated through it, after `known` ones, and their indices (+inf where they diverged)."""
        points = ([] if known is None else [known[0]]) + self.points
        values = np.concatenate(([] if known is None else [known[1]]) + self.values) if points else np.empty(0)
        return (np.concatenate(points) if points else np.empty((0, 0)),
                np.where(values < DIVERGED_PENALTY, values, np.inf))


def _side_by_side(objective: _Objective, runs: list) -> list:
    """Drive `runs` together and return what each returned.

    A run is a generator that yields the points it wants evaluated (through its _Allowance) and is sent their
    values. Each round is one batch call of every running run's points, so that runs of a few points each (the
    Nelder-Mead simplices, the local CMA-ES polishes) fill the engine's SIMD lanes and threads beside a DE
    population instead of each paying for a batch call of its own. A run's episodes are those of its batch of one
    (each member of a batch is simulated alone), so each run finds what it would alone. The runs are served in
    their order: one whose points do not fit in the budget the runs before it left is ended (_BudgetEnded).
    """
    results: list = [None] * len(runs)
    asked: list[np.ndarray | None] = [None] * len(runs)

    def advance(number: int, values: np.ndarray | None = None, ended: bool = False) -> None:
        try:
            asked[number] = runs[number].throw(_BudgetEnded()) if ended else runs[number].send(values)
        except StopIteration as finished:
            asked[number], results[number] = None, finished.value

    try:
        for number in range(len(runs)):
            advance(number)
        while any(points is not None for points in asked):
            room, batch = objective.remaining, []
            for number, points in enumerate(asked):
                if points is None:
                    continue
                if len(points) <= room:
                    batch.append(number)
                    room -= len(points)
                else:
                    advance(number, ended=True)
            if not batch:
                continue
            values = objective(np.concatenate([asked[number] for number in batch]))
            ends = np.cumsum([len(asked[number]) for number in batch])
            for number, start, end in zip(batch, np.concatenate([[0], ends[:-1]]), ends):
                advance(number, values[start:end])
    finally:
        for run in runs:
            run.close()
    return results


def _run_alone(objective: _Objective, run):
    """What one run returns, driven alone."""
    return _side_by_side(objective, [run])[0]


def _finite(value: float) -> float:
    """An objective value as a run's index: +inf for a divergence penalty."""
    return float(value) if value < DIVERGED_PENALTY else np.inf


def _distinct_best(points: np.ndarray, values: np.ndarray, count: int) -> list[int]:
    """The positions of the `count` best finite values whose points lie at least DISTINCT apart in some log gain."""
    chosen: list[int] = []
    for member in np.argsort(values, kind='stable'):
        if not np.isfinite(values[member]) or len(chosen) == count:
            break
        if all(np.max(np.abs(points[member] - points[other])) > DISTINCT for other in chosen):
            chosen.append(int(member))
    return chosen


def _members(popsize: int, dimension: int) -> int:
    """A DE run's population: scipy's own size."""
    return max(5, popsize * dimension)


def _generations(remaining: int, members: int) -> int:
    """The most generations of a DE run of `members` on DE_SHARE of `remaining` points after its first population."""
    return min(DE_GENERATIONS, int(DE_SHARE * remaining) // members - 1)


def _evolution_room(objective: _Objective, popsize: int, dimension: int) -> bool:
    """Whether a DE run has room for two generations in the budget left."""
    return _generations(objective.remaining, _members(popsize, dimension)) >= 1


def _evolution(objective: _Objective, box: tuple[np.ndarray, np.ndarray], popsize: int, rng, name: str,
               x0: np.ndarray | None = None, known: tuple[np.ndarray, np.ndarray] | None = None,
               stall: float | None = None):
    """One DE run over `box` from `rng`'s draws (with `x0` among its first members, if given) on at most DE_SHARE of
    the budget left, polished (see _polish, with `stall`) by local CMA-ES runs from the FINALISTS best distinct points
    among its own and the `known` ones (points, values). A run (see _side_by_side) that returns (its Restart, its
    generations), or None if the budget has no room for two of its generations.

    DE (scipy's: best1bin, Latin hypercube initialisation) evaluates its whole population (popsize × 2n members)
    as one batch per generation. The indices sum |e| and |P - P^nom| over the samples, so they have a kink
    wherever a sample's error or torque deviation changes sign: their landscape is rough, with local minima close
    together, and a population that samples the whole box finds deep ones that a local search from the ω rules
    misses.
    """
    low, high = box
    members = _members(popsize, len(low))
    allowance = _Allowance(objective)
    generations = _generations(allowance.remaining, members)
    if generations < 1:
        return None
    # scipy's DE calls its objective and has no ask/tell interface: it runs in a thread of its own, handing each
    # population over and waiting for its values, so that its batches can be shared with other runs.
    populations, answers = queue.SimpleQueue(), queue.SimpleQueue()

    def handed_over(population: np.ndarray) -> np.ndarray:
        populations.put(population.T)
        values = answers.get()
        if values is None:
            raise _BudgetEnded
        return values

    def solve() -> None:
        try:
            outcome = scipy.optimize.differential_evolution(
                handed_over, list(zip(low, high)), vectorized=True, updating='deferred', popsize=popsize,
                maxiter=generations, tol=DE_TOL, polish=False, x0=x0, rng=rng)
        except BaseException as error:  # handed to the run, which raises it where the search can report it
            outcome = error
        populations.put(outcome)

    solver = threading.Thread(target=solve, name=name, daemon=True)
    solver.start()
    best, asked = np.inf, 0
    try:
        while isinstance(request := populations.get(), np.ndarray):
            try:
                values = yield from allowance.evaluate(request)
            except _BudgetEnded:
                answers.put(None)
                request = populations.get()
                break
            asked += 1
            best = min(best, _finite(float(values.min())))
            answers.put(values)
    finally:
        if solver.is_alive():
            answers.put(None)
            solver.join()
    if isinstance(request, BaseException) and not isinstance(request, _BudgetEnded):
        raise request
    if isinstance(request, scipy.optimize.OptimizeResult):
        stopped_by, ran = ('tol',) if request.success else ('generations',), int(request.nit)
    else:
        stopped_by, ran = ('budget',), max(0, asked - 1)
    polish = _Allowance(objective)
    polished, _ = yield from _polish(polish, *allowance.history(known), rng, stall=stall, drop_runs_behind=True)
    return Restart(name, members, allowance.episodes + polish.episodes, min(best, polished), stopped_by), ran


def _polish(allowance: _Allowance, points: np.ndarray, values: np.ndarray, rng, sigma: float = LOCAL_SIGMA,
            stall: float | None = None, finalists: int = FINALISTS, drop_runs_behind: bool = False):
    """Local CMA-ES runs (σ0 = `sigma`, population LOCAL_POPSIZE) from the `finalists` best distinct `points` (by
    their `values`), their populations side by side in one batch, until cma stops each or the budget ends them
    (the last first), or, given `stall`, once their best improved by less than that fraction over the last
    STALL_CALLS batches, or once it falls behind the search's best (see STALL_CALLS); given `drop_runs_behind`, each
    local run also ends once it falls behind on its own. A run (see _side_by_side) that returns its best index and why
    it stopped: ('converged',), ('budget',), ('stalled',) or ('behind',)."""
    import cma  # see _cma

    chosen = _distinct_best(points, values, finalists)
    start = min(values[chosen], default=np.inf)
    # Unbounded: a local run stays far inside GAIN_RANGE, and cma's bound transformation took a third of its time;
    # a point outside would score as a divergence. Each run keeps its start's value and its best after each batch.
    runs = [(cma.CMAEvolutionStrategy(points[member], sigma, cma_options(rng, LOCAL_POPSIZE, CMA_XTOL, bounded=False)),
             float(values[member]), [])
            for member in chosen[:max(1, allowance.remaining // LOCAL_POPSIZE)]]
    best, bests, sizes, dropped, converged = np.inf, [], [], False, False
    while runs:
        while runs and LOCAL_POPSIZE * len(runs) > allowance.remaining:
            runs.pop()
        if not runs:
            break
        populations = [run.ask() for run, _, _ in runs]
        try:
            values = yield from allowance.evaluate(np.concatenate([np.array(population) for population in populations]))
        except _BudgetEnded:
            return best, ('budget',)
        best = min(best, _finite(float(values.min())))
        bests.append(best)
        sizes.append(len(values))
        if _behind(allowance, bests, start, sum(sizes[-STALL_CALLS:])):
            return best, ('behind',)
        if (stall is not None and len(bests) > STALL_CALLS and np.isfinite(best)
                and bests[-1 - STALL_CALLS] - best <= stall * abs(best)):
            return best, ('stalled',)
        going = []
        for (run, run_start, run_bests), population, run_values in zip(runs, populations, np.split(values, len(runs))):
            run.tell(population, run_values.tolist())
            run_bests.append(min(run_bests[-1] if run_bests else np.inf, _finite(float(run_values.min()))))
            if drop_runs_behind and _behind(allowance, run_bests, run_start, STALL_CALLS * LOCAL_POPSIZE):
                dropped = True
            elif run.stop():
                converged = True
            else:
                going.append((run, run_start, run_bests))
        runs = going
    if allowance.remaining < LOCAL_POPSIZE:
        return best, ('budget',)
    return best, ('behind',) if dropped and not converged else ('converged',)


def _behind(allowance: _Allowance, bests: list[float], start: float, points: int) -> bool:
    """Whether a polish, or one of its runs, whose best after each of its batch calls was `bests`, which started from
    points whose best was `start`, and which evaluated `points` points in its last STALL_CALLS calls, has fallen
    behind: more than SAME_BASIN above the search's best, and unable to get there at that pace on the budget left.
    Not before it has made STALL_CALLS calls."""
    if len(bests) <= STALL_CALLS:
        return False
    best, gained, lead = bests[-1], bests[-1 - STALL_CALLS] - bests[-1], allowance.objective.best_value
    reached = min(best, start)
    if not (np.isfinite(reached) and lead < DIVERGED_PENALTY and reached > (1.0 + SAME_BASIN) * lead):
        return False
    return not (np.isfinite(best) and gained > 0) or (best - lead) / gained * points > allowance.remaining


def _wide_cma(objective: _Objective, centre: np.ndarray, popsize: int, rng, name: str):
    """One CMA-ES run from `centre` with σ0 = WIDE_SIGMA and population `popsize`, until cma stops it or its share
    (WIDE_EVALUATIONS) has no room for its next population. A run (see _side_by_side) that returns its Restart, or
    None if the budget has no room for two populations."""
    import cma  # see _cma

    allowance = _Allowance(objective, WIDE_EVALUATIONS * len(centre) * popsize)
    if 2 * popsize > allowance.remaining:
        return None
    strategy = cma.CMAEvolutionStrategy(centre, WIDE_SIGMA, cma_options(rng, popsize, CMA_XTOL))
    best, stopped_by = np.inf, ()
    while not strategy.stop() and popsize <= allowance.remaining:
        population = strategy.ask()
        try:
            values = yield from allowance.evaluate(np.array(population))
        except _BudgetEnded:
            stopped_by = ('budget',)
            break
        strategy.tell(population, values.tolist())
        best = min(best, _finite(float(values.min())))
    stopped_by = stopped_by or tuple(strategy.stop()) or ('budget',)
    return Restart(name, popsize, allowance.episodes, best, stopped_by)


def _simplices(objective: _Objective, starts: np.ndarray, values: np.ndarray, rng, stall: float | None):
    """Nelder-Mead from the best `starts` (their `values` known) that START_SHARE of the budget left has room for,
    each an independent run (the others keep their start's index), then the CMA-ES polish of their best distinct ends
    on at most POLISH_SHARE of the budget then left, with `rng`'s draws (a run only if that has room for a population).
    A run (see _side_by_side) that returns their Restarts."""
    phase = _Allowance(objective, int(START_SHARE * objective.remaining))
    taken = np.sort(np.argsort(values, kind='stable')[:phase.remaining // (starts.shape[1] + 1)])
    bests, converged, episodes = values.copy(), np.zeros(len(starts), dtype=bool), np.zeros(len(starts), dtype=int)
    if len(taken):
        found, converged[taken] = yield from _nelder_mead(phase, starts[taken], START_STEP)
        bests[taken] = np.minimum(values[taken], found)
        episodes[taken] = phase.episodes // len(taken)
    runs = [Restart(f'Nelder-Mead from ω-rule start {number + 1} ({values[number]:.6g})', 1, int(episodes[number]),
                    _finite(bests[number]), ('converged',) if converged[number] else ('budget',),
                    from_rule_starts=True)
            for number in range(len(starts))]
    if len(taken):
        polish = _Allowance(objective, int(POLISH_SHARE * objective.remaining))
        best, stopped_by = yield from _polish(polish, *phase.history(), rng, POLISH_SIGMA, stall)
        if polish.episodes:
            runs.append(Restart('CMA-ES polish of the Nelder-Mead runs', LOCAL_POPSIZE, polish.episodes, best,
                                stopped_by, from_rule_starts=True))
    return runs


def _global(objective: _Objective, own_starts: np.ndarray, other_starts: np.ndarray, seed: int,
            popsize: int) -> tuple[tuple[Restart, ...], int, Certificate]:
    """A differential evolution from the best start and Nelder-Mead from every start side by side, each then
    polished, then wide CMA-ES runs and further differential evolutions by turns, until the certificate holds or
    the budget has no room for the next run.

    The first DE run (over the box of the law's own starts, the best of them among its members, its draws seeded
    by `seed`, on DE_SHARE of the budget) is the strongest single run measured on the paper's cases; the other law's
    starts join the Nelder-Mead. Each start's Nelder-Mead is one independent run; so is the polish of their ends
    (with draws of its own), each DE run with its polish and each wide CMA-ES run, the later ones each from their own
    draws (seeded by `seed` and their number). The CMA-ES runs start from the best start with WIDE_SIGMA and double
    their population run after run (IPOP-CMA-ES). On searches of STALL_GAINS gains or more every polish stops once it
    creeps, and the search ends with a final polish of its best point (drawing on after the first DE run's polish),
    its result in the certificate's final_polish. Returns the runs, DE's generations in all, and the certificate.
    """
    budget = objective.budget * len(objective.scenarios)
    starts = np.vstack([own_starts, other_starts])
    values = objective(starts)
    centre = starts[int(np.argmin(values))]
    first_draws = np.random.default_rng(seed)  # the first DE run's, then its polish's, then the final polish's
    stall = POLISH_STALL if starts.shape[1] >= STALL_GAINS else None
    cma_popsize = 4 + int(3 * np.log(starts.shape[1]))  # cma's default
    best_own = own_starts[int(np.argmin(values[:len(own_starts)]))]
    first = [_evolution(objective, search_box(own_starts), popsize, first_draws,
                        'differential evolution 1, from the best start', x0=best_own, known=(starts, values),
                        stall=stall),
             _simplices(objective, starts, values, np.random.default_rng([seed, 0, 1]), stall)]
    # The first wide CMA-ES run joins them when DE has room (it would come next, and most searches that converge do
    # so after it); its draws are those it would have after them.
    if _evolution_room(objective, popsize, starts.shape[1]):
        first.append(_wide_cma(objective, centre, cma_popsize, np.random.default_rng([seed, 1]), 'wide CMA-ES 1'))
    evolution, simplices, *widened = _side_by_side(objective, first)
    widened = [run for run in widened if run is not None]
    runs = ([] if evolution is None else [evolution[0]]) + simplices + widened
    generations = 0 if evolution is None else evolution[1]
    evolutions, wide = (0 if evolution is None else 1), len(widened)  # the DE runs and wide CMA-ES runs done
    while True:
        certificate = Certificate(tuple(runs), evolutions + wide, budget, objective.evaluations)
        if certificate.converged:
            break
        draws = np.random.default_rng([seed, evolutions + wide])
        if wide >= evolutions:
            evolution = _run_alone(objective, _evolution(
                objective, search_box(starts, WIDE_GAIN_SPREAD), popsize, draws,
                f'differential evolution {evolutions + 1}', stall=stall))
            if evolution is None:
                break
            run, ran = evolution
            generations += ran
            evolutions += 1
        else:
            run = _run_alone(objective, _wide_cma(objective, centre, cma_popsize * 2 ** wide, draws,
                                                  f'wide CMA-ES {wide + 1}'))
            if run is None:
                break
            wide += 1
        runs.append(run)
    if stall is not None:
        polish = _Allowance(objective)
        best, stopped_by = _run_alone(objective, _polish(polish, *objective.history_points(0), first_draws,
                                                         finalists=1))
        certificate = replace(certificate, episodes=objective.evaluations, final_polish=Restart(
            'final CMA-ES polish of the best point', LOCAL_POPSIZE, polish.episodes, best, stopped_by))
    return tuple(runs), generations, certificate


def _cma(allowance: _Allowance, starts: np.ndarray, step: float, seed: int, popsize: int | None):
    """CMA-ES (the `cma` package) from the best start, one batch per population: a run (see _side_by_side)."""
    # Imported here, not at the top: cma (with scipy.stats) takes 1.5 to 2 s that most commands need not wait.
    import cma

    values = yield from allowance.evaluate(starts)
    rng = np.random.default_rng(seed)
    strategy = cma.CMAEvolutionStrategy(starts[int(np.argmin(values))], step, cma_options(rng, popsize))
    while not strategy.stop() and strategy.popsize <= allowance.remaining:
        population = strategy.ask()
        try:
            strategy.tell(population, (yield from allowance.evaluate(np.array(population))).tolist())
        except _BudgetEnded:
            return


# The stages of a Nelder-Mead iteration, each simplex at its own: its reflected point, then (unless the reflection
# was accepted) the expansion or contraction, then (if that failed) the shrink of every vertex but the best.
_REFLECT, _TRIAL, _SHRINK = 0, 1, 2
_EXPAND, _OUTSIDE, _INSIDE = 0, 1, 2


def _nelder_mead(allowance: _Allowance, starts: np.ndarray, step: float):
    """Nelder-Mead (standard coefficients 1, 2, 1/2, 1/2) from every start at once: a run (see _side_by_side) that
    returns each start's best value and whether it ended converged (False: the budget or NM_EVALUATIONS ended it
    first).

    scipy's Nelder-Mead asks for one point at a time, so it cannot batch the starts; here each simplex goes through
    the stages of its iterations (the reflection; the expansion or contraction; the shrink) at its own pace, and
    every simplex's next stage is in one batch. Evaluating all four candidates at once would make an iteration one
    stage but would about double the episodes.
    """
    count, dimension = starts.shape
    converged = np.zeros(count, dtype=bool)
    if count * (dimension + 1) > allowance.remaining:
        return np.full(count, np.inf), converged
    simplex = starts[:, None, :] + np.concatenate([np.zeros((1, dimension)), step * np.eye(dimension)])[None]
    try:
        values = (yield from allowance.evaluate(simplex.reshape(-1, dimension))).reshape(count, dimension + 1)
    except _BudgetEnded:
        return np.full(count, np.inf), converged
    evaluated = np.full(count, dimension + 1)
    active = np.ones(count, dtype=bool)
    stage, move = np.full(count, _REFLECT), np.zeros(count, dtype=int)
    centroid, reflected, trial = np.empty((3, count, dimension))
    reflected_value = np.empty(count)
    shrunk = np.empty((count, dimension, dimension))
    while True:
        # A simplex starting an iteration: ordered, and ended once it has converged or spent its evaluations.
        starting = np.flatnonzero(active & (stage == _REFLECT))
        order = np.argsort(values[starting], axis=1, kind='stable')
        simplex[starting] = np.take_along_axis(simplex[starting], order[:, :, None], axis=1)
        values[starting] = np.take_along_axis(values[starting], order, axis=1)
        spread = np.max(np.abs(simplex[starting, 1:] - simplex[starting, :1]), axis=(1, 2))
        agreement = (np.max(np.abs(values[starting, 1:] - values[starting, :1]), axis=1)
                     <= NM_FTOL * np.abs(values[starting, 0]))
        settled = (spread <= NM_XTOL) & agreement
        converged[starting[settled]] = True
        active[starting[settled | (evaluated[starting] >= NM_EVALUATIONS * dimension)]] = False
        reflecting = np.flatnonzero(active & (stage == _REFLECT))
        trying = np.flatnonzero(active & (stage == _TRIAL))
        shrinking = np.flatnonzero(active & (stage == _SHRINK))
        centroid[reflecting] = simplex[reflecting, :-1].mean(axis=1)
        reflected[reflecting] = 2.0 * centroid[reflecting] - simplex[reflecting, -1]
        points = np.concatenate([reflected[reflecting], trial[trying], shrunk[shrinking].reshape(-1, dimension)])
        if len(points) == 0 or len(points) > allowance.remaining:
            break
        try:
            asked = yield from allowance.evaluate(points)
        except _BudgetEnded:
            break
        reflected_at, tried_at = asked[:len(reflecting)], asked[len(reflecting):len(reflecting) + len(trying)]
        shrunk_at = asked[len(reflecting) + len(trying):].reshape(len(shrinking), dimension)
        # The reflections: accepted between the best and the second worst, else an expansion or a contraction.
        rows = reflecting
        expand = reflected_at < values[rows, 0]
        accept = ~expand & (reflected_at < values[rows, -2])
        outside = ~expand & ~accept & (reflected_at < values[rows, -1])
        evaluated[rows] += 1
        simplex[rows[accept], -1], values[rows[accept], -1] = reflected[rows[accept]], reflected_at[accept]
        reflected_value[rows] = reflected_at
        move[rows] = np.where(expand, _EXPAND, np.where(outside, _OUTSIDE, _INSIDE))
        trial[rows] = np.where(expand[:, None], centroid[rows] + 2.0 * (reflected[rows] - centroid[rows]),
                               np.where(outside[:, None], centroid[rows] + 0.5 * (reflected[rows] - centroid[rows]),
                                        centroid[rows] + 0.5 * (simplex[rows, -1] - centroid[rows])))
        stage[rows[~accept]] = _TRIAL
        # The expansions and contractions: the better of trial and reflection replaces the worst vertex, or a
        # contraction that failed shrinks the simplex towards its best vertex.
        rows = trying
        evaluated[rows] += 1
        kind, worst = move[rows], values[rows, -1]
        take_trial = (((kind == _EXPAND) & (tried_at < reflected_value[rows]))
                      | ((kind == _OUTSIDE) & (tried_at <= reflected_value[rows]))
                      | ((kind == _INSIDE) & (tried_at < worst)))
        shrink = ((kind == _OUTSIDE) & (tried_at > reflected_value[rows])) | ((kind == _INSIDE) & (tried_at >= worst))
        keep = rows[~shrink]
        simplex[keep, -1] = np.where(take_trial[~shrink, None], trial[keep], reflected[keep])
        values[keep, -1] = np.where(take_trial[~shrink], tried_at[~shrink], reflected_value[keep])
        stage[keep] = _REFLECT
        contracted = rows[shrink]
        shrunk[contracted] = simplex[contracted, :1] + 0.5 * (simplex[contracted, 1:] - simplex[contracted, :1])
        stage[contracted] = _SHRINK
        # The shrinks.
        simplex[shrinking, 1:], values[shrinking, 1:] = shrunk[shrinking], shrunk_at
        evaluated[shrinking] += dimension
        stage[shrinking] = _REFLECT
    return values.min(axis=1), converged
