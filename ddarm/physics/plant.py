"""The plant: the arm's continuous dynamics under a torque held over each sampling period (spec §3, §5, §7).

`advance` is the one definition of the sampled plant step (hold, integration, divergence) and
`saturate` of the actuators' limit: the batch engine runs them for many episodes at once, the
plant node (through `Plant`) for one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ddarm.arrays import per_joint
from ddarm.errors import DdarmError
from ddarm.physics.dynamics import Chain, cached_njit, compiled_dynamics, typed_entry
from ddarm.samples import DEFAULT_PERIOD, PERIOD_RANGE

# RK4 steps per sampling period. 8 keeps the indices within 1e-6 relative of a 40-step
# reference for the ω-rule gains in the paper's settings (test_batch.py shows it). Episodes
# that swing the arm at 100+ rad/s (PD + gravity at ω >= 10 with delay 1, or ω = 20 with
# delay 0) need more: there the error falls as h⁴, 1.6e-3 at 8 steps for ω = 15, delay 1.
DEFAULT_SUBSTEPS = 8
# Beyond these the arm has left any physical motion: the episode has diverged.
DEFAULT_MAX_POSITION = 100.0  # rad
DEFAULT_MAX_VELOCITY = 1000.0  # rad/s
MAX_SUBSTEPS = 10_000
# Sampling periods the nodes accept, s (a timer of ROS); in-process episodes take any period of PERIOD_RANGE.
NODE_PERIOD_RANGE = (1e-4, 1.0)


class PlantError(DdarmError, ValueError):
    """A plant option or input that the plant refuses."""


def checked_mass_scale(values, dof: int) -> np.ndarray:
    """The plant's link masses (and moments) against the model's: `dof` finite positive factors."""
    return per_joint('mass_scale', values, dof, PlantError, positive=True)


def _optional(name: str, values, dof: int, **rule) -> np.ndarray | None:
    return None if values is None else per_joint(name, values, dof, PlantError, **rule)


@dataclass(frozen=True)
class PlantOptions:
    """Everything about the plant that is not the arm's rigid-body model.

    Per-joint arrays are None for "none": no torque limit, no friction beyond the URDF's <dynamics>, no external
    torque.
    """

    period: float = DEFAULT_PERIOD
    substeps: int = DEFAULT_SUBSTEPS
    torque_limit: np.ndarray | None = None
    viscous_friction: np.ndarray | None = None
    coulomb_friction: np.ndarray | None = None
    external_torque: np.ndarray | None = None
    max_position: float = DEFAULT_MAX_POSITION
    max_velocity: float = DEFAULT_MAX_VELOCITY

    def __post_init__(self) -> None:
        if not (np.isfinite(self.period) and PERIOD_RANGE[0] <= self.period <= PERIOD_RANGE[1]):
            raise PlantError(f'period must be within [{PERIOD_RANGE[0]:g}, {PERIOD_RANGE[1]:g}] s, '
                             f'got {self.period!r}')
        if not (isinstance(self.substeps, (int, np.integer)) and 1 <= self.substeps <= MAX_SUBSTEPS):
            raise PlantError(f'substeps must be an integer in [1, {MAX_SUBSTEPS}], got {self.substeps!r}')
        for name in ('max_position', 'max_velocity'):
            bound = getattr(self, name)
            if not (np.isfinite(bound) and bound > 0):
                raise PlantError(f'{name} must be finite and positive, got {bound!r}')

    def checked(self, dof: int) -> PlantOptions:
        """These options with every per-joint array validated for a `dof`-joint arm."""
        return PlantOptions(
            period=self.period, substeps=self.substeps,
            torque_limit=_optional('torque_limit', self.torque_limit, dof, positive=True),
            viscous_friction=_optional('viscous_friction', self.viscous_friction, dof, non_negative=True),
            coulomb_friction=_optional('coulomb_friction', self.coulomb_friction, dof, non_negative=True),
            external_torque=_optional('external_torque', self.external_torque, dof),
            max_position=self.max_position, max_velocity=self.max_velocity)

    def compiled(self, chain: Chain) -> tuple:
        """The options as the compiled step of `chain`'s plant reads them: its joints' friction (the URDF's and
        these options' beyond it, Chain.joint_friction), zeros for no external torque."""
        external = np.zeros(chain.dof) if self.external_torque is None else self.external_torque
        viscous, coulomb = chain.joint_friction(self.viscous_friction, self.coulomb_friction)
        return (*(np.ascontiguousarray(values, dtype=float) for values in (external, viscous, coulomb)),
                float(self.period), int(self.substeps), float(self.max_position), float(self.max_velocity))


def beyond_bounds(q=None, v=None, max_position: float = DEFAULT_MAX_POSITION,
                  max_velocity: float = DEFAULT_MAX_VELOCITY) -> bool:
    """Whether a state (q, q̇; either may be None, unknown) has left the bounds within which `advance` keeps the
    plant: the divergence rule applied to states no ddarm plant checked, such as a recording's."""
    return bool((q is not None and not np.all(np.abs(q) <= max_position))
                or (v is not None and not np.all(np.abs(v) <= max_velocity)))


# The compiled functions keep episodes on the last axis ("lanes"): see ddarm.physics.dynamics.
@cached_njit(inline='always')
def saturate(command, limit, applied, lanes):
    """The torque the actuators apply: each command clamped to ±limit (inf: no limit), sign kept."""
    for i in range(command.shape[0]):
        for b in range(lanes):
            applied[i, b] = min(max(command[i, b], -limit[i, b]), limit[i, b])


@cached_njit(inline='always')
def _plant_load(applied, external_torque, viscous_friction, coulomb_friction, v, load, lanes):
    """P + P^z - F(q̇): the actuators' torque plus the plant's other joint torques (spec §3)."""
    for i in range(v.shape[0]):
        for b in range(lanes):
            load[i, b] = applied[i, b] + (external_torque[i] - viscous_friction[i] * v[i, b]
                                          - coulomb_friction[i] * np.sign(v[i, b]))


@cached_njit(inline='always')
def step_workspace(n, lanes):
    """Scratch arrays for `advance`: the joint torques and the RK4 stages."""
    return (np.empty((n, lanes)), np.empty((n, lanes)), np.empty((n, lanes)), np.empty((n, lanes)),
            np.empty((4, n, lanes)), np.empty((4, n, lanes)))


@cached_njit()
def advance(forward_dynamics, mass_scale, options, applied, q, v, within, scratch, lanes):
    """Integrate [t_n, t_{n+1}) under the held torque `applied` (RK4 in `substeps` steps; spec §3, §5, §11).

    `forward_dynamics` is the plant's (Dynamics.forward_dynamics), its links scaled by `mass_scale`.

    Each lane whose new state is finite and within the bounds takes it (within[b] = True); any
    other keeps its state of t_n, frozen as the last one within bounds (within[b] = False; spec §12).
    """
    external_torque, viscous_friction, coulomb_friction, period, substeps, max_position, max_velocity = options
    load, qn, vn, qs, stage_v, stage_a = scratch
    n = q.shape[0]
    h = period / substeps
    qn[:], vn[:] = q, v
    for _ in range(substeps):
        qs[:], stage_v[0] = qn, vn
        for stage in range(4):
            vs = stage_v[stage]
            _plant_load(applied, external_torque, viscous_friction, coulomb_friction, vs, load, lanes)
            forward_dynamics(mass_scale, qs, vs, load, stage_a[stage], lanes)
            if stage < 3:
                step = h if stage == 2 else 0.5 * h
                for i in range(n):
                    for b in range(lanes):
                        qs[i, b] = qn[i, b] + step * vs[i, b]
                        stage_v[stage + 1, i, b] = vn[i, b] + step * stage_a[stage, i, b]
        for i in range(n):
            for b in range(lanes):
                qn[i, b] = qn[i, b] + h / 6.0 * (stage_v[0, i, b] + 2.0 * stage_v[1, i, b]
                                                 + 2.0 * stage_v[2, i, b] + stage_v[3, i, b])
                vn[i, b] = vn[i, b] + h / 6.0 * (stage_a[0, i, b] + 2.0 * stage_a[1, i, b]
                                                 + 2.0 * stage_a[2, i, b] + stage_a[3, i, b])
    for b in range(lanes):
        inside = True
        for i in range(n):
            inside = (inside and np.isfinite(qn[i, b]) and np.isfinite(vn[i, b])
                      and abs(qn[i, b]) <= max_position and abs(vn[i, b]) <= max_velocity)
        within[b] = inside
        if inside:
            for i in range(n):
                q[i, b], v[i, b] = qn[i, b], vn[i, b]


@cached_njit()
def _advance_one(forward_dynamics, mass_scale, options, applied, q, v):
    """`advance` for one episode, its workspace made here: the plant node's step."""
    within = np.empty(1, dtype=np.bool_)
    advance(forward_dynamics, mass_scale, options, applied, q, v, within, step_workspace(q.shape[0], 1), 1)
    return within[0]


class SampledPlant(Protocol):
    """What an episode's loop asks of a plant, ddarm's (`Plant`) or a robot's (MujocoPlant): the state at sample n,
    the torque the actuators apply for a command, and the period after it under that torque held."""

    q: np.ndarray
    v: np.ndarray

    def saturate(self, command: np.ndarray) -> np.ndarray: ...

    def advance(self, applied_torque: np.ndarray) -> bool: ...


class Plant:
    """One episode's plant: the state (q, q̇) at sample n, advanced one sampling period at a time.

    Once the state leaves the physical bounds (or stops being finite) the plant is `diverged`:
    its state stays frozen at the last sample within bounds. `mass_scale` scales each link of
    the plant against `chain` (the model): spec §2's plant/model mismatch.
    """

    def __init__(self, chain: Chain, options: PlantOptions, q, v, mass_scale=None) -> None:
        dof = chain.dof
        self.dof = dof
        self.options = options.checked(dof)
        self._forward_dynamics = compiled_dynamics(chain).forward_dynamics
        self._compiled_options = self.options.compiled(chain)
        scale = np.ones(dof) if mass_scale is None else checked_mass_scale(mass_scale, dof)
        self._mass_scale = np.ascontiguousarray(scale[:, None])
        limit = self.options.torque_limit
        self._limit = np.full((dof, 1), np.inf) if limit is None else np.ascontiguousarray(limit[:, None])
        self._q = per_joint('initial position', q, dof, PlantError)[:, None].copy()
        self._v = per_joint('initial velocity', v, dof, PlantError)[:, None].copy()
        self._advance_one = typed_entry(_advance_one, self._forward_dynamics, self._mass_scale,
                                        self._compiled_options, np.zeros((dof, 1)), self._q, self._v)
        self.sample = 0
        self.diverged = False

    @property
    def q(self) -> np.ndarray:
        return self._q[:, 0].copy()

    @property
    def v(self) -> np.ndarray:
        return self._v[:, 0].copy()

    @property
    def time(self) -> float:
        return self.sample * self.options.period

    def saturate(self, command: np.ndarray) -> np.ndarray:
        """The torque the actuators apply for a command (`saturate`).

        Raises PlantError for a command that is not `dof` numbers of shape (dof,): the compiled
        clamp reads `dof` values without bounds checks. Values are not checked: a NaN passes
        through as NaN (`advance` refuses it), as the nodes only pass commands checked finite.
        """
        try:
            values = np.asarray(command, dtype=float)
        except (TypeError, ValueError) as error:
            raise PlantError(f'sample {self.sample}: command must be {self.dof} numbers, got {command!r}') from error
        if values.shape != (self.dof,):
            raise PlantError(f'sample {self.sample}: command must be {self.dof} numbers of shape ({self.dof},), '
                             f'got shape {values.shape}: {command!r}')
        applied = np.empty((self.dof, 1))
        saturate(np.ascontiguousarray(values[:, None]), self._limit, applied, 1)
        return applied[:, 0]

    def advance(self, applied_torque: np.ndarray) -> bool:
        """Integrate [t_n, t_{n+1}) under a constant applied torque (zero-order hold).

        Returns False, and freezes the plant as diverged, when the state leaves its bounds.
        Raises PlantError for a torque that is not `dof` finite numbers: nothing is integrated.
        """
        torque = np.asarray(applied_torque, dtype=float)
        if torque.shape != (self.dof,) or not all(map(math.isfinite, torque.tolist())):  # np.isfinite: 6× the time
            raise PlantError(f'sample {self.sample}: torque must be {self.dof} finite numbers, '
                             f'got {applied_torque!r}')
        if self.diverged:
            return False
        if not self._advance_one(self._forward_dynamics, self._mass_scale, self._compiled_options,
                                 np.ascontiguousarray(torque[:, None]), self._q, self._v):
            self.diverged = True
            return False
        self.sample += 1
        return True


def warm_up(chain: Chain) -> None:
    """Load the compiled step (from numba's cache, or compile it) now, not at an episode's first sample."""
    plant = Plant(chain, PlantOptions(), np.zeros(chain.dof), np.zeros(chain.dof))
    plant.advance(plant.saturate(np.zeros(chain.dof)))
