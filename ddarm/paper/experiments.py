"""The paper's experiments (Tables 2-4, section 2) end to end: gains searched in-process through the batch
engine, every reported episode run through an EpisodeRecorder (the ROS graph), recorded, and scored from its bag.

What is the paper's (cases, delays, its figures) comes from ddarm.paper.settings; what we find goes into a
ddarm.paper.schema.Results. Nothing here needs ROS: the recorder is handed in.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ddarm.control.gains import SEARCH_START_OMEGAS, largest_stable_omega, omega_rule_computed_torque
from ddarm.control.laws import CONTROLLERS
from ddarm.control.stability import boundary_omega_delta
from ddarm.episodes.engine import warm_up
from ddarm.episodes.spec import EpisodeSpec, arm_joints, gains_from_omega
from ddarm.motion.programmed import paper_torque_limit, within_limits
from ddarm.paper.claims import judge_claims
from ddarm.paper.schema import (BoundaryRow, FrontRow, GainSet, OmegaProcedureRow, OmegaRuleRow, ParetoFront,
                                RestartRow, Results, Robustness, RunSettings, ScenarioRow, Search, StabilityRow,
                                Table4Row, TauRow)
from ddarm.paper.settings import Budget, Case, paper_settings
from ddarm.recording.bags import checked_output_path
from ddarm.reporting.progress import Progress
from ddarm.tuning.pareto import pareto_front
from ddarm.interrupts import Interrupted, check_stop
from ddarm.tuning.jobs import POLL_S, BackgroundJobs, Job, JobError
from ddarm.tuning.procedures import omega_procedure
from ddarm.tuning.robust import scenario_grid
from ddarm.tuning.search import omega_starts, search_gains


class EpisodeRecorder(Protocol):
    """What runs the reported episodes: the ROS graph session, in lockstep."""

    def record_and_score(self, spec: EpisodeSpec, bag: Path, command: str | None = None) -> tuple[Any, dict]:
        """Run `spec`, record it as a bag at `bag`, and return what ran and the bag's score (`ddarm score --json`)."""

    def prepare(self, spec: EpisodeSpec) -> None:
        """Get ready for episodes like `spec` (the session: start that law's nodes), before any is asked for."""


def _template(controller: str, case: Case) -> EpisodeSpec:
    return EpisodeSpec(controller=controller, trajectory=case.trajectory, duration=case.duration, period=case.period,
                       delay=paper_settings().delays[controller])


def _search_record(result, wall: float, start_count: int) -> Search:
    """A finished global search as results.json keeps it: the search scores its `start_count` starts first."""
    restarts = [RestartRow(start=restart.start, popsize=restart.popsize, episodes=restart.episodes,
                           index=restart.index if np.isfinite(restart.index) else None,
                           stopped_by=restart.stopped_by) for restart in result.restarts]
    return Search(episodes=result.episodes, wall_time_s=wall, episodes_per_s=result.episodes / wall,
                  in_process_index=result.index, start_index=float(np.min(result.history_index[:start_count])),
                  method=result.method, evolution_generations=result.evolution_generations, restarts=restarts,
                  restarts_within_1_percent=result.restarts_within(0.01), **result.certainty_fields(hint=False))


def optimise(template: EpisodeSpec, index: str, budget: Budget, progress=None) -> GainSet:
    """The global search (differential evolution, then local CMA-ES runs) from the ω-rule gains: the best there
    are, with how many of its local runs reached them. `progress` as search_gains takes it."""
    start_kp, start_kv = omega_starts(template, SEARCH_START_OMEGAS)
    started = time.perf_counter()
    result = search_gains(template, index=index, start_kp=start_kp, start_kv=start_kv, budget=budget.search_episodes,
                          method='global', popsize=budget.de_popsize, progress=progress)
    wall = time.perf_counter() - started
    return GainSet(name=f'{template.controller}-{index}-traj{template.trajectory}-T{template.duration:g}'
                        f'-dt{template.period:g}',
                   controller=template.controller, index=index, trajectory=template.trajectory,
                   duration=template.duration, period=template.period, delay=template.delay,
                   kp=tuple(result.kp.tolist()), kv=tuple(result.kv.tolist()),
                   search=_search_record(result, wall, len(start_kp)))


