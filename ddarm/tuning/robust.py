"""Robust tuning: the grid of scenarios a gain set must do well on, and each scenario's indices for given gains.

A scenario is the template episode with three of its fields replaced: τ of the initial disturbance (3.1), the
plant's link-mass scale against the controller's model, and a constant external torque P^z. The grid is their
Cartesian product; an axis not given is the template's own value. A robust search minimises the worst (max)
or the mean of the index over the grid (ddarm.tuning.search).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddarm.episodes.engine import BatchRunner, run_episode
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, arm_joints, check_episode
from ddarm.errors import DdarmError
from ddarm.motion.programmed import MotionError, checked_tau
from ddarm.physics.arm import default_urdf_path

# How a point's indices over the scenarios become the one value a search minimises: their max, or their mean.
AGGREGATES = ('worst', 'mean')


class RobustError(DdarmError, ValueError):
    """A scenario grid that cannot be run, named by its `ddarm tune` option."""


def _described(values) -> str:
    return ','.join(f'{float(value):g}' for value in np.atleast_1d(values))


def _no_repeats(option: str, values: list) -> None:
    seen = set()
    for value in values:
        key = value if isinstance(value, float) else tuple(value)
        if key in seen:
            raise RobustError(f'{option}: {_described(value)} is given twice (each value is one scenario)')
        seen.add(key)


def _checked_taus(taus, duration: float) -> list[float]:
    checked = []
    for tau in taus:
        try:
            checked.append(float(checked_tau(float(tau), duration)))
        except (MotionError, TypeError, ValueError) as error:
            raise RobustError(f'--robust-tau {tau!r}: τ must be a number within [0, T = {duration:g}] s') from error
    return checked


def _per_joint(option: str, values, joints: tuple[str, ...], *, scalar_for_all: bool, positive: bool) -> tuple:
    try:
        array = np.atleast_1d(np.array(values, dtype=float))
    except (TypeError, ValueError) as error:
        raise RobustError(f'{option}: {values!r} is not a number') from error
    dof, given = len(joints), _described(array)
    if not np.all(np.isfinite(array)) or (positive and not np.all(array > 0)):
        raise RobustError(f'{option} {given}: every value must be finite' + (' and positive' if positive else ''))
    if scalar_for_all and array.shape == (1,):
        array = np.full(dof, array[0])
    if array.shape != (dof,):
        raise RobustError(f'{option} {given}: {array.size} value{"s" if array.size != 1 else ""} for an arm of '
                          f'{dof} joints ({", ".join(joints)}): give {"one, or " if scalar_for_all else ""}{dof}, '
                          f'comma-separated')
    return tuple(float(value) for value in array)


def scenario_grid(template: EpisodeSpec, taus=None, mass_scales=None, external_torques=None, urdfs=None
                  ) -> tuple[EpisodeSpec, ...]:
    """The template with τ, mass scale and P^z replaced by each combination of the values given: the scenarios.

    Args:
        template: the nominal episode; its own τ, mass_scale and external_torque are the axes not given.
        taus: τ of (3.1) in s, each within [0, T].
        mass_scales: plant link mass / model link mass, each one number (every link) or one per joint.
        external_torques: constant joint torques P^z in N m (N for a prismatic joint), each one per joint.
        urdfs: the plant's URDF (absolute paths), the controller's model staying the template's.

    Scenarios in the order τ, then mass scale, then P^z, then URDF (the last varying fastest). Raises RobustError
    naming the option (--robust-tau, --robust-mass-scale, --robust-external-torque, --robust-urdf) of a value that
    cannot be run.
    """
    joints = arm_joints(template)[0]
    tau_axis = [template.tau] if taus is None else _checked_taus(taus, template.duration)
    mass_axis = [template.mass_scale] if mass_scales is None else [
        _per_joint('--robust-mass-scale', scale, joints, scalar_for_all=True, positive=True) for scale in mass_scales]
    torque_axis = [template.external_torque] if external_torques is None else [
        _per_joint('--robust-external-torque', torque, joints, scalar_for_all=False, positive=False)
        for torque in external_torques]
    urdf_axis = [template.urdf] if urdfs is None else list(urdfs)
    for option, axis, given in (('--robust-tau', tau_axis, taus), ('--robust-mass-scale', mass_axis, mass_scales),
                                ('--robust-external-torque', torque_axis, external_torques),
                                ('--robust-urdf', urdf_axis, urdfs)):
        if given is not None:
            if not axis:
                raise RobustError(f'{option}: give at least one value')
            _no_repeats(option, axis)
    # The plant's URDF varies; the controller's model stays the template's.
    model = (template.model_urdf or template.urdf or str(default_urdf_path())) if urdfs is not None \
        else template.model_urdf
    scenarios = []
    for tau, mass_scale, external_torque, urdf in itertools.product(tau_axis, mass_axis, torque_axis, urdf_axis):
        scenario = dataclasses.replace(template, tau=tau, mass_scale=mass_scale, external_torque=external_torque,
                                       urdf=urdf, model_urdf=model)
        try:
            check_episode(scenario)
        except EpisodeError as error:
            raise RobustError(f'the scenario {describe_scenario(scenario, len(joints))}: {error}') from error
        scenarios.append(scenario)
    return tuple(scenarios)


def scenario_record(scenario: EpisodeSpec, dof: int) -> dict:
    """What defines the scenario, for the JSON: τ (s), the mass scale per joint, P^z per joint (N m) or None."""
    return {'tau': scenario.tau,
            'mass_scale': list(scenario.mass_scale) if scenario.mass_scale is not None else [1.0] * dof,
            'external_torque': list(scenario.external_torque) if scenario.external_torque is not None else None,
            'urdf': scenario.urdf}


def describe_scenario(scenario: EpisodeSpec, dof: int) -> str:
    """The scenario in one phrase: `τ = 0.1 s, mass scale 1.2, P^z 0,20,5 N m`."""
    record = scenario_record(scenario, dof)
    scale = record['mass_scale']
    torque = record['external_torque']
    plant = '' if scenario.model_urdf is None else f", plant {Path(scenario.urdf or default_urdf_path()).name}"
    return (f"τ = {record['tau']:g} s, mass scale {_described(scale[:1] if len(set(scale)) == 1 else scale)}, "
            f"P^z {'none' if torque is None else _described(torque) + ' N m'}{plant}")


@dataclass(frozen=True)
class ScenarioBatch:
    """Scenarios that one batch call of the engine runs together: they differ only in τ and the mass scale,
    which the engine varies per member.

    `members` are the scenarios' positions in the grid; `taus` (G,) and `mass_scales` (G, n) theirs.
    """

    template: EpisodeSpec
    runner: BatchRunner  # the template's batches, planned once for the whole search
    members: tuple[int, ...]
    taus: np.ndarray
    mass_scales: np.ndarray


def scenario_batches(scenarios: tuple[EpisodeSpec, ...]) -> tuple[ScenarioBatch, ...]:
    """The scenarios grouped into as few batch calls as the engine allows: one per distinct rest of the spec."""
    groups: dict[EpisodeSpec, list[int]] = {}
    for position, scenario in enumerate(scenarios):
        groups.setdefault(dataclasses.replace(scenario, tau=0.0, mass_scale=None), []).append(position)
    batches = []
    for members in groups.values():
        template = scenarios[members[0]]
        runner = BatchRunner(template)
        dof = runner.dof
        batches.append(ScenarioBatch(
            template, runner, tuple(members), np.array([scenarios[m].tau for m in members], dtype=float),
            np.array([scenarios[m].mass_scale or (1.0,) * dof for m in members], dtype=float)))
    return tuple(batches)


def scenario_indices(scenarios: tuple[EpisodeSpec, ...], kp, kv) -> list[dict]:
    """Each scenario's I1, I2, I and whether it diverged, with gains kp, kv: each scenario run alone (run_episode).

    A diverged scenario's indices cover only its samples before the divergence.
    """
    indices = []
    for scenario in scenarios:
        episode = run_episode(dataclasses.replace(scenario, kp=tuple(map(float, kp)), kv=tuple(map(float, kv))))
        indices.append({**episode.indices(), 'diverged': bool(episode.diverged[0])})
    return indices


@dataclass(frozen=True)
class ScenarioScores:
    """One gain set's indices on every scenario (each run alone), and their worst and mean for `index_name`."""

    kp: np.ndarray
    kv: np.ndarray
    index_name: str
    per_scenario: list[dict]  # scenario_indices

    @property
    def diverged(self) -> bool:
        return any(scores['diverged'] for scores in self.per_scenario)

    @property
    def worst(self) -> float | None:
        """The largest index over the scenarios; None if any diverged (its index would understate it)."""
        return None if self.diverged else max(scores[self.index_name] for scores in self.per_scenario)

    @property
    def mean(self) -> float | None:
        """The mean index over the scenarios; None if any diverged."""
        return None if self.diverged else float(np.mean([scores[self.index_name] for scores in self.per_scenario]))

    def aggregate(self, how: str) -> float | None:
        """`worst` or `mean`."""
        return self.worst if how == 'worst' else self.mean

    def to_dict(self) -> dict:
        return {'kp': self.kp.tolist(), 'kv': self.kv.tolist(), 'per_scenario': self.per_scenario,
                'worst': self.worst, 'mean': self.mean}


def scenario_scores(scenarios: tuple[EpisodeSpec, ...], kp, kv, index_name: str) -> ScenarioScores:
    """The gains kp, kv scored on every scenario."""
    return ScenarioScores(np.array(kp, dtype=float), np.array(kv, dtype=float), index_name,
                          scenario_indices(scenarios, kp, kv))
