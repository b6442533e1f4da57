"""The programmed motions of section 3: bang-bang joint profiles, and their nominal torque (spec §4, §7)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ddarm.errors import DdarmError
from ddarm.physics.arm import Arm


class MotionError(DdarmError, ValueError):
    """A programmed motion or sampling that cannot be used; the text names the problem."""


# Sample instants land on T/2 and T only up to rounding (0.01 * 50): within this
# relative distance of a phase boundary the later phase applies (spec §4).
_PHASE_EDGE = 1e-9


@dataclass(frozen=True)
class ProgrammedMotion:
    """q^d(t) = q0 + (qf - q0) s(t/T), s the bang-bang profile; qf held after T."""

    q0: np.ndarray
    qf: np.ndarray
    duration: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.duration) and self.duration > 0):
            raise MotionError(f'duration must be finite and positive, got {self.duration!r}')
        if np.shape(self.q0) != np.shape(self.qf) or np.ndim(self.q0) != 1:
            raise MotionError(f'q0 and qf must be vectors of one length, got {self.q0!r} and {self.qf!r}')

    @property
    def dof(self) -> int:
        return len(self.q0)

    def sample(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration at times t (shape (..., n) for t of shape (...))."""
        u = (np.asarray(t, dtype=float) / self.duration)[..., None]
        span = np.asarray(self.qf, dtype=float) - np.asarray(self.q0, dtype=float)
        accelerating = u < 0.5 - _PHASE_EDGE
        moving = u <= 1.0 + _PHASE_EDGE
        uc = np.clip(u, 0.0, 1.0)
        s = np.where(accelerating, 2.0 * uc**2, 1.0 - 2.0 * (1.0 - uc) ** 2)
        ds = np.where(accelerating, 4.0 * uc, 4.0 * (1.0 - uc))
        dds = np.where(accelerating, 4.0, -4.0)
        s = np.where(moving, s, 1.0)
        ds = np.where(moving, ds, 0.0)
        dds = np.where(moving, dds, 0.0)
        position = self.q0 + span * s
        velocity = span * ds / self.duration
        acceleration = span * dds / self.duration**2
        return position, velocity, acceleration


# The paper's motions are data: ddarm/paper/data/trajectory-<number>.yaml (spec §4), numbered from 1 without a
# leading zero. Any other file there (`trajectory-x.yaml`, `trajectory-01.yaml`, an editor's backup) is no paper
# motion and is ignored: only the names are read here, at import; a file is read when its motion is first used.
_PAPER_MOTION_NAME = re.compile(r'trajectory-([1-9][0-9]*)\.yaml')
_PAPER_MOTIONS = {int(match[1]): path
                  for path in (Path(__file__).resolve().parents[1] / 'paper' / 'data').glob('trajectory-*.yaml')
                  if (match := _PAPER_MOTION_NAME.fullmatch(path.name))}
PAPER_TRAJECTORIES = tuple(sorted(_PAPER_MOTIONS))


@lru_cache(maxsize=None)
def paper_motion_file(number: int):
    """The motion file of trajectory `number` (a ddarm.motion.files.MotionFile), read once."""
    from ddarm.motion.files import load_motion  # files.py imports this module: a top-level import would be circular

    if number not in _PAPER_MOTIONS:
        raise MotionError(f'trajectory must be one of {list(PAPER_TRAJECTORIES)}, got {number!r}')
    return load_motion(_PAPER_MOTIONS[number])


def paper_trajectory(number: int, duration: float) -> ProgrammedMotion:
    """Trajectory `number` (1 or 2) of the paper's section 3, of duration T."""
    motion = paper_motion_file(number).motion
    # Fresh arrays, as every call returned before the motions were files: a caller may change its copy.
    return ProgrammedMotion(motion.q0.copy(), motion.qf.copy(), float(duration))


def paper_motion_joints(number: int) -> tuple[str, ...]:
    """The joints trajectory `number` drives, by name, in the order of its positions (its file's joint_names)."""
    return paper_motion_file(number).joint_names


def sample_count(duration: float, period: float) -> int:
    """k_max = T / Δ of (2.5); T must be a whole number of sampling periods."""
    if not (np.isfinite(period) and period > 0):
        raise MotionError(f'sampling period must be finite and positive, got {period!r}')
    if not (np.isfinite(duration) and duration > 0):
        raise MotionError(f'duration T must be finite and positive, got {duration!r} s')
    ratio = duration / period
    k_max = int(round(ratio))
    if k_max < 1 or abs(ratio - k_max) > 1e-9 * max(1.0, ratio):
        raise MotionError(f'duration {duration} s is not a whole number of sampling periods {period} s')
    return k_max


def sample_times(duration: float, period: float) -> np.ndarray:
    """t_j = j Δ for j = 0 … k_max, each a product, never a running sum (spec §5)."""
    return np.arange(sample_count(duration, period) + 1) * period


def checked_tau(tau, duration: float) -> np.ndarray:
    """τ of the disturbance (3.1), a number or one per episode, each within [0, T]; MotionError otherwise."""
    values = np.asarray(tau, dtype=float)
    bad = ~(np.isfinite(values) & (values >= 0) & (values <= duration))
    if values.ndim == 0 and bad:
        raise MotionError(f'tau must be within [0, T = {duration}] s, got {tau!r}')
    if bad.any():
        episode = int(np.argmax(bad))
        raise MotionError(f'tau must be within [0, T = {duration}] s: episode {episode} has {values[episode]!r}')
    return values


def disturbed_start(motion: ProgrammedMotion, tau) -> tuple[np.ndarray, np.ndarray]:
    """(3.1) with spec §7's sign: q(0) = q^d(0) and q̇(0) = q̇^d(0) - q̇^d(τ), so that e(0) = 0 and ė(0) = q̇^d(τ),
    against the motion; for τ of shape (B,), q̇(0) has shape (B, n).

    The paper's motions start at rest (q̇^d(0) = 0): q̇(0) = -q̇^d(τ) as (3.1) writes it. A waypoint motion may
    not (a linear first segment): with τ = 0 its arm still starts at rest, as a robot does (spec §16).
    """
    _, v_at_start, _ = motion.sample(0.0)
    _, v_at_tau, _ = motion.sample(checked_tau(tau, motion.duration))
    return np.array(motion.q0, dtype=float), v_at_start - v_at_tau


def nominal_torque(arm: Arm, motion: ProgrammedMotion, times: np.ndarray) -> np.ndarray:
    """P^nom(t) = M(q^d) q̈^d + V(q^d, q̇^d) + G(q^d) at each time (spec §7); shape (len(times), n).

    Computed off-line, before the episode, by Pinocchio (the model's source): only the loop runs compiled.
    """
    positions, velocities, accelerations = motion.sample(times)
    return np.array([arm.inverse_dynamics(q, v, a) for q, v, a in zip(positions, velocities, accelerations)])


# A torque at its limit is within it: the recorded torque may exceed the limit it was clamped to by rounding.
LIMIT_TOLERANCE = 1e-9  # N m


def within_limits(max_abs_torque, limit) -> bool:
    """Whether every joint's largest torque stays within its limit."""
    return bool(np.all(np.asarray(max_abs_torque, dtype=float) <= np.asarray(limit, dtype=float) + LIMIT_TOLERANCE))


def paper_torque_limit(nominal: np.ndarray) -> np.ndarray:
    """Table 2's "inputs limited": |P_i| ≤ 2 max_j |P_i^nom(jΔ)| (spec §7)."""
    return 2.0 * np.max(np.abs(nominal), axis=0)