def pareto_record(beyond, budget: Budget, seed_i1: GainSet, seed_i: GainSet, progress=None) -> ParetoFront:
    """The I1–I2 front of `beyond.law` in `beyond.case`, seeded by that case's I1 and I optima."""
    template = _template(beyond.law, beyond.case)
    seeds = (seed_i1, seed_i)
    front = pareto_front(template, budget=budget.pareto_episodes,
                         seeds=[(np.array(seed.kp), np.array(seed.kv)) for seed in seeds], progress=progress)
    return ParetoFront(
        controller=beyond.law, trajectory=beyond.case.trajectory, duration=beyond.case.duration,
        period=beyond.case.period, delay=template.delay, method=front.method, episodes=front.episodes,
        wall_time_s=front.wall_time_s, front_size=front.front_size, searches=front.searches,
        searches_converged=front.searches_converged, seeds=tuple(seed.name for seed in seeds),
        seeds_on_front=front.seeds_on_front,
        front=[FrontRow(I1=point.I1, I2=point.I2, kp=tuple(point.kp.tolist()), kv=tuple(point.kv.tolist()))
               for point in front.front])


def robust_record(beyond, budget: Budget, nominal: GainSet, progress=None) -> Robustness:
    """Gains for the `beyond.robust` objective of I over its scenarios, the nominal (3.2) optimum one more start;
    their episodes through ROS (`rows`) are run later."""
    template = _template(beyond.law, beyond.case)
    grid = beyond.robust
    scenarios = scenario_grid(template, taus=grid.taus, mass_scales=grid.mass_scales)
    start_kp, start_kv = omega_starts(template, SEARCH_START_OMEGAS)
    start_kp, start_kv = np.vstack([start_kp, nominal.kp]), np.vstack([start_kv, nominal.kv])
    started = time.perf_counter()
    result = search_gains(template, index='I', start_kp=start_kp, start_kv=start_kv, budget=budget.robust_episodes,
                          method='global', popsize=budget.de_popsize, scenarios=scenarios, aggregate=grid.objective,
                          progress=progress)
    return Robustness(
        controller=beyond.law, trajectory=beyond.case.trajectory, duration=beyond.case.duration,
        period=beyond.case.period, delay=template.delay, objective=grid.objective, kp=tuple(result.kp.tolist()),
        kv=tuple(result.kv.tolist()), nominal=nominal.name,
        # The ω-rule starts come first; the last start is the nominal optimum.
        search=_search_record(result, time.perf_counter() - started, len(start_kp) - 1), rows=[])


