"""Checks on recorded or received samples that need no ROS: stamps to sample indices, joints by name.

The nodes apply them to messages as they arrive, the bag scorer to messages as recorded.
"""

from __future__ import annotations

import math

import numpy as np

from ddarm.errors import DdarmError

# Refused before any work (docs/faults.md 6): far beyond the joint count of any arm we run.
MAX_JOINTS = 64
# Refused before any work (docs/faults.md 6): far beyond an episode length we run.
MAX_REFERENCE_POINTS = 1_000_000
# Sample periods of an episode, refused beyond before any work (docs/faults.md 6).
MAX_SAMPLES = 1_000_000
# Δ in s: below a microsecond no controller samples, and T/Δ, ω* = ωΔ*/Δ stay far from overflow.
PERIOD_RANGE = (1e-6, 10.0)
# Δ in s: the paper's 100 Hz, every episode's (and so every node's) default.
DEFAULT_PERIOD = 0.01
# The fields of a reference point, in the order a reference holds them: q^d, q̇^d, q̈^d, P^nom.
REFERENCE_FIELDS = ('positions', 'velocities', 'accelerations', 'effort')


class MessageError(DdarmError, ValueError):
    """A message that cannot be used as it is; the text names the problem."""


def stamp_ns(stamp) -> int:
    """A stamp (a builtin_interfaces/Time, a Clock's clock, ddarm's Stamp: sec and nanosec) in integer ns, exact."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def sample_at(t: float, period: float) -> int:
    """n for a time t_n = n Δ; refuses a negative time or one between sample instants."""
    n = round(t / period)
    if n < 0 or abs(t - n * period) > 1e-6 * period + 1e-9:
        raise MessageError(f'stamp {t:.9f} s is not a sample instant of period {period} s')
    return int(n)


def joint_order(names, joints: list[str], what: str) -> np.ndarray | slice:
    """Indices that put the message's joints in our order; refuses unknown, missing or duplicate names.

    Our own order (what ddarm's nodes send) is the whole slice: a message read at every sample costs no copy.
    """
    names = list(names)
    if names == list(joints):
        return slice(None)
    if len(names) > MAX_JOINTS:
        raise MessageError(f'{what}: {len(names)} joint names is more than the {MAX_JOINTS} allowed')
    if len(set(names)) != len(names):
        raise MessageError(f'{what}: duplicate joint names {names}')
    unknown = sorted(set(names) - set(joints))
    missing = [joint for joint in joints if joint not in names]
    if unknown or missing:
        raise MessageError(f'{what}: unknown joints {unknown}, missing joints {missing} (expected {joints})')
    return np.array([names.index(joint) for joint in joints])


def finite_array(values, name: str, field: str, expected: int) -> np.ndarray:
    """`values` as `expected` finite numbers; refuses another count, or a NaN or infinite value."""
    if len(values) != expected:
        raise MessageError(f'{name}: {field} has {len(values)} values for {expected} joints')
    array = np.array(values, dtype=float)
    # math.isfinite over a joint vector's few numbers: a sixth of np.isfinite's time, at every sample of a node.
    if not all(map(math.isfinite, array.tolist())):
        bad = np.flatnonzero(~np.isfinite(array))
        raise MessageError(f'{name}: {field} is not finite at index {bad.tolist()}: {array[bad].tolist()}')
    return array


def checked_reference(names, points, joints: list[str], period: float) -> tuple[np.ndarray, ...]:
    """A reference's times and fields (our joint order), each (samples, n): one point per sample from t = 0.

    `points` are (t, positions, velocities, accelerations, effort), t the point's time from the
    start; each must be a sample instant j Δ, in order, and every field `len(joints)` finite numbers.
    Returns (times, q, v, a, nominal), times the sample instants j Δ.
    """
    what = 'reference'
    order = joint_order(names, joints, what)
    points = list(points)
    if not points:
        raise MessageError(f'{what}: no points')
    if len(points) > MAX_REFERENCE_POINTS:
        raise MessageError(f'{what}: {len(points)} points is more than the {MAX_REFERENCE_POINTS} allowed')
    count = len(joints)
    fields = {name: [] for name in REFERENCE_FIELDS}
    times = []
    for j, (t, *values) in enumerate(points):
        if abs(t - j * period) > 1e-6 * period + 1e-9:
            raise MessageError(f'{what}: point {j} is at {t} s, not at sample time {j * period} s')
        times.append(j * period)
        for name, field in zip(REFERENCE_FIELDS, values):
            fields[name].append(finite_array(field, f'{what} point {j}', name, count)[order])
    return (np.array(times), *(np.array(fields[name]) for name in REFERENCE_FIELDS))
