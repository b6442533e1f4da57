"""The plant: the arm's continuous dynamics under a torque held over each sampling period (MODEL.md 3, 5, 7)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ddarm.errors import DdarmError
from ddarm.physics.arm import Arm

# RK4 steps per sampling period. 8 keeps the indices within 1e-6 relative of a 40-step
# reference for the ω-rule gains in the paper's settings (test_batch.py shows it). Episodes
# that swing the arm at 100+ rad/s (PD + gravity at ω >= 10 with delay 1, or ω = 20 with
# delay 0) need more: there the error falls as h⁴, 1.6e-3 at 8 steps for ω = 15, delay 1.
DEFAULT_SUBSTEPS = 8
# Beyond these the arm has left any physical motion: the episode has diverged.
DEFAULT_MAX_POSITION = 100.0  # rad
DEFAULT_MAX_VELOCITY = 1000.0  # rad/s
MAX_SUBSTEPS = 10_000


class PlantError(DdarmError, ValueError):
    """A plant option or input that the plant refuses."""


def _joint_vector(name: str, value, dof: int, *, positive: bool = False,
                  non_negative: bool = False) -> np.ndarray | None:
    if value is None:
        return None
    array = np.asarray(value, dtype=float)
    if array.shape != (dof,):
        raise PlantError(f'{name} needs {dof} values (one per joint), got {value!r}')
    if not np.all(np.isfinite(array)):
        raise PlantError(f'{name} must be finite, got {value!r}')
    if positive and np.any(array <= 0):
        raise PlantError(f'{name} must be positive, got {value!r}')
    if non_negative and np.any(array < 0):
        raise PlantError(f'{name} must not be negative, got {value!r}')
    return array


@dataclass(frozen=True)
class PlantOptions:
    """Everything about the plant that is not the arm's rigid-body model.

    Per-joint arrays are None for "none": no torque limit, no friction, no external torque.
    """

    period: float = 0.01
    substeps: int = DEFAULT_SUBSTEPS
    torque_limit: np.ndarray | None = None
    viscous_friction: np.ndarray | None = None
    coulomb_friction: np.ndarray | None = None
    external_torque: np.ndarray | None = None
    max_position: float = DEFAULT_MAX_POSITION
    max_velocity: float = DEFAULT_MAX_VELOCITY

    def __post_init__(self) -> None:
        if not (np.isfinite(self.period) and 0 < self.period <= 1.0):
            raise PlantError(f'period must be in (0, 1] s, got {self.period!r}')
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
            torque_limit=_joint_vector('torque_limit', self.torque_limit, dof, positive=True),
            viscous_friction=_joint_vector('viscous_friction', self.viscous_friction, dof,
                                           non_negative=True),
            coulomb_friction=_joint_vector('coulomb_friction', self.coulomb_friction, dof,
                                           non_negative=True),
            external_torque=_joint_vector('external_torque', self.external_torque, dof),
            max_position=self.max_position, max_velocity=self.max_velocity)


@dataclass
class Plant:
    """The arm's state (q, q̇) at sample n, advanced one sampling period at a time.

    Once the state leaves the physical bounds (or stops being finite) the plant is
    `diverged`: its state stays frozen at the last sample within bounds.
    """

    arm: Arm
    options: PlantOptions
    q: np.ndarray
    v: np.ndarray
    sample: int = 0
    diverged: bool = False
    _zero: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.options = self.options.checked(self.arm.dof)
        self.q = self._state_vector('initial position', self.q)
        self.v = self._state_vector('initial velocity', self.v)
        self._zero = np.zeros(self.arm.dof)

    def _state_vector(self, name: str, value) -> np.ndarray:
        array = np.array(value, dtype=float)
        if array.shape != (self.arm.dof,) or not np.all(np.isfinite(array)):
            raise PlantError(f'{name} must be {self.arm.dof} finite numbers, got {value!r}')
        return array

    @property
    def time(self) -> float:
        return self.sample * self.options.period

    def saturate(self, torque: np.ndarray) -> np.ndarray:
        """The torque the actuators apply for a command: clamped to ±limit, sign kept."""
        limit = self.options.torque_limit
        return torque if limit is None else np.clip(torque, -limit, limit)

    def _external(self, v: np.ndarray) -> np.ndarray:
        """P^z - F(q̇): joint torques other than the actuators' (MODEL.md 2-3)."""
        options = self.options
        torque = self._zero if options.external_torque is None else options.external_torque
        if options.viscous_friction is not None:
            torque = torque - options.viscous_friction * v
        if options.coulomb_friction is not None:
            torque = torque - options.coulomb_friction * np.sign(v)
        return torque

    def _acceleration(self, q: np.ndarray, v: np.ndarray, torque: np.ndarray) -> np.ndarray:
        return self.arm.forward_dynamics(q, v, torque + self._external(v))

    def advance(self, applied_torque: np.ndarray) -> bool:
        """Integrate [t_n, t_{n+1}) under a constant applied torque (zero-order hold).

        Returns False, and freezes the plant as diverged, when the state leaves its bounds.
        Raises PlantError for a torque that is not `dof` finite numbers: nothing is integrated.
        """
        torque = np.asarray(applied_torque, dtype=float)
        if torque.shape != (self.arm.dof,) or not np.all(np.isfinite(torque)):
            raise PlantError(f'sample {self.sample}: torque must be {self.arm.dof} finite numbers, '
                             f'got {applied_torque!r}')
        if self.diverged:
            return False
        h = self.options.period / self.options.substeps
        q, v = self.q, self.v
        with np.errstate(all='ignore'):
            for _ in range(self.options.substeps):
                a1 = self._acceleration(q, v, torque)
                q2, v2 = q + 0.5 * h * v, v + 0.5 * h * a1
                a2 = self._acceleration(q2, v2, torque)
                q3, v3 = q + 0.5 * h * v2, v + 0.5 * h * a2
                a3 = self._acceleration(q3, v3, torque)
                q4, v4 = q + h * v3, v + h * a3
                a4 = self._acceleration(q4, v4, torque)
                q = q + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
                v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        if not self.within_bounds(q, v):
            self.diverged = True
            return False
        self.q, self.v = q, v
        self.sample += 1
        return True

    def within_bounds(self, q: np.ndarray, v: np.ndarray) -> bool:
        return bool(np.all(np.isfinite(q)) and np.all(np.isfinite(v))
                    and np.max(np.abs(q)) <= self.options.max_position
                    and np.max(np.abs(v)) <= self.options.max_velocity)


def disturbed_initial_state(position: np.ndarray, velocity_at_tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3.1) with MODEL.md 7's sign: start at q^d(0) with q̇(0) = -q̇^d(τ), against the motion."""
    return np.array(position, dtype=float), -np.array(velocity_at_tau, dtype=float)