class Reproduction:
    """Runs every experiment into one output folder: bags/ here, results.json and the report by the caller."""

    def __init__(self, out: Path, budget: Budget, command: str, progress=None, bar=None) -> None:
        self.out, self.budget, self.command = out, budget, command
        self.progress = progress or (lambda message: None)
        # bar(label, total, index_name, position): the Progress each search reports to, on line `position` of a
        # terminal (one per search running at once); shown by the caller, none by default.
        self.bar = bar or (lambda label, total, index_name, position: Progress(total, label, quiet=True))
        self.settings = paper_settings()
        self.results = Results(
            command=command, quick=budget != self.settings.budgets.full,
            started=time.strftime('%Y-%m-%dT%H:%M:%S%z'),
            settings=RunSettings(paper_delays=self.settings.delays, search_budget=budget.search_episodes,
                                 de_popsize=budget.de_popsize, taus=budget.taus, start_omegas=SEARCH_START_OMEGAS,
                                 pareto_budget=budget.pareto_episodes, robust_budget=budget.robust_episodes),
            reconstruction=self.settings.reconstruction)

    def _episode(self, recorder: EpisodeRecorder, spec: EpisodeSpec, name: str) -> dict:
        """One recorded episode, scored from its bag: the fields every row shares, as keyword arguments."""
        bag = checked_output_path(self.out / 'bags' / name)
        _, scored = recorder.record_and_score(spec, bag, command=self.command)
        # The paper's limit whether or not the episode ran limited, from the bag's own nominal maxima
        # (the maxima of a one-sample series are that sample).
        limit = paper_torque_limit(np.array([scored['max_abs_nominal_torque']]))
        return {'I1': scored['I1'], 'I2': scored['I2'], 'I': scored['I'], 'diverged': scored['diverged'],
                'max_abs_torque': tuple(scored['max_abs_torque']), 'torque_limit': tuple(limit.tolist()),
                'within_limits': within_limits(scored['max_abs_torque'], limit),
                'bag': str(bag.relative_to(self.out))}

    def _laws(self) -> list[str]:
        """The laws in the order their searches end: `beyond.law`'s first, as the front and robust search need them."""
        return [self.settings.beyond.law, *(law for law in CONTROLLERS if law != self.settings.beyond.law)]

    def first_episode(self) -> EpisodeSpec:
        """An episode of the law whose episodes `run_episodes` runs first, while no search is done yet."""
        return _template(self._laws()[0], self.settings.case)

    def search_jobs(self) -> list[Job]:
        """Every search as a job: the gain sets the tables need, keyed (controller, index, case), I1 (2.5) at the
        paper's case and I (3.2) at each of Table 4's; then the I1–I2 front ('front') and the robust gains
        ('robust') of `beyond.law` in `beyond.case`, which start from that case's optima."""
        beyond, jobs = self.settings.beyond, []
        seeds = tuple((beyond.law, index, beyond.case) for index in ('I1', 'I'))
        for controller in CONTROLLERS:
            for index, cases in (('I1', (self.settings.case,)), ('I', self.settings.table4_cases)):
                for case in cases:
                    key = (controller, index, case)
                    # Cost (episodes x samples) first, so that the last to start are short; the front's and the
                    # robust search's seeds before all.
                    cost = self.budget.search_episodes * case.duration / case.period
                    jobs.append(Job(key, f'{controller} {index} trajectory {case.trajectory}, '
                                         f'T = {case.duration}, Δ = {case.period}', optimise,
                                    (_template(controller, case), index, self.budget),
                                    total=self.budget.search_episodes, index_name=index,
                                    priority=cost + (1e12 if key in seeds else 0.0)))
        samples = beyond.case.duration / beyond.case.period
        jobs.append(Job('front', f'I1–I2 front: {beyond.law} trajectory {beyond.case.trajectory}, '
                                 f'T = {beyond.case.duration}, Δ = {beyond.case.period}', pareto_record,
                        (beyond, self.budget), needs=seeds, total=self.budget.pareto_episodes,
                        priority=self.budget.pareto_episodes * samples))
        grid = beyond.robust
        jobs.append(Job('robust', f'robust gains: {beyond.law}, {grid.objective} I over τ = {list(grid.taus)} × '
                                  f'mass scale {list(grid.mass_scales)}', robust_record, (beyond, self.budget),
                        needs=seeds[1:], total=self.budget.robust_episodes,
                        priority=self.budget.robust_episodes * samples))
        return jobs

    def start_searches(self, workers: int = 1) -> BackgroundJobs:
        """The searches (`search_jobs`), `workers` at a time, in the background (ddarm.tuning.jobs; the same results
        for any number), each shown by its own bar."""
        if workers > 1:
            # Compiled (or loaded from numba's cache) here once: workers starting on an empty cache would each
            # compile the whole loop at once, on the same cores.
            warm_up()
        bars, positions = {}, {}  # by job: its Progress, and the terminal line it holds

        def start(job: Job) -> None:
            self.progress(('searching ' if isinstance(job.key, tuple) else '') + job.label)
            positions[job.key] = min(set(range(workers)) - set(positions.values()))
            bars[job.key] = self.bar(job.label, job.total, job.index_name, positions[job.key])

        def done(job: Job, result) -> None:
            bars.pop(job.key).close()
            del positions[job.key]

        def end() -> None:  # the bars of jobs a failure or a stop cut short
            for bar in bars.values():
                bar.close()

        return BackgroundJobs(self.search_jobs(), workers, on_start=start, on_done=done, on_end=end,
                              on_progress=lambda job, episodes, best: bars[job.key].update(episodes, best))

    def take_searches(self, found: dict) -> dict:
        """The searches' results into `results` (gain sets in the order of `search_jobs`), with the stability map;
        returns the gain sets by key."""
        beyond = self.settings.beyond
        gains = {job.key: found[job.key] for job in self.search_jobs() if isinstance(job.key, tuple)}
        self.results.gains = list(gains.values())
        robust_rows = self.results.robust.rows if self.results.robust is not None else []
        self.results.pareto = found['front']
        self.results.robust = dataclasses.replace(found['robust'], rows=robust_rows)
        self.results.stability_map = [
            BoundaryRow(delay=delay, zeta=zeta, omega_delta=boundary_omega_delta(delay, zeta))
            for delay in beyond.stability_map.delays for zeta in beyond.stability_map.zetas]
        return gains

    def run_episodes(self, recorders: EpisodeRecorder | list[EpisodeRecorder], searches: BackgroundJobs) -> None:
        """Every reported episode through `recorders`, each group as soon as the searches it needs are done (while
        the others go on), then the searches' results into `results`.

        With several recorders (graph sessions), each runs groups in a thread of its own, as they become ready:
        the same episodes, the same bags, in less time. Among the groups ready, a recorder's current law's come
        first: a session starts a controller process for each switch of law. The rows are kept in the order of
        the tables, whatever order they ran in.
        """
        recorders = list(recorders) if isinstance(recorders, (list, tuple)) else [recorders]
        groups = self._episode_groups()
        unknown = sorted({str(key) for group in groups for key in group[1] if key not in searches.labels})
        if unknown:
            raise JobError(f'the reported episodes need searches that are not run: {unknown}')
        case = self.settings.case
        schedule = _Schedule(groups, searches, lambda recorder, law: recorder.prepare(_template(law, case)))
        if len(recorders) == 1:
            schedule.work(recorders[0])
        else:
            schedule.work_on(recorders)
        order = {controller: rank for rank, controller in enumerate(CONTROLLERS)}
        for rows in (self.results.table2, self.results.table3, self.results.table4,
                     self.results.section2.omega_rules, self.results.section2.omega_procedure):
            rows.sort(key=lambda row: order[row.controller])  # stable: each law's rows ran in the tables' order
        self.take_searches(searches.wait())

    @property
    def episode_groups(self) -> int:
        """How many groups of reported episodes there are: more graph sessions than this would idle."""
        return len(self._episode_groups())

    def _episode_groups(self) -> list[tuple]:
        """(law, the searches it needs, what runs it on a recorder) for each group of reported episodes."""
        case, beyond = self.settings.case, self.settings.beyond
        groups = []
        for controller in self._laws():
            groups += [
                (controller, ((controller, 'I1', case), (controller, 'I', case)),
                 lambda recorder, found, law=controller: self._tables_2_and_3(recorder, found, law)),
                (controller, tuple((controller, 'I', table4) for table4 in self.settings.table4_cases),
                 lambda recorder, found, law=controller: self._table4(recorder, found, law)),
                (controller, (), lambda recorder, found, law=controller: self._section2(recorder, law))]
        groups += [(beyond.law, ('robust', (beyond.law, 'I', beyond.case)),
                    lambda recorder, found: self._robust(recorder, found)),
                   ('computed_torque', (), lambda recorder, found: self._stability(recorder))]
        return groups

    def _robust(self, recorder: EpisodeRecorder, found: dict) -> None:
        """The robust gains and the nominal optimum on every scenario, each through the ROS graph."""
        beyond = self.settings.beyond
        robust, nominal = found['robust'], found[(beyond.law, 'I', beyond.case)]
        template = _template(beyond.law, beyond.case)
        rows = []
        for scenario in scenario_grid(template, taus=beyond.robust.taus, mass_scales=beyond.robust.mass_scales):
            for name, kp, kv in (('robust', robust.kp, robust.kv), ('nominal', nominal.kp, nominal.kv)):
                self.progress(f'robust: {name} gains at τ = {scenario.tau}, mass scale {scenario.mass_scale}')
                scale = '-'.join(f'{value:g}' for value in scenario.mass_scale)
                row = self._episode(recorder, scenario.with_gains(kp, kv),
                                    f'robust-{name}-tau{scenario.tau:g}-mass{scale}')
                rows.append(ScenarioRow(tau=scenario.tau, mass_scale=tuple(scenario.mass_scale), gains=name,
                                        I1=row['I1'], I2=row['I2'], I=row['I'], diverged=row['diverged'],
                                        bag=row['bag']))
        self.results.robust = dataclasses.replace(robust, rows=rows)

    def _tables_2_and_3(self, recorder: EpisodeRecorder, gains: dict, controller: str) -> None:
        case = self.settings.case
        template = _template(controller, case)
        for table, index in (('table2', 'I1'), ('table3', 'I')):
            entry = gains[(controller, index, case)]
            for limited in ((False, True) if table == 'table2' else (False,)):
                for tau in self.budget.taus:
                    self.progress(f'{table}: {controller} τ = {tau} {"limited" if limited else "unlimited"}')
                    spec = dataclasses.replace(template.with_gains(entry.kp, entry.kv), tau=tau,
                                               torque_limit='paper' if limited else 'none')
                    name = f"{table}-{controller}-tau{tau:.2f}-{'limited' if limited else 'unlimited'}"
                    paper = (self.settings.table2_figure(controller, limited, tau) if table == 'table2'
                             else self.settings.table3_figure(controller, tau))
                    getattr(self.results, table).append(TauRow(
                        controller=controller, tau=tau, limited=limited, gains=entry.name,
                        **self._episode(recorder, spec, name), paper=paper))

    def _table4(self, recorder: EpisodeRecorder, gains: dict, controller: str) -> None:
        for case in self.settings.table4_cases:
            entry = gains[(controller, 'I', case)]
            self.progress(f'table4: {controller} trajectory {case.trajectory}, T = {case.duration}, Δ = {case.period}')
            spec = _template(controller, case).with_gains(entry.kp, entry.kv)
            row = self._episode(recorder, spec,
                                f'table4-{controller}-traj{case.trajectory}-T{case.duration:g}-dt{case.period:g}')
            self.results.table4.append(Table4Row(
                controller=controller, trajectory=case.trajectory, duration=case.duration, period=case.period,
                delay=spec.delay, gains=entry.name, kp=entry.kp, kv=entry.kv, **row,
                paper=self.settings.table4_figures(controller, case)))

    def _section2(self, recorder: EpisodeRecorder, controller: str) -> None:
        case = self.settings.case
        template = _template(controller, case)
        omega = self.settings.omega_rules[controller]
        kp, kv = gains_from_omega(template, omega)
        self.progress(f'section 2: {controller} ω = {omega} rule')
        self.results.section2.omega_rules.append(OmegaRuleRow(
            controller=controller, omega=omega, kp=tuple(kp.tolist()), kv=tuple(kv.tolist()),
            **self._episode(recorder, template.with_gains(kp, kv), f'section2-{controller}-omega{omega:g}')))
        procedure = self.settings.omega_procedure[controller]
        disturbed = dataclasses.replace(template, **procedure.disturbance)
        choice = omega_procedure(disturbed, np.radians(procedure.max_error_deg))
        row = OmegaProcedureRow(controller=controller, case=procedure.case, max_error_deg=procedure.max_error_deg,
                                omega_min=choice.omega_min, omega=choice.omega,
                                kp=None if choice.kp is None else tuple(choice.kp.tolist()),
                                kv=None if choice.kv is None else tuple(choice.kv.tolist()))
        if choice.omega is not None:
            self.progress(f'section 2: {controller} ω procedure, ω = {choice.omega:.4g}')
            row = dataclasses.replace(row, **self._episode(recorder, disturbed.with_gains(choice.kp, choice.kv),
                                                           f'section2-{controller}-procedure'))
        self.results.section2.omega_procedure.append(row)

    def _stability(self, recorder: EpisodeRecorder) -> None:
        """Computed torque at the paper's ω for each Δ, against the boundary ω*(Δ) of its sampled error
        dynamics (2.8), which is computed torque's: PD + gravity's depends on the arm's configuration."""
        stability = self.settings.stability
        template = _template('computed_torque', self.settings.case)
        for period in stability.periods:
            boundary = largest_stable_omega(period, template.delay)
            kp, kv = omega_rule_computed_torque(len(arm_joints(template)[0]), stability.omega)
            self.progress(f'stability: computed torque ω = {stability.omega:g} at Δ = {period}')
            spec = dataclasses.replace(template, period=period).with_gains(kp, kv)
            row = self._episode(recorder, spec, f'stability-dt{period:g}-omega{stability.omega:g}')
            self.results.section2.stability.append(StabilityRow(
                period=period, omega_max_stable=boundary, omega_15_stable=bool(stability.omega < boundary),
                I1_at_omega_15=row['I1'], diverged_at_omega_15=row['diverged'], bag=row['bag']))

    def judge_claims(self) -> None:
        self.results.claims = judge_claims(self.results, self.settings)


