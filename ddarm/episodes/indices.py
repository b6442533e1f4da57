"""The performance indices (2.5) and (3.2) with the weights of MODEL.md section 8.

Arrays have the sample on the second-to-last axis and the joint on the last, so a
leading batch axis is free.
"""

from __future__ import annotations

import numpy as np

from ddarm.errors import DdarmError

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


def index_2_5(errors: np.ndarray, k_max: int) -> np.ndarray:
    """(2.5): I_1 = (1/k_max) Σ_j Σ_i |e_i(jΔ)| S_i over the samples given (j = 0 … k_max)."""
    if k_max < 1:
        raise IndicesError(f'k_max must be at least 1, got {k_max}')
    return np.sum(np.abs(errors) * error_weights(errors.shape[-1]), axis=(-2, -1)) / k_max


def torque_index(torques: np.ndarray, nominal: np.ndarray, k_max: int,
                 weights: np.ndarray | None = None) -> np.ndarray:
    """(3.2)'s I_2 = (1/k_max) Σ_j Σ_i |P_i(jΔ) - P_i^nom(jΔ)| R_i, P the torque actually applied."""
    if k_max < 1:
        raise IndicesError(f'k_max must be at least 1, got {k_max}')
    if weights is None:
        weights = torque_weights(nominal)
    samples = torques.shape[-2]
    return np.sum(np.abs(torques - nominal[..., :samples, :]) * weights, axis=(-2, -1)) / k_max


def index_3_2(errors: np.ndarray, torques: np.ndarray, nominal: np.ndarray,
              k_max: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3.2): I = I_1 + I_2; returns (I, I_1, I_2). R_i comes from the whole `nominal` series."""
    first = index_2_5(errors, k_max)
    second = torque_index(torques, nominal, k_max)
    return first + second, first, second
