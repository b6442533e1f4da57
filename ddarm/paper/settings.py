"""The paper's settings, read from data/settings.yaml into frozen dataclasses.

The file holds everything that is the paper's rather than the code's: the delays, the cases, the τ
grid, the published figures of Tables 2-4, section 2's cases, the claims' thresholds, the budgets, the
reconstruction notes. Beyond the types (ddarm.paper.typed), the loader refuses settings that would fail
only deep into a run, naming the key: a law or τ without its figures, a case on a motion that does not
exist, a disturbance with a value per joint for another arm, and every episode `ddarm reproduce` would
run from them that ddarm.episodes.spec.check_episode refuses (T not a whole number of periods, a τ beyond
T, a delay out of range, an ω rule <= 0, ...), budgets too small for the searches, two bags of one name.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np
import yaml

from ddarm.control.gains import SEARCH_START_OMEGAS, omega_rule_computed_torque
from ddarm.control.laws import CONTROLLERS, GainError, checked_delay
from ddarm.episodes.spec import EpisodeSpec, check_episode, gains_from_omega
from ddarm.errors import DdarmError
from ddarm.datafiles import DataFileError, read_data_file
from ddarm.motion.files import DataLoader
from ddarm.motion.programmed import PAPER_TRAJECTORIES, MotionError, paper_motion_joints
from ddarm.paper import typed
from ddarm.tuning.methods import DEFAULT_POPULATION
from ddarm.tuning.procedures import steady_state_error_per_unit_gain
from ddarm.tuning.search import least_budget

SETTINGS_PATH = Path(__file__).resolve().parent / 'data' / 'settings.yaml'

Controller = Literal[CONTROLLERS]
# The episode options section 2's procedure may disturb (ddarm.episodes.spec.EpisodeSpec fields).
Disturbance = Literal['external_torque', 'mass_scale']


class SettingsError(DdarmError, ValueError):
    """Paper settings that cannot be run; the text names the file and the key."""


@dataclass(frozen=True)
class Case:
    """One experiment's motion and sampling: a paper trajectory, its duration T and Δ in s."""

    trajectory: int
    duration: float
    period: float


@dataclass(frozen=True)
class Budget:
    """How hard the searches try (episodes per search, DE's population per dimension; episodes of the front and
    of the robust search) and the τ run through ROS."""

    search_episodes: int
    de_popsize: int
    taus: tuple[float, ...]
    pareto_episodes: int
    robust_episodes: int

    @classmethod
    def full(cls) -> Budget:
        return paper_settings().budgets.full

    @classmethod
    def quick(cls) -> Budget:
        return paper_settings().budgets.quick


@dataclass(frozen=True)
class Budgets:
    full: Budget
    quick: Budget


@dataclass(frozen=True)
class Table2Figures:
    """One law's column pair of Table 2, one figure per τ (None: the paper prints none)."""

    unlimited: tuple[float | None, ...]
    limited: tuple[float | None, ...]


@dataclass(frozen=True)
class Table4Figures:
    I: float
    I1: float
    I2: float


@dataclass(frozen=True)
class Table4Case:
    case: Case
    paper: Mapping[Controller, Table4Figures]


@dataclass(frozen=True)
class ProcedureCase:
    """Section 2's procedure for one law: the disturbance (described, and as episode options) and the
    permitted steady-state error."""

    case: str
    disturbance: Mapping[Disturbance, tuple[float, ...]]
    max_error_deg: float


@dataclass(frozen=True)
class Range:
    """The closed interval [low, high]."""

    low: float
    high: float


@dataclass(frozen=True)
class ClaimThresholds:
    """The numbers in the paper's claims that ddarm.paper.claims judges our results against."""

    table4_I1_ratio: Range  # PD + gravity's Table 4 I1 / computed torque's, in every case


@dataclass(frozen=True)
class Stability:
    """The claim that computed torque at ω stays stable for every Δ ≤ claimed_period, and the Δ run."""

    omega: float
    claimed_period: float
    periods: tuple[float, ...]


@dataclass(frozen=True)
class RobustGrid:
    """The scenarios the robust gains are tuned over: τ (3.1) × plant link-mass scale (every link), and the aggregate."""

    taus: tuple[float, ...]
    mass_scales: tuple[float, ...]
    objective: Literal['worst', 'mean']


