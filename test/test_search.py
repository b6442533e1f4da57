"""The gain searches (spec §9): they improve on their starts, are deterministic, and never prefer a divergence."""

from dataclasses import replace

import numpy as np
import pytest

from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning import search
from ddarm.tuning.search import SearchError, omega_starts, search_gains
from reference_episode import reference_episode
from test_arms import example_spec

CT = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, delay=1)
PD = EpisodeSpec(controller='pd_gravity', kp=(2800.0, 2700.0, 350.0), kv=(560.0, 540.0, 70.0), delay=0)


@pytest.mark.parametrize('method', ['global', 'nelder-mead', 'cma'])
@pytest.mark.parametrize('index, key', [('I1', 'I1'), ('I', 'I')])
def test_a_small_search_improves_on_its_best_start(method, index, key):
    kp, kv = omega_starts(CT, [10.0, 15.0])
    budget = 1000 if method == 'global' else 120  # DE needs a few generations of 15 x 2n members
    result = search_gains(CT, index=index, start_kp=kp, start_kv=kv, budget=budget, method=method, seed=3)
    start = min(run_episode(EpisodeSpec(controller='computed_torque', kp=p, kv=v, delay=1)).indices()[key]
                for p, v in zip(kp, kv))
    assert result.index < 0.9 * start
    assert result.episodes == len(result.history_index) <= budget
    assert result.index == pytest.approx(np.min(result.history_index))
    assert np.all(np.diff(result.best_so_far()) <= 0)
    # The best gains are an episode that scores what the search says (in the independent reference loop).
    found = reference_episode(EpisodeSpec(controller='computed_torque', kp=result.kp, kv=result.kv, delay=1))
    assert found.indices[key] == pytest.approx(result.index, rel=1e-9)


@pytest.mark.parametrize('method', ['global', 'nelder-mead', 'cma'])
def test_a_search_is_a_pure_function_of_its_arguments(method):
    kp, kv = omega_starts(PD, [5.0, 10.0])
    runs = []
    for global_seed in (1, 2):
        # Nothing else drawing from NumPy's global generator changes the search.
        np.random.seed(global_seed)
        runs.append(search_gains(PD, index='I', start_kp=kp, start_kv=kv, budget=60, method=method, seed=7))
    np.testing.assert_array_equal(runs[0].history_kp, runs[1].history_kp)
    np.testing.assert_array_equal(runs[0].history_index, runs[1].history_index)
    assert runs[0].index == runs[1].index


def test_the_cma_seed_changes_the_draws():
    kp, kv = omega_starts(CT, [15.0])
    first, second = (search_gains(CT, index='I1', start_kp=kp, start_kv=kv, budget=30, method='cma', seed=seed)
                     for seed in (1, 2))
    assert not np.array_equal(first.history_kp, second.history_kp)


@pytest.mark.parametrize('method', ['global', 'nelder-mead', 'cma'])
def test_a_diverged_episode_never_looks_good(method):
    # Diverged at sample 3, this episode's partial (2.5) is far below that of any stable gains.
    diverging_kp, diverging_kv = np.full(3, 1e7), np.full(3, 10.0)
    partial = run_episode(EpisodeSpec(controller='pd_gravity', kp=diverging_kp, kv=diverging_kv, delay=0))
    stable = run_episode(PD)
    assert partial.diverged[0] and partial.indices()['I1'] < 0.1 * stable.indices()['I1']
    result = search_gains(PD, index='I1', start_kp=[PD.kp, diverging_kp], start_kv=[PD.kv, diverging_kv],
                          budget=200 if method == 'global' else 40, method=method)
    assert np.isinf(result.history_index).any()
    assert np.isfinite(result.index) and result.index <= stable.indices()['I1']
    assert not np.allclose(result.kp, diverging_kp)


@pytest.mark.parametrize('change, problem', [
    (dict(index='2.6'), 'index'),
    (dict(method='simplex'), 'method'),
    (dict(budget=5), 'budget'),
    (dict(budget=100.0), 'budget'),
    (dict(start_kp=[[225.0] * 3], start_kv=[[30.0] * 2]), 'shape'),
    (dict(start_kp=[[225.0, -1.0, 225.0]], start_kv=[[30.0] * 3]), 'positive'),
    (dict(start_kp=[[225.0, 1e12, 225.0]], start_kv=[[30.0] * 3]), 'GAIN_RANGE'),
    (dict(step=0.0), 'step'),
    (dict(method='cma', popsize=1), 'popsize'),
])
def test_bad_searches_are_refused_with_the_problem_named(change, problem):
    arguments = dict(index='I1', start_kp=[[225.0] * 3], start_kv=[[30.0] * 3], budget=100, method='nelder-mead')
    with pytest.raises(SearchError, match=problem):
        search_gains(CT, **{**arguments, **change})


