"""results.json as typed data: what `ddarm reproduce` writes and the report reads (docs/reproduce.md lists the keys).

One definition for both sides: ddarm.paper.experiments builds these objects and writes `to_json()`;
the report takes `Results.from_json`, which refuses a missing or unknown key, a value of the wrong
type, a law or index outside the vocabulary, or a row naming gains that are not there. Each file says
its `schema_version` (SCHEMA_VERSION); a results.json of another version, or of none, is refused by that key
rather than reported wrongly.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ddarm.episodes.indices import INDICES
from ddarm.errors import DdarmError
from ddarm.paper import typed
from ddarm.paper.settings import Controller, Table4Figures

Index = Literal[INDICES]
Vector = tuple[float, ...]
# results.json's layout: raise it with any change to the keys or their meaning. `duration` came within version 2,
# beside `T`, which it renames and which is still written: files with either key (or both) read alike. Version 3
# added each search's `converged` and `certainty`.
SCHEMA_VERSION = 3


class ResultsError(DdarmError, ValueError):
    """Results that do not follow the schema; the text names the key."""


@dataclass(frozen=True)
class RunSettings:
    paper_delays: Mapping[Controller, int]
    search_budget: int
    de_popsize: int
    taus: Vector
    start_omegas: Vector
    pareto_budget: int
    robust_budget: int


@dataclass(frozen=True)
class RestartRow:
    """One CMA-ES run of a global search (ddarm.tuning.search.Restart)."""

    start: str  # the point it started from, e.g. 'point 1 seen (0.123839)'
    popsize: int
    episodes: int
    index: float | None  # its best index; None when every episode of the run diverged
    stopped_by: tuple[str, ...]


@dataclass(frozen=True)
class Search:
    episodes: int
    wall_time_s: float
    episodes_per_s: float
    in_process_index: float
    start_index: float  # the best ω-rule start's index
    method: str
    evolution_generations: int  # differential evolution's generations before the local runs
    restarts: list[RestartRow]
    restarts_within_1_percent: int  # the runs whose best is within 1 % of in_process_index: a confidence figure
    converged: bool | None  # whether the global search's certificate holds (None: a method that gives none)
    certainty: str  # the certificate's one line (ddarm.tuning.search.SearchResult.certainty)


@dataclass(frozen=True)
class GainSet:
    """Gains optimised for `index` in one case; rows name it by `name`."""

    name: str
    controller: Controller
    index: Index
    trajectory: int
    duration: float = typed.aliased('T')
    period: float
    delay: int
    kp: Vector
    kv: Vector
    search: Search


@dataclass(frozen=True)
class TauRow:
    """A Table 2 or Table 3 cell: I1 at one τ; `paper` the paper's figure, None where it prints none."""

    controller: Controller
    tau: float
    limited: bool
    gains: str
    I1: float
    I2: float
    I: float
    diverged: bool
    max_abs_torque: Vector
    torque_limit: Vector  # the paper's, 2 max |P^nom|, whether or not the episode was limited
    within_limits: bool
    bag: str
    paper: float | None


@dataclass(frozen=True)
class Table4Row:
    controller: Controller
    trajectory: int
    duration: float = typed.aliased('T')
    period: float
    delay: int
    gains: str
    kp: Vector
    kv: Vector
    I1: float
    I2: float
    I: float
    diverged: bool
    max_abs_torque: Vector
    torque_limit: Vector
    within_limits: bool
    bag: str
    paper: Table4Figures | None


@dataclass(frozen=True)
class OmegaRuleRow:
    controller: Controller
    omega: float
    kp: Vector
    kv: Vector
    I1: float
    I2: float
    I: float
    diverged: bool
    max_abs_torque: Vector
    torque_limit: Vector
    within_limits: bool
    bag: str


@dataclass(frozen=True)
class OmegaProcedureRow:
    """Section 2's procedure for one law. When no ω passes, omega, kp and kv are None, and so is everything
    after them: there was no episode (the defaults, for building the row before its episode runs)."""

    controller: Controller
    case: str
    max_error_deg: float
    omega_min: float
    omega: float | None
    kp: Vector | None
    kv: Vector | None
    I1: float | None = None
    I2: float | None = None
    I: float | None = None
    bag: str | None = None
    diverged: bool | None = None
    max_abs_torque: Vector | None = None
    torque_limit: Vector | None = None
    within_limits: bool | None = None


@dataclass(frozen=True)
class StabilityRow:
    """One Δ of the sampling claim; the `15` in the keys is the paper's ω (settings: stability.omega)."""

    period: float
    omega_max_stable: float
    omega_15_stable: bool
    I1_at_omega_15: float
    diverged_at_omega_15: bool
    bag: str


@dataclass(frozen=True)
class FrontRow:
    """One point of the I1–I2 front (in-process, batch engine) and its gains."""

    I1: float
    I2: float
    kp: Vector
    kv: Vector


