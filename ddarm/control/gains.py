"""Gains from the simplified models of section 2: the ω rules and the steady-state errors (spec §6).

Sign convention: spec §3's (1.1) adds P^z to the actuator torque, M q̈ + V + G + F = P + P^z.
The paper writes the external-torque error as K_p e = M⁻¹(q_f) P^z, which holds for P^z
on the load side of (1.1); under the spec's convention the same error has the opposite
sign. Only magnitudes enter the ω procedure, so both give the same ω.
"""

from __future__ import annotations

import numpy as np

from ddarm.control.laws import GainError, checked_gains
from ddarm.control.stability import boundary_omega

# The ω of the ω-rule gains the searches start from: around the paper's ω = 15, on both sides.
SEARCH_START_OMEGAS = (8.0, 12.0, 15.0, 20.0, 30.0)


def omega_rule_pd_gravity(mass_diagonal: np.ndarray, omega) -> tuple[np.ndarray, np.ndarray]:
    """(2.3): k_p^i = m_ii ω², k_v^i = 2 m_ii ω; `omega` may carry leading batch axes."""
    omega = np.asarray(omega, dtype=float)[..., None]
    return mass_diagonal * omega**2, 2.0 * mass_diagonal * omega


def omega_rule_gains(law: str, model, omega: float, final_position=None) -> tuple[np.ndarray, np.ndarray]:
    """The ω rule of `law` for the controller's `model` (an Arm); PD + gravity takes m_ii at q_f = `final_position`."""
    if law == 'computed_torque':
        return omega_rule_computed_torque(model.dof, omega)
    if final_position is None:
        raise GainError('the PD + gravity ω rule needs the final position q_f')
    return omega_rule_pd_gravity(np.diag(model.mass_matrix(final_position)), omega)


def gains_from_parameters(law: str, omega: float, kp, kv, model, final_position=None):
    """A controller's K_p, K_v: the ω rule of `law` when omega > 0, else the given kp, kv.

    None when the PD + gravity rule still needs q_f (`final_position` unknown). GainError
    names what is missing or wrong.
    """
    if not (np.isfinite(omega) and omega >= 0):
        raise GainError(f'omega must be finite and not negative, got {omega!r}')
    if omega == 0:
        if kp is None or kv is None:
            raise GainError('set kp and kv (one per joint), or omega > 0')
        return checked_gains(kp, kv, model.dof)
    if law == 'pd_gravity' and final_position is None:
        return None
    return omega_rule_gains(law, model, omega, final_position)


def omega_rule_computed_torque(dof: int, omega) -> tuple[np.ndarray, np.ndarray]:
    """Section 2.2: k_p^i = ω², k_v^i = 2ω."""
    omega = np.asarray(omega, dtype=float)[..., None]
    ones = np.ones(dof)
    return ones * omega**2, ones * 2.0 * omega


def computed_torque_error_external(mass_matrix_final: np.ndarray, kp: np.ndarray,
                                   external_torque: np.ndarray) -> np.ndarray:
    """Steady-state e under a constant P^z: K_p e = -M⁻¹(q_f) P^z (the paper's formula, the spec's sign, §6.2)."""
    return -np.linalg.solve(mass_matrix_final, external_torque) / kp


def computed_torque_error_mass(model_mass_matrix_final: np.ndarray, gravity_final: np.ndarray,
                               model_gravity_final: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """Steady-state e for a mass mismatch: K_p e = M̂⁻¹(q_f) [G(q_f) - Ĝ(q_f)]."""
    return np.linalg.solve(model_mass_matrix_final, gravity_final - model_gravity_final) / kp


def pd_gravity_error(gravity_final: np.ndarray, model_gravity_final: np.ndarray,
                     external_torque: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """Steady-state e of (2.1) at rest at q_f: G(q_f) = K_p e + Ĝ(q_f) + P^z, so K_p e = G - Ĝ - P^z."""
    return (gravity_final - model_gravity_final - external_torque) / kp


def smallest_omega(error_per_unit_kp: np.ndarray, gain_scale: np.ndarray,
                   permitted_error: np.ndarray) -> float:
    """The smallest ω with |e_i| ≤ permitted_i, where e_i = c_i / k_p^i and k_p^i = g_i ω².

    `error_per_unit_kp` is c (the error the formulas give for K_p = I), `gain_scale` is g
    (m_ii for PD + gravity, 1 for computed torque). The first step of section 6's procedure.
    """
    permitted = np.asarray(permitted_error, dtype=float)
    if np.any(permitted <= 0) or not np.all(np.isfinite(permitted)):
        raise GainError(f'permitted errors must be finite and positive, got {permitted_error!r}')
    return float(np.sqrt(np.max(np.abs(error_per_unit_kp) / (gain_scale * permitted))))


def largest_stable_omega(period: float, delay: int) -> float:
    """ω* in rad/s of the ω rule (ζ = 1) per joint, sampled at `period` Δ (s) with a `delay`-sample compute delay:
    the exact boundary of ddarm.control.stability (computed torque with an exact model; PD + gravity's per-joint
    model, which leaves out M's coupling)."""
    return boundary_omega(period, delay, 1.0)