def test_the_global_search_certifies_its_best_by_independent_runs_and_stops_once_they_agree():
    kp, kv = omega_starts(CT, [8.0, 15.0, 30.0])
    ceiling = 100_000
    result = search_gains(CT, index='I', start_kp=kp, start_kv=kv, budget=ceiling, method='global', seed=1)
    certificate = result.certificate
    kinds = [run.start.split(' ')[0] for run in result.restarts]
    # DE from the best start, Nelder-Mead from the three starts and from the other law's five ω-rule starts, then
    # global runs of both kinds.
    assert kinds[:9] == ['differential'] + ['Nelder-Mead'] * 8 and 'wide' in kinds[9:]
    assert certificate.runs == result.restarts and sum(run.episodes for run in result.restarts) <= result.episodes
    assert result.index == pytest.approx(np.min(result.history_index))
    assert result.index == pytest.approx(min(run.index for run in result.restarts), rel=1e-12)
    # Computed torque on the paper's trajectory has one deep basin: the runs agree, and the search stops early.
    agreeing = sum(run.index <= 1.005 * result.index for run in result.restarts)
    assert result.converged and agreeing >= 3 and certificate.within(0.005) == agreeing
    assert result.episodes < 0.75 * ceiling and certificate.episodes == result.episodes
    assert certificate.summary().startswith('converged: ')
    as_json = certificate.to_dict()
    assert as_json['converged'] is True and as_json['runs_within_0_5_percent'] == agreeing
    assert as_json['rule_start_runs_within_0_5_percent'] >= 1 and as_json['global_runs_within_0_5_percent'] >= 1
    # 6 gains: every polish runs to cma's end, and there is no final one.
    assert certificate.final_polish is None and as_json['final_polish'] is None
    assert sum(basin['runs'] for basin in as_json['basins']) == sum(np.isfinite(r.index) for r in result.restarts)
    assert as_json['basins'][0]['index'] == pytest.approx(result.index)
    # The independent reference loop, whose different order of sums parts from the engine's by ~1e-8.
    found = reference_episode(EpisodeSpec(controller='computed_torque', kp=result.kp, kv=result.kv, delay=1))
    assert found.indices['I'] == pytest.approx(result.index, rel=1e-7)


@pytest.mark.parametrize('budget', [100, 2000])
def test_a_budget_too_small_says_not_converged_and_never_claims_convergence(budget):
    kp, kv = omega_starts(PD, [5.0, 10.0, 20.0])
    result = search_gains(PD, index='I', start_kp=kp, start_kv=kv, budget=budget, method='global', seed=1)
    assert result.converged is False and result.episodes <= budget
    summary = result.certificate.summary()
    assert summary.startswith('not converged: ') and f'try --budget {2 * budget}' in summary
    assert result.certificate.to_dict()['converged'] is False
    # A polish the budget left no room for is no run of the certificate.
    assert all(run.episodes > 0 for run in result.restarts if 'polish' in run.start)


def test_the_other_methods_give_no_certificate():
    kp, kv = omega_starts(CT, [15.0])
    result = search_gains(CT, index='I', start_kp=kp, start_kv=kv, budget=60, method='nelder-mead')
    assert result.certificate is None and result.converged is None


class _Bowl:
    """A stand-in for the search's objective: 1 + |x|^2 over log gains, its points and values kept."""

    scenarios = (None,)

    def __init__(self, budget: int) -> None:
        self.remaining, self.calls, self.points, self.values = budget, 0, [np.full((1, 4), 0.3)], [np.array([1.36])]

    @staticmethod
    def value(points):
        return 1.0 + np.sum(points ** 2, axis=1)

    def __call__(self, points):
        values = self.value(np.asarray(points))
        self.remaining -= len(points)
        self.calls += 1
        self.points.append(np.asarray(points))
        self.values.append(values)
        return values

    def history_points(self, since=0):
        return np.concatenate(self.points[since:]), np.concatenate(self.values[since:])

    @property
    def best_value(self):
        return min(float(values.min()) for values in self.values)


