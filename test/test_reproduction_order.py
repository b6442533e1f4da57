"""Reproduction.run_episodes: each group of reported episodes runs as soon as its searches are done, whatever order
they end in; the rows keep the tables' order, and the law's nodes are switched as seldom as the order allows."""

import dataclasses
import threading

import pytest

from ddarm.control.laws import CONTROLLERS
from ddarm.paper.experiments import Reproduction
from ddarm.paper.settings import Budget

SCORED = {'I1': 0.5, 'I2': 1.5, 'I': 2.0, 'diverged': False, 'max_abs_torque': [1.0, 1.0, 1.0],
          'max_abs_nominal_torque': [10.0, 10.0, 10.0]}


class Recorder:
    """An EpisodeRecorder that records nothing, scores what it is told, and notes which law ran or was prepared."""

    def __init__(self) -> None:
        self.events = []

    def record_and_score(self, spec, bag, command=None):
        self.events.append(('run', spec.controller, bag.name))
        return None, SCORED

    def prepare(self, spec):
        self.events.append(('prepare', spec.controller, None))


class Searches:
    """The searches' results handed out one at a time, in a given order, as BackgroundJobs hands them out."""

    def __init__(self, found: dict, order: list) -> None:
        self.found, self.order, self.results = found, list(order), {}
        self.labels = {key: str(key) for key in found}
        self.lock = threading.Lock()  # several recorders' threads wait at once

    def ready(self, keys) -> bool:
        return all(key in self.results for key in keys)

    def wait_for_change(self) -> None:
        with self.lock:
            if self.order:
                key = self.order.pop(0)
                self.results[key] = self.found[key]

    def wait(self, keys=None) -> dict:
        keys = list(self.found) if keys is None else keys
        while not self.ready(keys):
            self.wait_for_change()
        return {key: self.results[key] for key in keys}


@pytest.fixture(scope='module')
def found(tmp_path_factory):
    """Every search of a reproduction at a small budget, by key."""
    budget = dataclasses.replace(Budget.quick(), search_episodes=300, pareto_episodes=300, robust_episodes=400)
    reproduction = Reproduction(tmp_path_factory.mktemp('searches'), budget, 'ddarm reproduce')
    with reproduction.start_searches(2) as searches:
        return budget, searches.wait()


def _switches(events):
    laws = [law for kind, law, _ in events if kind == 'run']
    return sum(1 for before, after in zip(laws, laws[1:]) if before != after)


@pytest.mark.parametrize('ending', ['in order', 'reversed'])
def test_rows_keep_the_tables_order_whatever_order_the_searches_end_in(tmp_path, found, ending):
    budget, results = found
    order = list(results) if ending == 'in order' else list(reversed(results))
    (tmp_path / 'bags').mkdir()
    reproduction = Reproduction(tmp_path, budget, 'ddarm reproduce')
    recorder = Recorder()
    reproduction.run_episodes(recorder, Searches(results, order))
    done = reproduction.results
    for rows in (done.table2, done.table3, done.table4, done.section2.omega_rules):
        assert [row.controller for row in rows] == sorted((row.controller for row in rows), key=CONTROLLERS.index)
    assert [(row.limited, row.tau) for row in done.table2 if row.controller == 'pd_gravity'] == [
        (limited, tau) for limited in (False, True) for tau in budget.taus]
    assert [gain_set.name for gain_set in done.gains] == [
        results[key].name for key in results if isinstance(key, tuple)]
    assert done.pareto == results['front'] and len(done.robust.rows) == 8
    assert dataclasses.replace(done.robust, rows=[]) == results['robust']
    ran = [bag for kind, _, bag in recorder.events if kind == 'run']
    assert len(ran) == len(set(ran)) == 2 * (2 * len(budget.taus) + len(budget.taus) + 4 + 2) + 8 + 6
    # A switch only when nothing of the current law is ready: computed torque's episodes first (its searches seed
    # the front and the robust search, so they run first), PD + gravity's as its searches end, and back at most once.
    assert _switches(recorder.events) <= 2


def test_the_nodes_of_the_next_law_are_started_while_its_searches_run(tmp_path, found):
    budget, results = found
    pd_searches = [key for key in results if isinstance(key, tuple) and key[0] == 'pd_gravity']
    # PD + gravity's searches end first: its episodes run, while computed torque's wait for theirs.
    order = pd_searches + [key for key in results if key not in pd_searches]
    (tmp_path / 'bags').mkdir()
    recorder = Recorder()
    Reproduction(tmp_path, budget, 'ddarm reproduce').run_episodes(recorder, Searches(results, order))
    prepared = recorder.events.index(('prepare', 'computed_torque', None))
    before, after = recorder.events[:prepared], recorder.events[prepared + 1:]
    assert {law for kind, law, _ in before if kind == 'run'} >= {'pd_gravity'}
    assert all(law == 'computed_torque' for _, law, _ in after)  # PD + gravity was done, computed torque's nodes up
    assert [law for kind, law, _ in before if kind == 'run'][-1] == 'pd_gravity'
    assert _switches(recorder.events) == 2  # computed torque's episodes that need no search, PD + gravity's, back



def _table_rows(results):
    """Every row of the tables, as results.json holds them (with the bag each is scored from)."""
    return [row for rows in (results.table2, results.table3, results.table4, results.section2.omega_rules,
                             results.robust.rows, results.section2.stability) for row in rows]


@pytest.mark.parametrize('ending', ['in order', 'reversed'])
def test_several_recorders_run_every_episode_once_and_give_the_same_rows(tmp_path, found, ending):
    budget, results = found
    order = list(results) if ending == 'in order' else list(reversed(results))
    rows = {}
    for count in (1, 3):
        out = tmp_path / str(count)
        (out / 'bags').mkdir(parents=True)
        recorders = [Recorder() for _ in range(count)]
        reproduction = Reproduction(out, budget, 'ddarm reproduce')
        reproduction.run_episodes(recorders if count > 1 else recorders[0], Searches(results, order))
        ran = [bag for recorder in recorders for kind, _, bag in recorder.events if kind == 'run']
        assert len(ran) == len(set(ran)) == 2 * (2 * len(budget.taus) + len(budget.taus) + 4 + 2) + 8 + 6
        rows[count] = _table_rows(reproduction.results)
    assert rows[1] == rows[3]


class StartingTogether(Recorder):
    """A recorder whose first episode waits for the other recorders' first: every one of them takes a group."""

    def __init__(self, together: threading.Barrier, fails: bool) -> None:
        super().__init__()
        self.together, self.fails, self.started = together, fails, False

    def record_and_score(self, spec, bag, command=None):
        if not self.started:
            self.started = True
            self.together.wait(timeout=30)
        if self.fails:
            raise RuntimeError(f'no graph for {bag.name}')
        return super().record_and_score(spec, bag, command)


def test_a_failing_recorder_stops_the_run_with_its_error(tmp_path, found):
    budget, results = found
    (tmp_path / 'bags').mkdir()
    together = threading.Barrier(2)
    recorders = [StartingTogether(together, fails=False), StartingTogether(together, fails=True)]
    with pytest.raises(RuntimeError, match='no graph for'):
        Reproduction(tmp_path, budget, 'ddarm reproduce').run_episodes(recorders, Searches(results, list(results)))
    ran = [bag for kind, _, bag in recorders[0].events if kind == 'run']
    assert 0 < len(ran) < 2 * (2 * len(budget.taus) + len(budget.taus) + 4 + 2) + 8 + 6  # it stopped after its group