@dataclass(frozen=True)
class StabilityMap:
    """The delays d and damping ratios ζ of the stability map (ωΔ* of ddarm.control.stability)."""

    delays: tuple[int, ...]
    zetas: tuple[float, ...]


@dataclass(frozen=True)
class Beyond:
    """What ddarm adds to the paper: the I1–I2 front and the robust gains of one law in one Table 4 case, whose
    (3.2) optimum is set on the front and is the nominal gains the robust ones are compared with; the map."""

    law: Controller
    case: Case
    robust: RobustGrid
    stability_map: StabilityMap


@dataclass(frozen=True)
class PaperSettings:
    delays: Mapping[Controller, int]
    case: Case
    taus: tuple[float, ...]
    table2: Mapping[Controller, Table2Figures]
    table3: Mapping[Controller, tuple[float | None, ...]]
    table4: tuple[Table4Case, ...]
    tracking_case: Case
    omega_rules: Mapping[Controller, float]
    omega_procedure: Mapping[Controller, ProcedureCase]
    stability: Stability
    claims: ClaimThresholds
    budgets: Budgets
    beyond: Beyond
    reconstruction: tuple[str, ...]

    @property
    def table4_cases(self) -> tuple[Case, ...]:
        return tuple(entry.case for entry in self.table4)

    def table2_figure(self, controller: str, limited: bool, tau: float) -> float | None:
        figures = self.table2[controller]
        return (figures.limited if limited else figures.unlimited)[self.taus.index(tau)]

    def table3_figure(self, controller: str, tau: float) -> float | None:
        return self.table3[controller][self.taus.index(tau)]

    def table4_figures(self, controller: str, case: Case) -> Table4Figures:
        return self.table4[self.table4_cases.index(case)].paper[controller]


def load_settings(path: Path | str = SETTINGS_PATH) -> PaperSettings:
    """The settings file at `path`; SettingsError names the file and the key of anything refused."""
    path = Path(path)
    try:
        document = yaml.load(read_data_file(path), Loader=DataLoader)
    except (OSError, DataFileError, yaml.YAMLError) as error:
        raise SettingsError(f'{path}: cannot read the settings: {error}') from error
    _refuse_huge_integers(document, path, '')
    # A user's copy may still name a case's duration T, as this file did before.
    settings = typed.read(PaperSettings, document, str(path), SettingsError, renamed={Case: {'T': 'duration'}})
    _check(settings, path)
    return settings


@lru_cache(maxsize=1)
def paper_settings() -> PaperSettings:
    """The paper's settings (data/settings.yaml), read once."""
    return load_settings()


def _check(settings: PaperSettings, path: Path) -> None:
    def fail(message: str):
        raise SettingsError(f'{path}: {message}')

    per_controller = {'delays': settings.delays, 'table2': settings.table2, 'table3': settings.table3,
                      'omega_rules': settings.omega_rules, 'omega_procedure': settings.omega_procedure}
    per_controller.update({f'table4[{i}].paper': entry.paper for i, entry in enumerate(settings.table4)})
    for key, mapping in per_controller.items():
        for controller in CONTROLLERS:
            if controller not in mapping:
                fail(f"missing key {f'{key}.{controller}'!r}")
    for controller in CONTROLLERS:
        columns = {f'table2.{controller}.unlimited': settings.table2[controller].unlimited,
                   f'table2.{controller}.limited': settings.table2[controller].limited,
                   f'table3.{controller}': settings.table3[controller]}
        for key, figures in columns.items():
            if len(figures) != len(settings.taus):
                fail(f'{key} has {len(figures)} figures for the {len(settings.taus)} taus')
    for name in ('full', 'quick'):
        unknown = [tau for tau in getattr(settings.budgets, name).taus if tau not in settings.taus]
        if unknown:
            fail(f'budgets.{name}.taus {unknown} are not among the taus the paper prints figures for')
    cases = {'case': settings.case, 'tracking_case': settings.tracking_case}
    cases.update({f'table4[{i}].case': case for i, case in enumerate(settings.table4_cases)})
    joints = {}  # per case key: the number of joints its motion drives
    for key, case in cases.items():
        if case.trajectory not in PAPER_TRAJECTORIES:
            fail(f'{key}.trajectory must be one of {list(PAPER_TRAJECTORIES)}, got {case.trajectory}')
        try:
            joints[key] = len(paper_motion_joints(case.trajectory))
        except MotionError as error:
            fail(f'{key}.trajectory {case.trajectory}: {error}')
    needs = {'case': 'Table 3 runs the I (3.2) gains searched there', 'tracking_case': 'the tracking figure '
             'shows its Table 4 episodes'}
    for key, reason in needs.items():
        if cases[key] not in settings.table4_cases:
            fail(f'{key} {cases[key]} must be one of the table4 cases: {reason}')
    if settings.beyond.case != settings.case:
        fail(f'beyond.case {settings.beyond.case} must be case {settings.case}: the front is seeded by the (2.5) and '
             '(3.2) optima searched there, and the robust gains are set beside its (3.2) optimum')
    for controller, procedure in settings.omega_procedure.items():
        for option, values in procedure.disturbance.items():
            if len(values) != joints['case']:
                fail(f'omega_procedure.{controller}.disturbance.{option} has {len(values)} values for the '
                     f'{joints["case"]} joints of trajectory {settings.case.trajectory}')
    _check_runs(settings, cases, joints, fail)
    _check_claims_and_budgets(settings, max(joints.values()), fail)
    _check_beyond(settings.beyond, fail)