def test_a_polish_given_a_stall_stops_once_its_best_creeps_and_otherwise_runs_to_cmas_end():
    stalled, full = _Bowl(100_000), _Bowl(100_000)

    def polish(bowl, stall=None):
        run = search._polish(search._Allowance(bowl), *bowl.history_points(), np.random.default_rng(0), 0.1, stall)
        return search._run_alone(bowl, run)

    best, stopped_by = polish(stalled, search.POLISH_STALL)
    assert stopped_by == ('stalled',) and polish(full)[1] == ('converged',)
    assert search.STALL_CALLS < stalled.calls < full.calls and full.remaining > 0
    # It stopped at the first call whose best had improved by less than the stall over the last STALL_CALLS calls.
    bests = np.minimum.accumulate([values.min() for values in stalled.values[1:]])
    assert best == bests[-1] and bests[-1 - search.STALL_CALLS] - best <= search.POLISH_STALL * best
    assert all(bests[call - search.STALL_CALLS] - bests[call] > search.POLISH_STALL * bests[call]
               for call in range(search.STALL_CALLS, len(bests) - 1))


class _LedBowl(_Bowl):
    """The bowl in a search whose best so far, found by another run, is `lead`."""

    def __init__(self, budget: int, lead: float) -> None:
        super().__init__(budget)
        self.lead = lead

    @property
    def best_value(self):
        return min(self.lead, super().best_value)


def test_a_polish_that_cannot_reach_the_searchs_best_at_its_pace_stops_behind_and_one_that_leads_goes_on():
    def polish(bowl):
        run = search._polish(search._Allowance(bowl), *bowl.history_points(), np.random.default_rng(0), 0.1)
        return search._run_alone(bowl, run)

    # The bowl's floor is 1: a run elsewhere at 0.5 cannot be reached, one at 1.005 is within SAME_BASIN of it.
    behind, within, alone = _LedBowl(100_000, 0.5), _LedBowl(100_000, 1.005), _Bowl(100_000)
    best, stopped_by = polish(behind)
    assert stopped_by == ('behind',) and polish(within)[1] == ('converged',) and polish(alone)[1] == ('converged',)
    assert search.STALL_CALLS < behind.calls < alone.calls == within.calls
    # It stopped at the first call from which, at the pace of its last STALL_CALLS calls, the budget left could not
    # bring its best down to the lead.
    bests = np.minimum.accumulate([values.min() for values in behind.values[1:]])
    spent = np.cumsum([len(points) for points in behind.points[1:]])

    def out_of_reach(call):
        gained = bests[call - search.STALL_CALLS] - bests[call]
        used = spent[call] - spent[call - search.STALL_CALLS]
        return gained <= 0 or (bests[call] - 0.5) / gained * used > 100_000 - spent[call]

    assert best == bests[-1] and out_of_reach(len(bests) - 1)
    assert not any(out_of_reach(call) for call in range(search.STALL_CALLS, len(bests) - 1))


class _TwoBowls(_Bowl):
    """Two basins: 1 + |x|^2 about the origin, 1.5 + |x - 2|^2 about (2, 2, 2, 2); starts in each."""

    def __init__(self, budget: int) -> None:
        super().__init__(budget)
        self.points, self.values = [np.array([[0.3, 0.0, 0.0, 0.0], [2.3, 2.0, 2.0, 2.0]])], [np.array([1.09, 1.59])]

    @staticmethod
    def value(points):
        return np.minimum(1.0 + np.sum(points ** 2, axis=1), 1.5 + np.sum((points - 2.0) ** 2, axis=1))


def test_a_polish_that_drops_its_runs_behind_ends_the_run_in_the_shallower_basin_and_finds_the_same_best():
    found = {}
    for drop in (False, True):
        bowls = _TwoBowls(100_000)
        run = search._polish(search._Allowance(bowls), *bowls.history_points(), np.random.default_rng(3), 0.1,
                             drop_runs_behind=drop)
        best, stopped_by = search._run_alone(bowls, run)
        in_shallower = sum(int(np.sum(np.all(np.abs(points - 2.0) < 1.0, axis=1))) for points in bowls.points[1:])
        found[drop] = best, stopped_by, in_shallower, bowls.calls
    # Both reach the deeper floor (the runs share one generator, so the draws differ once a run has ended).
    assert found[True][1] == found[False][1] == ('converged',)
    assert found[True][0] == pytest.approx(1.0, abs=1e-6) and found[False][0] == pytest.approx(1.0, abs=1e-6)
    # The run in the basin 50 % above the other's floor ended once it could not get there, long before cma's end.
    assert search.STALL_CALLS * search.LOCAL_POPSIZE < found[True][2] < found[False][2]