@dataclass(frozen=True)
class ParetoFront:
    """The I1–I2 front of one law in one case (ddarm.tuning.pareto), seeded by that case's I1 and I optima.

    `seeds` names the gain sets that seeded it (results.gains); `seeds_on_front` says whether each is one of
    the front's `front_size` non-dominated episodes."""

    controller: Controller
    trajectory: int
    duration: float = typed.aliased('T')
    period: float
    delay: int
    method: str
    episodes: int
    wall_time_s: float
    front_size: int
    searches: int
    searches_converged: int
    seeds: tuple[str, ...]
    seeds_on_front: tuple[bool, ...]
    front: list[FrontRow]


@dataclass(frozen=True)
class ScenarioRow:
    """One scenario's episode through the ROS graph, scored from its bag, for one gain set."""

    tau: float
    mass_scale: Vector
    gains: Literal['robust', 'nominal']
    I1: float
    I2: float
    I: float
    diverged: bool
    bag: str


@dataclass(frozen=True)
class Robustness:
    """Gains tuned for the `objective` (worst or mean) of I (3.2) over the scenarios, beside the nominal optimum
    (`nominal`, a results.gains name), each run on every scenario through the ROS graph (`rows`)."""

    controller: Controller
    trajectory: int
    duration: float = typed.aliased('T')
    period: float
    delay: int
    objective: Literal['worst', 'mean']
    kp: Vector
    kv: Vector
    nominal: str
    search: Search
    rows: list[ScenarioRow]


@dataclass(frozen=True)
class BoundaryRow:
    """ωΔ* of the sampled loop for a delay d and damping ratio ζ (ddarm.control.stability)."""

    delay: int
    zeta: float
    omega_delta: float


@dataclass(frozen=True)
class Section2:
    omega_rules: list[OmegaRuleRow] = field(default_factory=list)
    omega_procedure: list[OmegaProcedureRow] = field(default_factory=list)
    stability: list[StabilityRow] = field(default_factory=list)


@dataclass(frozen=True)
class Claim:
    claim: str
    reproduced: bool
    evidence: str


@dataclass
class Results:
    """Every cell of the reproduction. Filled as the experiments run: not frozen, its lists grow, and
    `claims` and `wall_time_s` come last. `schema_version` is written first, and always SCHEMA_VERSION."""

    schema_version: int = field(default=SCHEMA_VERSION, kw_only=True)
    command: str
    quick: bool
    started: str
    settings: RunSettings
    gains: list[GainSet] = field(default_factory=list)
    table2: list[TauRow] = field(default_factory=list)
    table3: list[TauRow] = field(default_factory=list)
    table4: list[Table4Row] = field(default_factory=list)
    section2: Section2 = field(default_factory=Section2)
    pareto: ParetoFront | None = None
    robust: Robustness | None = None
    stability_map: list[BoundaryRow] = field(default_factory=list)
    reconstruction: tuple[str, ...] = ()
    claims: list[Claim] = field(default_factory=list)
    wall_time_s: float | None = None

    def to_json(self) -> dict:
        return typed.write(self)

    @classmethod
    def from_json(cls, data, source: str = 'results') -> Results:
        """`data` (results.json's object) as Results; ResultsError names `source` and the key refused."""
        # The version first: another version's keys would otherwise be refused one by one, never by what they are.
        if isinstance(data, dict):
            if 'schema_version' not in data:
                raise ResultsError(f"{source}: missing key 'schema_version' (results.json of schema_version "
                                   f'{SCHEMA_VERSION} holds it: this file is from before the schema had versions)')
            version = data['schema_version']
            if isinstance(version, bool) or version != SCHEMA_VERSION:
                raise ResultsError(f'{source}: schema_version is {version!r}: this ddarm reads results.json of '
                                   f'schema_version {SCHEMA_VERSION} only')
        results = typed.read(cls, data, source, ResultsError)
        names = [gains.name for gains in results.gains]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise ResultsError(f'{source}: gains[{i}].name {name!r} names two gain sets')
        for part in ('table2', 'table3', 'table4'):
            for i, row in enumerate(getattr(results, part)):
                if row.gains not in names:
                    raise ResultsError(f'{source}: {part}[{i}].gains names {row.gains!r}, which is not in '
                                       'results.gains')
        named = [('robust.nominal', results.robust.nominal)] if results.robust else []
        named += [(f'pareto.seeds[{i}]', name) for i, name in enumerate(results.pareto.seeds if results.pareto else ())]
        for key, name in named:
            if name not in names:
                raise ResultsError(f'{source}: {key} names {name!r}, which is not in results.gains')
        return results

    @classmethod
    def load(cls, path: Path | str) -> Results:
        """results.json at `path`."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise ResultsError(f'{path}: cannot read the results: {error}') from error
        return cls.from_json(data, str(path))

    def gain_set(self, name: str) -> GainSet:
        return next(gains for gains in self.gains if gains.name == name)
