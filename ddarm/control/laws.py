"""The two sampled control laws of section 2 and their compute delay (spec §5).

The compiled functions are the one definition of each law and of the delay: the batch engine
runs them for many episodes at once (episodes on the last axis, "lanes"), the controller nodes
for one through `SampledController`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ddarm.arrays import per_joint
from ddarm.errors import DdarmError
from ddarm.physics.arm import Arm
from ddarm.physics.dynamics import Chain, cached_njit, compiled_dynamics, typed_entry

PD_GRAVITY, COMPUTED_TORQUE = 0, 1  # the compiled functions' code for each law
MAX_DELAY = 100


class GainError(DdarmError, ValueError):
    """Gains or a delay that a controller refuses; the old ones stay in force."""


def checked_gains(kp, kv, dof: int) -> tuple[np.ndarray, np.ndarray]:
    """K_p, K_v diagonals as arrays: `dof` finite positive numbers each, or GainError."""
    return (per_joint('kp', kp, dof, GainError, positive=True), per_joint('kv', kv, dof, GainError, positive=True))


def checked_delay(delay) -> int:
    if isinstance(delay, bool) or not isinstance(delay, (int, np.integer)) or not 0 <= delay <= MAX_DELAY:
        raise GainError(f'compute delay must be a whole number of samples in [0, {MAX_DELAY}], got {delay!r}')
    return int(delay)


def checked_friction(name: str, values, dof: int) -> np.ndarray | None:
    """The model's friction F̂ for computed torque: None, or `dof` finite numbers >= 0."""
    return None if values is None else per_joint(name, values, dof, GainError, non_negative=True)


def gravity_feedforward(model: Arm, q_ref: np.ndarray) -> np.ndarray:
    """Ĝ(q^d(t_j)) of PD + gravity at every sample (shape (samples, n)): computed off-line, before the
    episode, from the controller's model by Pinocchio, as the paper computes its gravity term off-line."""
    return np.array([model.gravity(q) for q in q_ref])


@cached_njit(inline='always')
def measured_sample(n, delay):
    """The sample whose state the torque for sample n is computed from: n - d, or 0 while n < d."""
    return n - delay if n >= delay else 0


@cached_njit(inline='always')
def pd_gravity(kp, kv, q_ref_measured, v_ref_measured, gravity_ref, qm, vm, command, lanes):
    """(2.1): P = K_p e + K_v ė + Ĝ(q^d(t_n)), e and ė at the measured sample."""
    for i in range(qm.shape[0]):
        for b in range(lanes):
            command[i, b] = (kp[i, b] * (q_ref_measured[i] - qm[i, b])
                             + kv[i, b] * (v_ref_measured[i] - vm[i, b]) + gravity_ref[i])


@cached_njit()
def computed_torque(inverse_dynamics, model_scale, kp, kv, q_ref_measured, v_ref_measured, a_ref, qm, vm,
                    viscous_friction, coulomb_friction, commanded_acceleration, command, lanes):
    """(2.6): P = M̂(q)(q̈^d + K_p e + K_v ė) + V̂(q, q̇) + Ĝ(q) + F̂(q̇) at the measured state.

    The model's inverse dynamics (Dynamics.inverse_dynamics) at the measured state with the commanded
    acceleration; the paper's (2.11) swaps K_p and K_v by a misprint, (2.6) is meant (spec §5).
    """
    n = qm.shape[0]
    for i in range(n):
        for b in range(lanes):
            commanded_acceleration[i, b] = (a_ref[i] + kp[i, b] * (q_ref_measured[i] - qm[i, b])
                                            + kv[i, b] * (v_ref_measured[i] - vm[i, b]))
    inverse_dynamics(model_scale, qm, vm, commanded_acceleration, command, lanes)
    for i in range(n):
        for b in range(lanes):
            command[i, b] += viscous_friction[i] * vm[i, b] + coulomb_friction[i] * np.sign(vm[i, b])


@cached_njit(inline='always')
def law_command(controller, inverse_dynamics, model_scale, kp, kv, q_ref_measured, v_ref_measured, a_ref,
                gravity_ref, qm, vm, viscous_friction, coulomb_friction, commanded_acceleration, command, lanes):
    """The command of the law coded `controller` (a law class's `code`) for every lane."""
    if controller == PD_GRAVITY:
        pd_gravity(kp, kv, q_ref_measured, v_ref_measured, gravity_ref, qm, vm, command, lanes)
    else:
        computed_torque(inverse_dynamics, model_scale, kp, kv, q_ref_measured, v_ref_measured, a_ref, qm, vm,
                        viscous_friction, coulomb_friction, commanded_acceleration, command, lanes)


@cached_njit()
def _command_one(controller, inverse_dynamics, kp, kv, q_ref_measured, v_ref_measured, a_ref, gravity_ref, qm, vm,
                 viscous_friction, coulomb_friction):
    """One episode's command, its workspace made here: the controller node's step."""
    n = qm.shape[0]
    command = np.empty((n, 1))
    law_command(controller, inverse_dynamics, np.ones((n, 1)), kp, kv, q_ref_measured, v_ref_measured, a_ref,
                gravity_ref, qm, vm, viscous_friction, coulomb_friction, np.empty((n, 1)), command, 1)
    return command[:, 0]


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
    """Hands back the measurement the torque for sample n is computed from: that of `measured_sample`
    (n - d, or sample 0 while n < d) when the states come one sample after another from sample 0.

    A controller sees arrivals, not the plant: it holds the last d + 1 and hands back the oldest,
    so after a lost state, or a reset in the middle of an episode, it uses the state d arrivals ago
    (or the first one since the reset).
    """

    def __init__(self, delay: int) -> None:
        self.delay = checked_delay(delay)
        self._history: deque = deque(maxlen=self.delay + 1)

    def push(self, measurement):
        """Store this sample's measurement; return the one its torque uses."""
        self._history.append(measurement)
        return self._history[0]

    def clear(self) -> None:
        self._history.clear()

    def __len__(self) -> int:
        return len(self._history)


