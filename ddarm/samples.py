"""Checks on recorded or received samples that need no ROS: stamps to sample indices, joints by name.

The nodes apply them to messages as they arrive, the bag scorer to messages as recorded.
"""

from __future__ import annotations

import numpy as np

from ddarm.errors import DdarmError

# Refused before any work (FAULTS.md 6): far beyond the joint count of any arm we run.
MAX_JOINTS = 64


class MessageError(DdarmError, ValueError):
    """A message that cannot be used as it is; the text names the problem."""


def sample_at(t: float, period: float) -> int:
    """n for a time t_n = n Δ; refuses a negative time or one between sample instants."""
    n = round(t / period)
    if n < 0 or abs(t - n * period) > 1e-6 * period + 1e-9:
        raise MessageError(f'stamp {t:.9f} s is not a sample instant of period {period} s')
    return int(n)


def joint_order(names, joints: list[str], what: str) -> np.ndarray:
    """Indices that put the message's joints in our order; refuses unknown, missing or duplicate names."""
    names = list(names)
    if len(names) > MAX_JOINTS:
        raise MessageError(f'{what}: {len(names)} joint names is more than the {MAX_JOINTS} allowed')
    if len(set(names)) != len(names):
        raise MessageError(f'{what}: duplicate joint names {names}')
    unknown = sorted(set(names) - set(joints))
    missing = [joint for joint in joints if joint not in names]
    if unknown or missing:
        raise MessageError(f'{what}: unknown joints {unknown}, missing joints {missing} (expected {joints})')
    return np.array([names.index(joint) for joint in joints])
