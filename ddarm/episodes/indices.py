"""The performance indices I1 (2.5), I2 and I = I1 + I2 (3.2), with the weights of spec §8.

`accumulate` is their one definition, sample by sample: the batch engine sums it as it runs
the episodes, `score_series` over recorded samples (the ROS driver's and the bag scorer's).
"""

from __future__ import annotations

import numpy as np

from ddarm.errors import DdarmError
from ddarm.physics.dynamics import cached_njit

INDICES = ('I1', 'I2', 'I')
# The paper numbers its indices by equation: (2.5) is I1, (3.2) is I.
PAPER_EQUATIONS = {'2.5': 'I1', '3.2': 'I'}
# S_i = 360/2π: errors in radians weigh as degrees.
DEGREES_PER_RADIAN = 360.0 / (2.0 * np.pi)
# R_i makes a torque deviation of 10 % of the joint's largest nominal torque weigh as 1°.
TORQUE_WEIGHT_PERCENT = 10.0


class IndicesError(DdarmError, ValueError):
    """Samples the indices cannot be computed from."""


def error_weights(dof: int) -> np.ndarray:
    """S_i of (2.5)."""
    return np.full(dof, DEGREES_PER_RADIAN)


def torque_weights(nominal: np.ndarray) -> np.ndarray:
    """R_i = 10 / max_j |P_i^nom(jΔ)| of (3.2), from the nominal torque at the samples."""
    largest = np.max(np.abs(nominal), axis=-2)
    if np.any(largest <= 0) or not np.all(np.isfinite(largest)):
        raise IndicesError(f'every joint needs a nonzero finite nominal torque to weigh its torque '
                           f'deviation, got maxima {largest}')
    return TORQUE_WEIGHT_PERCENT / largest


@cached_njit(inline='always')
def accumulate(q_ref, q, applied, nominal, error_weight, torque_weight, error_sum, torque_sum, b):
    """Adds sample j's terms for episode b: Σ_i |e_i(jΔ)| S_i to (2.5)'s sum, Σ_i |P_i - P_i^nom| R_i to I2's.

    q_ref and nominal are the sample's (n,) values, q and applied the (n, lanes) state and torque.
    """
    for i in range(q_ref.shape[0]):
        error_sum[b] += abs(q_ref[i] - q[i, b]) * error_weight[i]
        torque_sum[b] += abs(applied[i, b] - nominal[i]) * torque_weight[i]


@cached_njit()
def _sums(q_ref, q, torque, nominal, error_weight, torque_weight):
    error_sum, torque_sum = np.zeros(1), np.zeros(1)
    n = q.shape[1]
    for j in range(q.shape[0]):
        accumulate(q_ref[j], q[j].reshape((n, 1)), torque[j].reshape((n, 1)), nominal[j], error_weight, torque_weight,
                   error_sum, torque_sum, 0)
    return error_sum[0], torque_sum[0]


def score_series(q_ref: np.ndarray, q: np.ndarray, torque: np.ndarray, nominal: np.ndarray,
                 k_max: int) -> dict[str, float]:
    """I1, I2 and I of one episode from its scored samples j = 0 … (shape (samples, n)), divided by k_max.

    R_i comes from the whole `nominal` series; q_ref and nominal may run past the scored samples.
    IndicesError for series the compiled sums would read out of bounds: q and torque of different
    shapes, more samples than q_ref or nominal hold, or joint counts that differ.
    """
    if k_max < 1:
        raise IndicesError(f'k_max must be at least 1, got {k_max}')
    q_ref, q, torque, nominal = (np.asarray(x, dtype=float) for x in (q_ref, q, torque, nominal))
    shapes = f'q_ref {q_ref.shape}, q {q.shape}, torque {torque.shape}, nominal {nominal.shape}'
    if any(x.ndim != 2 for x in (q_ref, q, torque, nominal)):
        raise IndicesError(f'every series must have shape (samples, joints), got {shapes}')
    if q.shape != torque.shape:
        raise IndicesError(f'q and torque must have the same shape (one row per scored sample), got {shapes}')
    if len({x.shape[1] for x in (q_ref, q, torque, nominal)}) != 1:
        raise IndicesError(f'every series must have the same joint count, got {shapes}')
    samples = len(q)
    if samples > len(q_ref) or samples > len(nominal):
        raise IndicesError(f'{samples} scored samples, more than q_ref and nominal hold, got {shapes}')
    error_sum, torque_sum = _sums(*(np.ascontiguousarray(x, dtype=float) for x in (
        q_ref[:samples], q, torque, nominal[:samples], error_weights(q.shape[-1]), torque_weights(nominal))))
    first, second = error_sum / k_max, torque_sum / k_max
    return {'I1': first, 'I2': second, 'I': first + second}