def _vector(values, dof: int) -> np.ndarray:
    """`values` as the compiled law reads them: `dof` float64, C-contiguous."""
    vector = np.ascontiguousarray(values, dtype=float)
    if vector.shape != (dof,):
        raise GainError(f'the law needs {dof} values per joint quantity, got shape {vector.shape}')
    return vector


def _column(values, dof: int) -> np.ndarray:
    return _vector(values, dof)[:, None]


class _Law:
    """A law on the controller's model (`chain`), with gains that are replaced only by valid ones.

    Each law says what it needs besides the state: `gravity_feedforward`, Ĝ(q^d) computed off-line;
    `model_friction`, the model's F̂ (the plant's friction, spec §5).
    """

    code = PD_GRAVITY
    name = ''
    gravity_feedforward = False
    model_friction = False

    def __init__(self, chain: Chain, kp, kv, viscous_friction=None, coulomb_friction=None) -> None:
        self.chain = chain
        self._inverse_dynamics = compiled_dynamics(chain).inverse_dynamics
        self.set_gains(kp, kv)
        zero = np.zeros(chain.dof)
        self.viscous_friction = checked_friction('viscous_friction', viscous_friction, chain.dof)
        self.coulomb_friction = checked_friction('coulomb_friction', coulomb_friction, chain.dof)
        # F̂: the model URDF's <dynamics> and the friction given beyond it.
        self._friction = tuple(_vector(values, chain.dof) for values in chain.joint_friction(
            self.viscous_friction, self.coulomb_friction)) if self.model_friction else (zero, zero)
        column = np.zeros((chain.dof, 1))
        self._command_one = typed_entry(_command_one, self.code, self._inverse_dynamics, column, column, zero, zero,
                                        zero, zero, column, column, *self._friction)

    def set_gains(self, kp, kv) -> None:
        self.kp, self.kv = checked_gains(kp, kv, self.chain.dof)
        # As the compiled law reads them (one lane), made once here rather than at every sample.
        self._gain_columns = (_column(self.kp, self.chain.dof), _column(self.kv, self.chain.dof))

    def torque(self, measured: Measurement, reference: ReferencePoint, gravity_ref: np.ndarray | None = None):
        """The command from the measured sample and the reference at t_n.

        PD + gravity needs `gravity_ref`, Ĝ(q^d(t_n)) from `gravity_feedforward`; computed torque ignores it.
        """
        if self.gravity_feedforward and gravity_ref is None:
            raise GainError('PD + gravity needs the gravity feedforward Ĝ(q^d(t_n)) (gravity_feedforward)')
        dof = self.chain.dof
        return self._command_one(self.code, self._inverse_dynamics, *self._gain_columns,
                                 _vector(measured.q_ref, dof), _vector(measured.v_ref, dof), _vector(reference.a, dof),
                                 np.zeros(dof) if gravity_ref is None else _vector(gravity_ref, dof),
                                 _column(measured.q, dof), _column(measured.v, dof), *self._friction)


class PDGravityLaw(_Law):
    """Fig. 1: PD on the errors plus the model's gravity at the programmed position."""

    code = PD_GRAVITY
    name = 'pd_gravity'
    gravity_feedforward = True


class ComputedTorqueLaw(_Law):
    """Fig. 2: the model's inverse dynamics at the measured state, with friction F̂ if the model has it."""

    code = COMPUTED_TORQUE
    name = 'computed_torque'
    model_friction = True


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

    def step(self, measurement: Measurement, reference: ReferencePoint,
             gravity_ref: np.ndarray | None = None) -> np.ndarray:
        """The torque for this sample from the delayed measurement and the reference at t_n."""
        return self.law.torque(self.buffer.push(measurement), reference, gravity_ref)

    def reset(self) -> None:
        """A new episode: forget the measurements of the last one."""
        self.buffer.clear()


# Every law by its name: the one list the engine, the nodes and the CLI read.
LAWS = {law.name: law for law in (PDGravityLaw, ComputedTorqueLaw)}
CONTROLLERS = tuple(LAWS)


def make_law(controller: str, chain: Chain, kp, kv, viscous_friction=None, coulomb_friction=None):
    """The law named `controller` (one of CONTROLLERS) on the controller's model."""
    if controller not in LAWS:
        raise GainError(f'controller must be one of {CONTROLLERS}, got {controller!r}')
    law = LAWS[controller]
    if law.model_friction:
        return law(chain, kp, kv, viscous_friction, coulomb_friction)
    return law(chain, kp, kv)


def warm_up(chain: Chain) -> None:
    """Load both compiled laws (from numba's cache, or compile them) now, not at an episode's first sample."""
    dof = chain.dof
    zero, one = np.zeros(dof), np.ones(dof)
    for law in LAWS.values():
        law(chain, one, one).torque(Measurement(zero, zero, zero, zero), ReferencePoint(zero, zero, zero), zero)
