"""PD + gravity (2.1) and computed torque (2.6)/(2.11), sampled with a compute delay of d samples (MODEL.md 5).

The law functions broadcast over leading axes (the joint is the last axis), so a
batch of gain vectors evaluates in one call.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ddarm.errors import DdarmError
from ddarm.physics.arm import Arm

CONTROLLERS = ('pd_gravity', 'computed_torque')
MAX_DELAY = 100


class GainError(DdarmError, ValueError):
    """Gains or a delay that a controller refuses; the old ones stay in force."""


def checked_gains(kp, kv, dof: int) -> tuple[np.ndarray, np.ndarray]:
    """K_p, K_v diagonals as arrays: `dof` finite positive numbers each, or GainError."""
    checked = []
    for name, gains in (('kp', kp), ('kv', kv)):
        try:
            array = np.array(gains, dtype=float)
        except (TypeError, ValueError) as error:
            raise GainError(f'{name} must be numbers, got {gains!r}') from error
        if array.shape != (dof,):
            raise GainError(f'{name} needs {dof} values (one per joint), got {gains!r}')
        if not np.all(np.isfinite(array)) or np.any(array <= 0):
            raise GainError(f'{name} must be finite and positive, got {gains!r}')
        checked.append(array)
    return checked[0], checked[1]


def checked_delay(delay) -> int:
    if isinstance(delay, bool) or not isinstance(delay, (int, np.integer)) or not 0 <= delay <= MAX_DELAY:
        raise GainError(f'compute delay must be a whole number of samples in [0, {MAX_DELAY}], got {delay!r}')
    return int(delay)


def pd_gravity(kp: np.ndarray, kv: np.ndarray, error: np.ndarray, error_rate: np.ndarray,
               gravity_at_reference: np.ndarray) -> np.ndarray:
    """(2.1): P = K_p e + K_v ė + Ĝ(q^d)."""
    return kp * error + kv * error_rate + gravity_at_reference


def computed_torque(mass_matrix: np.ndarray, bias: np.ndarray, kp: np.ndarray, kv: np.ndarray,
                    error: np.ndarray, error_rate: np.ndarray,
                    reference_acceleration: np.ndarray) -> np.ndarray:
    """(2.6): P = M̂(q)(q̈^d + K_p e + K_v ė) + V̂(q, q̇) + Ĝ(q) + F̂(q, q̇); `bias` = V̂ + Ĝ + F̂.

    The paper's (2.11) swaps K_p and K_v by a misprint; (2.6) is meant (MODEL.md 5).
    """
    command = reference_acceleration + kp * error + kv * error_rate
    return np.einsum('...ij,...j->...i', mass_matrix, command) + bias


@dataclass(frozen=True)
class Measurement:
    """What the controller reads at one sample instant: the state and the programmed motion there."""

    q: np.ndarray
    v: np.ndarray
    q_ref: np.ndarray
    v_ref: np.ndarray

    @property
    def error(self) -> np.ndarray:
        """e = q^d - q."""
        return self.q_ref - self.q

    @property
    def error_rate(self) -> np.ndarray:
        """ė = q̇^d - q̇."""
        return self.v_ref - self.v


@dataclass(frozen=True)
class ReferencePoint:
    """The programmed motion at the instant t_n the torque is applied from."""

    q: np.ndarray
    v: np.ndarray
    a: np.ndarray


class DelayBuffer:
    """Hands back the measurement of sample n - d, or that of sample 0 while n < d (MODEL.md 5)."""

    def __init__(self, delay: int) -> None:
        self.delay = checked_delay(delay)
        self._history: deque = deque(maxlen=self.delay + 1)

    def push(self, measurement):
        """Store sample n's measurement; return the one the torque for sample n uses."""
        self._history.append(measurement)
        return self._history[0]

    def clear(self) -> None:
        self._history.clear()

    def __len__(self) -> int:
        return len(self._history)


class PDGravityLaw:
    """Fig. 1: PD on the errors plus the model's gravity at the programmed position."""

    name = 'pd_gravity'

    def __init__(self, model: Arm, kp, kv) -> None:
        self.model = model
        self.kp, self.kv = checked_gains(kp, kv, model.dof)

    def set_gains(self, kp, kv) -> None:
        self.kp, self.kv = checked_gains(kp, kv, self.model.dof)

    def torque(self, measured: Measurement, reference: ReferencePoint) -> np.ndarray:
        return pd_gravity(self.kp, self.kv, measured.error, measured.error_rate,
                          self.model.gravity(reference.q))


class ComputedTorqueLaw:
    """Fig. 2: the model's inverse dynamics at the measured state, with friction F̂ if the model has it."""

    name = 'computed_torque'

    def __init__(self, model: Arm, kp, kv, viscous_friction=None, coulomb_friction=None) -> None:
        self.model = model
        self.kp, self.kv = checked_gains(kp, kv, model.dof)
        self.viscous_friction = viscous_friction
        self.coulomb_friction = coulomb_friction

    def set_gains(self, kp, kv) -> None:
        self.kp, self.kv = checked_gains(kp, kv, self.model.dof)

    def friction(self, v: np.ndarray) -> np.ndarray:
        """F̂(q̇): viscous plus Coulomb, as the plant's model of friction."""
        torque = np.zeros_like(v)
        if self.viscous_friction is not None:
            torque = torque + self.viscous_friction * v
        if self.coulomb_friction is not None:
            torque = torque + self.coulomb_friction * np.sign(v)
        return torque

    def torque(self, measured: Measurement, reference: ReferencePoint) -> np.ndarray:
        bias = self.model.bias(measured.q, measured.v) + self.friction(measured.v)
        return computed_torque(self.model.mass_matrix(measured.q), bias, self.kp, self.kv,
                               measured.error, measured.error_rate, reference.a)


class SampledController:
    """A law run on samples: P_n from the measurement of sample n - d and the reference at t_n."""

    def __init__(self, law: PDGravityLaw | ComputedTorqueLaw, delay: int) -> None:
        self.law = law
        self.buffer = DelayBuffer(delay)

    @property
    def delay(self) -> int:
        return self.buffer.delay

    def set_delay(self, delay: int) -> None:
        """A new delay takes effect on a fresh history (as at an episode's start)."""
        self.buffer = DelayBuffer(delay)

    def step(self, measurement: Measurement, reference: ReferencePoint) -> np.ndarray:
        return self.law.torque(self.buffer.push(measurement), reference)

    def reset(self) -> None:
        """A new episode: forget the measurements of the last one."""
        self.buffer.clear()


def make_law(controller: str, model: Arm, kp, kv, viscous_friction=None, coulomb_friction=None):
    """The law named `controller` (one of CONTROLLERS) on the controller's model."""
    if controller == 'pd_gravity':
        return PDGravityLaw(model, kp, kv)
    if controller == 'computed_torque':
        return ComputedTorqueLaw(model, kp, kv, viscous_friction, coulomb_friction)
    raise GainError(f'controller must be one of {CONTROLLERS}, got {controller!r}')