class _Schedule:
    """The groups of reported episodes still to run, handed to recorders as their searches end.

    A recorder keeps to its law while that law has groups ready; it switches when another law's
    group waited for a search, or when its law has none left (the episodes that need no search
    wait for their law's turn). One thread per recorder (`work_on`): the groups are taken under a
    lock, and a failure in one thread stops the others after their group under way (a stop by
    signal, at their next check).
    """

    def __init__(self, groups: list, searches, prepare) -> None:
        self.groups, self.searches, self.prepare = list(groups), searches, prepare
        self.lock = threading.Lock()
        self.failed = threading.Event()

    def _next(self, law: str | None, recorder) -> tuple | None:
        """The next group for a recorder whose nodes run `law`; None once no group is left (or another thread failed)."""
        while not self.failed.is_set():
            with self.lock:
                if not self.groups:
                    return None
                ready = [group for group in self.groups if self.searches.ready(group[1])]
                law_done = all(group[0] != law for group in self.groups)
                choices = ([group for group in ready if group[0] == law]
                           or [group for group in ready if group[1] or law_done])
                if choices:
                    self.groups.remove(choices[0])
                    return choices[0]
                switch = law is not None and law_done
                if switch:
                    law = self.groups[0][0]
            if switch:
                # This law is done and the other's next episodes wait for a search: switch the nodes now, while it
                # runs, not after (outside the lock: stopping a node waits until the graph has forgotten it).
                self.prepare(recorder, law)
            self.searches.wait_for_change()
        return None

    def work(self, recorder) -> None:
        """Run groups on `recorder` until none is left."""
        law = None
        while (group := self._next(law, recorder)) is not None:
            law = group[0]
            group[2](recorder, self.searches.wait(group[1]))

    def work_on(self, recorders: list) -> None:
        """`work` on every recorder at once, one thread each; the first failure (or a stop) is raised here, the
        others noted on it.

        A node process ends with the thread that started it (`ddarm.ros.lifetime`): recorders that start
        processes of their own should be `SessionProcess`es started from the main thread, which the
        threads here only talk to.
        """
        errors = []

        def run(recorder) -> None:
            try:
                self.work(recorder)
            except BaseException as error:  # handed to the calling thread, which raises it
                errors.append(error)
                self.failed.set()

        threads = [threading.Thread(target=run, args=(recorder,), name=f'ddarm-episodes-{number}')
                   for number, recorder in enumerate(recorders)]
        for thread in threads:
            thread.start()
        try:
            for thread in threads:
                while thread.is_alive():
                    thread.join(POLL_S)
                    check_stop()
        except BaseException:
            self.failed.set()  # the others stop after their group under way; a stop reaches them by check_stop
            _join_despite_stops(threads)  # never leave a thread using a recorder the caller is about to close
            raise
        if errors:
            for later in errors[1:]:
                errors[0].add_note(f'another graph session failed too: {type(later).__name__}: {later}')
            raise errors[0]


def _join_despite_stops(threads: list[threading.Thread]) -> None:
    """Wait for every thread, whatever stops come meanwhile (a second Ctrl-C), then raise the last of them."""
    stop = None
    for thread in threads:
        while thread.is_alive():
            try:
                thread.join(POLL_S)
            except Interrupted as again:
                stop = again
    if stop is not None:
        raise stop