def test_a_polish_whose_every_run_fell_behind_says_so():
    bowls = _LedBowl(100_000, 0.5)  # another run's best, below both basins' floors
    bowls.points, bowls.values = [np.array([[0.3, 0.0, 0.0, 0.0], [2.3, 2.0, 2.0, 2.0]])], [np.array([1.09, 1.09])]
    run = search._polish(search._Allowance(bowls), *bowls.history_points(), np.random.default_rng(3), 0.1,
                         drop_runs_behind=True)
    best, stopped_by = search._run_alone(bowls, run)
    assert stopped_by == ('behind',) and best > 1.0 and bowls.remaining > 0


def test_a_polish_from_the_searchs_best_point_is_not_behind_while_its_own_points_lie_above_it():
    bowl = _Bowl(100_000)
    bowl.points, bowl.values = [np.zeros((1, 4)), np.full((1, 4), 0.3)], [np.array([1.0]), np.array([1.36])]
    allowance = search._Allowance(bowl)
    calls = search.STALL_CALLS + 1
    # Its own best gained nothing, but it started from the best point: it leads.
    assert not search._behind(allowance, [1.2] * calls, 1.0, 320)
    assert search._behind(allowance, [1.2] * calls, 1.36, 320)
    assert search._behind(allowance, [np.inf] * calls, 1.2, 320)  # its points all diverged
    assert not search._behind(allowance, [1.3] * (calls - 1) + [1.2], 1.36, 320)  # 0.2 / 0.1 x 320 points fit
    assert not search._behind(allowance, [1.2] * (calls - 1), 1.36, 320)  # too few calls to tell its pace


def test_a_search_of_many_gains_ends_with_a_polish_of_its_best_point_outside_the_agreement():
    template = example_spec('scara', 'pd_gravity')  # 4 joints: 8 gains
    kp, kv = omega_starts(template, [5.0, 10.0])
    budget = 6000
    result = search_gains(template, index='I', start_kp=kp, start_kv=kv, budget=budget, method='global', seed=1)
    polish = result.certificate.final_polish
    assert polish is not None and polish not in result.certificate.runs and result.episodes <= budget
    assert sum(run.episodes for run in result.restarts) + polish.episodes <= result.episodes
    assert result.certificate.episodes == result.episodes
    assert result.index == pytest.approx(min([run.index for run in result.restarts] + [polish.index]), rel=1e-12)
    as_json = result.certificate.to_dict()
    assert as_json['final_polish']['episodes'] == polish.episodes
    assert as_json['converged'] == result.certificate.converged


@pytest.mark.parametrize('polish_episodes, line', [
    (640, 'Then a final polish of the best point (not one of the runs above): best I 0.98 in 640 episodes.'),
    (0, 'The runs left no budget for a final polish of the best point.')])
def test_the_report_names_the_final_polish_beside_the_runs_it_is_not_one_of(polish_episodes, line):
    from ddarm.tuning.report import certificate_section

    runs = tuple(search.Restart(f'run {number}', 1, 100, value, ('converged',))
                 for number, value in enumerate([1.0, 1.001, 1.2]))
    polish = search.Restart('final CMA-ES polish of the best point', 16, polish_episodes,
                            0.98 if polish_episodes else np.inf, ('converged',))
    certificate = search.Certificate(runs, 2, 1000, 300 + polish_episodes, final_polish=polish)
    lines = certificate_section(certificate.to_dict(), 'I')
    assert line in lines and not any('final CMA-ES polish' in text for text in lines)  # not a row of the runs
    assert certificate.within(0.005) == 2 and certificate.best == 1.0  # the polish is not a run


@pytest.mark.parametrize('rule_start_best, verdict', [
    (1.004, 'converged: '),
    (1.006, 'not converged: '),  # only the global runs agree
])
def test_runs_of_one_family_alone_do_not_certify_a_basin(rule_start_best, verdict):
    # Four global runs agree; the Nelder-Mead runs and the polish of their ends reach 1.004 or 1.006 of the best.
    global_runs = tuple(search.Restart(f'global {number}', 9, 1000, value, ('tolx',))
                        for number, value in enumerate([1.0, 1.001, 1.002, 1.003]))
    from_rule_starts = tuple(search.Restart(f'Nelder-Mead {number}', 1, 100, value, ('converged',), True)
                             for number, value in enumerate([1.3, 1.5, rule_start_best]))
    certificate = search.Certificate(from_rule_starts + global_runs, 4, 100_000, 4300)
    assert certificate.within(0.005) == 4 + (rule_start_best < 1.005) and certificate.settled
    assert certificate.summary().startswith(verdict) and certificate.converged == (verdict == 'converged: ')
    as_json = certificate.to_dict()
    assert as_json['global_runs_within_0_5_percent'] == 4
    assert as_json['rule_start_runs_within_0_5_percent'] == (rule_start_best < 1.005)
    if not certificate.converged:
        assert '; no run from the ω-rule starts within 0.5 %' in certificate.summary()
    # The same with the families' roles swapped.
    swapped = search.Certificate(tuple(replace(run, from_rule_starts=not run.from_rule_starts)
                                       for run in certificate.runs), 3, 100_000, 4300)
    assert swapped.converged == certificate.converged
    if not swapped.converged:
        assert '; no global run within 0.5 %' in swapped.summary()