def _check_beyond(beyond: Beyond, fail) -> None:
    for tau in beyond.robust.taus:
        if not (math.isfinite(tau) and 0 <= tau <= beyond.case.duration):
            fail(f'beyond.robust.taus: {tau!r} must be within [0, T = {beyond.case.duration:g}] s')
    for scale in beyond.robust.mass_scales:
        _positive(fail, 'beyond.robust.mass_scales', scale)
    for key, values in (('beyond.robust.taus', beyond.robust.taus), ('beyond.robust.mass_scales',
                                                                      beyond.robust.mass_scales),
                        ('beyond.stability_map.delays', beyond.stability_map.delays),
                        ('beyond.stability_map.zetas', beyond.stability_map.zetas)):
        if not values or len(set(values)) != len(values):
            fail(f'{key} must hold at least one value, none twice, got {list(values)}')
    for delay in beyond.stability_map.delays:
        if delay < 0:
            fail(f'beyond.stability_map.delays: {delay} must be a whole number of samples >= 0')
    for zeta in beyond.stability_map.zetas:
        _positive(fail, 'beyond.stability_map.zetas', zeta)


def _positive(fail, key: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        fail(f'{key} must be finite and positive, got {value!r}')


def _check_runs(settings: PaperSettings, cases: dict[str, Case], joints: dict[str, int], fail) -> None:
    """Every episode `ddarm reproduce` runs from `settings` (ddarm.paper.experiments builds the same specs),
    through ddarm.episodes.spec.check_episode as it would be when it ran; a refusal names the key it comes from."""
    seen = set()

    def checked(key: str, build) -> EpisodeSpec:
        try:
            spec = build()
            if spec not in seen:
                check_episode(spec)
                seen.add(spec)
            return spec
        except (DdarmError, ValueError, ArithmeticError) as error:
            fail(f'{key}: {error}')

    def distinct(key: str, names: list[str]) -> None:
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            fail(f'{key} give two episodes the bag name(s) {repeated}: each episode records a bag of its own')

    for controller, delay in settings.delays.items():
        try:
            checked_delay(delay)
        except GainError as error:
            fail(f'delays.{controller}: {error}')
    for key, case in cases.items():
        _positive(fail, f'{key}.duration', case.duration)
        _positive(fail, f'{key}.period', case.period)
    # Bag names (ddarm.paper.experiments) hold τ to 2 decimals, T and Δ as %g.
    distinct('the table4 cases', [f'traj{case.trajectory}-T{case.duration:g}-dt{case.period:g}'
                                  for case in settings.table4_cases])
    distinct('the taus', [f'tau{tau:.2f}' for tau in settings.taus])
    distinct('the stability.periods', [f'dt{period:g}' for period in settings.stability.periods])
    case = settings.case
    for controller in CONTROLLERS:
        # The searches' and Table 4's episodes, but their gains.
        templates = {key: checked(key, lambda: EpisodeSpec(
            controller=controller, trajectory=each.trajectory, duration=each.duration, period=each.period,
            delay=settings.delays[controller]))
            for key, each in cases.items()}
        template = templates['case']
        # Tables 2 and 3: every τ the paper prints (a budget runs some of them), unlimited and limited.
        for i, tau in enumerate(settings.taus):
            for limit in ('none', 'paper'):
                checked(f'taus[{i}]', lambda: dataclasses.replace(template, tau=tau, torque_limit=limit))
        # Section 2: the ω rule's episode, and the procedure's disturbed one.
        omega = settings.omega_rules[controller]
        _positive(fail, f'omega_rules.{controller}', omega)
        checked(f'omega_rules.{controller}', lambda: dataclasses.replace(
            template, **dict(zip(('kp', 'kv'), gains_from_omega(template, omega)))))
        procedure = settings.omega_procedure[controller]
        _positive(fail, f'omega_procedure.{controller}.max_error_deg', procedure.max_error_deg)
        disturbed = checked(f'omega_procedure.{controller}.disturbance',
                            lambda: dataclasses.replace(template, **procedure.disturbance))
        if not np.any(steady_state_error_per_unit_gain(disturbed)[0]):
            fail(f'omega_procedure.{controller}.disturbance {dict(procedure.disturbance)} causes no steady-state '
                 'error: the procedure would have no smallest ω to find')
    # The sampling claim: computed torque at ω for every period, at the case's duration.
    stability = settings.stability
    _positive(fail, 'stability.omega', stability.omega)
    _positive(fail, 'stability.claimed_period', stability.claimed_period)
    kp, kv = omega_rule_computed_torque(joints['case'], stability.omega)
    for i, period in enumerate(stability.periods):
        _positive(fail, f'stability.periods[{i}]', period)
        checked(f'stability.periods[{i}]', lambda: EpisodeSpec(
            controller='computed_torque', kp=kp, kv=kv, trajectory=case.trajectory, duration=case.duration,
            period=period, delay=settings.delays['computed_torque']))


def _check_claims_and_budgets(settings: PaperSettings, joints: int, fail) -> None:
    ratio = settings.claims.table4_I1_ratio
    _positive(fail, 'claims.table4_I1_ratio.low', ratio.low)
    if not (math.isfinite(ratio.high) and ratio.high >= ratio.low):
        fail(f'claims.table4_I1_ratio.high must be finite and at least low = {ratio.low!r}, got {ratio.high!r}')
    # Each search (ddarm.paper.experiments.optimise) is the global search: ddarm.tuning.search.search_gains
    # refuses a budget below its ω-rule starts and their simplices; the robust search has the nominal optimum
    # as one more start, and each point costs an episode per scenario; the front needs its two seeds and a first
    # population.
    search_least = least_budget('global', len(SEARCH_START_OMEGAS), 2 * joints)
    scenarios = len(settings.beyond.robust.taus) * len(settings.beyond.robust.mass_scales)
    for name in ('full', 'quick'):
        budget, key = getattr(settings.budgets, name), f'budgets.{name}'
        if budget.de_popsize < 2:
            fail(f'{key}.de_popsize must be at least 2, got {budget.de_popsize}')
        for part, value, least in (('search_episodes', budget.search_episodes, search_least),
                                   ('robust_episodes', budget.robust_episodes, (search_least + 1) * scenarios),
                                   ('pareto_episodes', budget.pareto_episodes, 2 + DEFAULT_POPULATION)):
            if value < least:
                fail(f'{key}.{part} must be at least {least}, got {value}')
        if not budget.taus:
            fail(f'{key}.taus must hold at least one τ')


def _refuse_huge_integers(data, path: Path, key: str) -> None:
    """An integer beyond a float's range is no setting (and would overflow where a number is read)."""
    if isinstance(data, dict):
        for name, item in data.items():
            _refuse_huge_integers(item, path, f'{key}.{name}' if key else str(name))
    elif isinstance(data, list):
        for i, item in enumerate(data):
            _refuse_huge_integers(item, path, f'{key}[{i}]')
    elif isinstance(data, int) and not isinstance(data, bool) and abs(data) > sys.float_info.max:
        raise SettingsError(f'{path}: {key} is an integer beyond the range of a float')
