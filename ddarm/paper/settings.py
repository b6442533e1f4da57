"""The paper's settings, read from data/settings.yaml into frozen dataclasses.

The file holds everything that is the paper's rather than the code's: the delays, the cases, the τ
grid, the published figures of Tables 2-4, section 2's cases, the budgets, the reconstruction notes.
Beyond the types (ddarm.paper.typed), the loader refuses settings that would fail only deep into a
run: a law or τ without its figures, a case on a motion that does not exist, a disturbance with a
value per joint for another arm.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from collections.abc import Mapping
from typing import Literal

import yaml

from ddarm.control.laws import CONTROLLERS
from ddarm.errors import DdarmError
from ddarm.motion.files import DataLoader
from ddarm.motion.programmed import PAPER_TRAJECTORIES, paper_trajectory
from ddarm.paper import typed

SETTINGS_PATH = Path(__file__).resolve().parent / 'data' / 'settings.yaml'

Controller = Literal[CONTROLLERS]
# The episode options section 2's procedure may disturb (ddarm.episodes.spec.EpisodeSpec fields).
Disturbance = Literal['external_torque', 'mass_scale']


class SettingsError(DdarmError, ValueError):
    """Paper settings that cannot be run; the text names the file and the key."""


@dataclass(frozen=True)
class Case:
    """One experiment's motion and sampling: a paper trajectory, T and Δ in s."""

    trajectory: int
    T: float
    period: float


@dataclass(frozen=True)
class Budget:
    """How hard the searches try (episodes per search, CMA-ES population) and the τ run through ROS."""

    search_episodes: int
    cma_popsize: int
    taus: tuple[float, ...]

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
class Stability:
    """The claim that computed torque at ω stays stable for every Δ ≤ claimed_period, and the Δ run."""

    omega: float
    claimed_period: float
    periods: tuple[float, ...]


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
    budgets: Budgets
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
        document = yaml.load(path.read_text(), Loader=DataLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise SettingsError(f'{path}: cannot read the settings: {error}') from error
    settings = typed.read(PaperSettings, document, str(path), SettingsError)
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
    for key, case in cases.items():
        if case.trajectory not in PAPER_TRAJECTORIES:
            fail(f'{key}.trajectory must be one of {list(PAPER_TRAJECTORIES)}, got {case.trajectory}')
    needs = {'case': 'Table 3 runs the I (3.2) gains searched there', 'tracking_case': 'the tracking figure '
             'shows its Table 4 episodes'}
    for key, reason in needs.items():
        if cases[key] not in settings.table4_cases:
            fail(f'{key} {cases[key]} must be one of the table4 cases: {reason}')
    joints = paper_trajectory(settings.case.trajectory, settings.case.T).dof
    for controller, procedure in settings.omega_procedure.items():
        for option, values in procedure.disturbance.items():
            if len(values) != joints:
                fail(f'omega_procedure.{controller}.disturbance.{option} has {len(values)} values for the '
                     f'{joints} joints of trajectory {settings.case.trajectory}')