def _bowl_run(bowl, kind):
    """One of the search's runs on `bowl`: Nelder-Mead from two starts, a polish, or a DE run over a box."""
    if kind == 'nelder-mead':
        return search._nelder_mead(search._Allowance(bowl), np.array([[0.3, -0.2, 0.5, 0.1], [-1.0, 1.0, 0.4, 0.0]]),
                                   0.5)
    if kind == 'polish':
        return search._polish(search._Allowance(bowl), *bowl.history_points(), np.random.default_rng(5), 0.1)
    return search._evolution(bowl, (np.full(4, -2.0), np.full(4, 2.0)), 5,
                             np.random.default_rng(7), 'DE')


def test_runs_side_by_side_find_what_each_finds_alone_in_fewer_batches():
    alone, calls = {}, 0
    for kind in ('nelder-mead', 'polish', 'evolution'):
        alone[kind] = search._run_alone(bowl := _Bowl(100_000), _bowl_run(bowl, kind))
        calls += bowl.calls
    together = _Bowl(100_000)
    found = search._side_by_side(together, [_bowl_run(together, kind) for kind in alone])
    for kind, result in zip(alone, found):
        np.testing.assert_equal(result, alone[kind])
    assert together.calls < calls


def test_a_de_run_in_its_thread_is_scipys_own_and_leaves_no_thread():
    import threading

    import scipy.optimize
    bowl, populations = _Bowl(100_000), []

    def bowl_values(population):
        populations.append(population.T.copy())
        return 1.0 + np.sum(population.T ** 2, axis=1)

    restart, generations = search._run_alone(bowl, _bowl_run(bowl, 'evolution'))
    direct = scipy.optimize.differential_evolution(
        bowl_values, [(-2.0, 2.0)] * 4, vectorized=True, updating='deferred', popsize=5,
        maxiter=search.DE_GENERATIONS, tol=search.DE_TOL, polish=False, rng=np.random.default_rng(7))
    assert generations == direct.nit and restart.stopped_by == ('tol',)
    for asked, evaluated in zip(bowl.points[1:], populations, strict=False):
        np.testing.assert_array_equal(asked, evaluated)
    assert len(bowl.points) > len(populations) + 1  # the polish after it
    assert not any(thread.name == 'DE' for thread in threading.enumerate())


@pytest.mark.parametrize('budget', [60, 400])
def test_a_budget_ends_runs_side_by_side_within_it_and_their_threads(budget):
    import threading
    bowl = _Bowl(budget)
    search._side_by_side(bowl, [_bowl_run(bowl, kind) for kind in ('nelder-mead', 'evolution', 'polish')])
    assert 0 <= bowl.remaining and not any(thread.name == 'DE' for thread in threading.enumerate())


def test_a_search_stopped_midway_leaves_no_thread_behind():
    import threading

    class Stopped(Exception):
        pass

    class Stopping(_Bowl):
        def __call__(self, points):
            if self.calls == 3:
                raise Stopped
            return super().__call__(points)

    bowl = Stopping(100_000)
    with pytest.raises(Stopped):
        search._side_by_side(bowl, [_bowl_run(bowl, kind) for kind in ('evolution', 'nelder-mead')])
    assert not any(thread.name == 'DE' for thread in threading.enumerate())


def test_each_simplex_goes_its_own_way_beside_the_others():
    starts = np.array([[0.3, -0.2, 0.5, 0.1], [-1.0, 1.0, 0.4, 0.0], [2.0, 2.0, -2.0, 1.0]])
    together = search._run_alone(bowl := _Bowl(100_000), search._nelder_mead(search._Allowance(bowl), starts, 0.5))
    for number, start in enumerate(starts):
        bowl = _Bowl(100_000)
        alone = search._run_alone(bowl, search._nelder_mead(search._Allowance(bowl), start[None], 0.5))
        assert alone[0][0] == together[0][number] and alone[1][0] == together[1][number]
    assert together[1].all()  # the bowl's simplices converge
