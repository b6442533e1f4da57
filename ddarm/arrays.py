"""The one check of per-joint and per-episode number arrays, for every option, gain and node parameter.

Each caller passes its own error class, so a refusal names the layer that refused (PlantError,
GainError, BatchError, ...) while the rule and the wording stay one.
"""

from __future__ import annotations

import numpy as np


def per_joint(name: str, values, dof: int, error: type[Exception], *, positive: bool = False,
              non_negative: bool = False) -> np.ndarray:
    """`values` as `dof` finite numbers (one per joint), or `error` naming `name` and what is wrong."""
    try:
        array = np.array(values, dtype=float)
    except (TypeError, ValueError) as problem:
        raise error(f'{name} must be numbers, got {values!r}') from problem
    if array.shape != (dof,):
        raise error(f'{name} needs {dof} values (one per joint), got {values!r}')
    if positive and not np.all(np.isfinite(array) & (array > 0)):
        raise error(f'{name} must be finite and positive, got {values!r}')
    if not np.all(np.isfinite(array)):
        raise error(f'{name} must be finite, got {values!r}')
    if non_negative and np.any(array < 0):
        raise error(f'{name} must not be negative, got {values!r}')
    return array


def per_episode(name: str, values, size: int | None, dof: int, error: type[Exception]) -> np.ndarray:
    """A (B, n) array of finite positive numbers, one row per episode; B = `size` unless None."""
    try:
        array = np.array(values, dtype=float)
    except (TypeError, ValueError) as problem:
        raise error(f'{name} must be numbers, got {values!r}') from problem
    rows = 'B' if size is None else size
    if array.ndim != 2 or array.shape[1] != dof or (size is not None and array.shape[0] != size):
        raise error(f'{name} must have shape ({rows}, {dof}): one row of {dof} values per episode, '
                    f'got shape {array.shape}')
    bad = ~np.all(np.isfinite(array) & (array > 0), axis=1)
    if bad.any():
        member = int(np.argmax(bad))
        raise error(f'{name} must be finite and positive: episode {member} has {array[member].tolist()}')
    return array
