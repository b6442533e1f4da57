"""The programmed motions of section 3: bang-bang joint profiles, and their nominal torque (spec §4, §7)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ddarm.errors import DdarmError
from ddarm.physics.arm import Arm


class MotionError(DdarmError, ValueError):
    """A programmed motion or sampling that cannot be used; the text names the problem."""


# Sample instants land on T/2 and T only up to rounding (0.01 * 50): within this
# relative distance of a phase boundary the later phase applies (spec §5).
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


# The paper's motions are data: ddarm/paper/data/trajectory-<number>.yaml (spec §4).
_PAPER_MOTIONS = {int(path.stem.removeprefix('trajectory-')): path
                  for path in (Path(__file__).resolve().parents[1] / 'paper' / 'data').glob('trajectory-*.yaml')}
PAPER_TRAJECTORIES = tuple(sorted(_PAPER_MOTIONS))


@lru_cache(maxsize=None)
def _paper_motion(number: int) -> ProgrammedMotion:
    from ddarm.motion.files import load_motion  # files.py imports this module: a top-level import would be circular

    return load_motion(_PAPER_MOTIONS[number]).motion


def paper_trajectory(number: int, duration: float) -> ProgrammedMotion:
    """Trajectory 1 or 2 of the paper's section 3, of duration T."""
    if number not in _PAPER_MOTIONS:
        raise MotionError(f'trajectory must be one of {sorted(PAPER_TRAJECTORIES)}, got {number!r}')
    motion = _paper_motion(number)
    # Fresh arrays, as every call returned before the motions were files: a caller may change its copy.
    return ProgrammedMotion(motion.q0.copy(), motion.qf.copy(), float(duration))


def sample_count(duration: float, period: float) -> int:
    """k_max = T / Δ of (2.5); T must be a whole number of sampling periods."""
    if not (np.isfinite(period) and period > 0):
        raise MotionError(f'sampling period must be finite and positive, got {period!r}')
    ratio = duration / period
    k_max = int(round(ratio))
    if k_max < 1 or abs(ratio - k_max) > 1e-9 * max(1.0, ratio):
        raise MotionError(f'duration {duration} s is not a whole number of sampling periods {period} s')
    return k_max


def sample_times(duration: float, period: float) -> np.ndarray:
    """t_j = j Δ for j = 0 … k_max, each a product, never a running sum (spec §5)."""
    return np.arange(sample_count(duration, period) + 1) * period


def nominal_torque(arm: Arm, motion: ProgrammedMotion, times: np.ndarray) -> np.ndarray:
    """P^nom(t) = M(q^d) q̈^d + V(q^d, q̇^d) + G(q^d) at each time (spec §7); shape (len(times), n).

    Computed off-line, before the episode, by Pinocchio (the model's source): only the loop runs compiled.
    """
    positions, velocities, accelerations = motion.sample(times)
    return np.array([arm.inverse_dynamics(q, v, a) for q, v, a in zip(positions, velocities, accelerations)])


def paper_torque_limit(nominal: np.ndarray) -> np.ndarray:
    """Table 2's "inputs limited": |P_i| ≤ 2 max_j |P_i^nom(jΔ)| (spec §7)."""
    return 2.0 * np.max(np.abs(nominal), axis=0)
