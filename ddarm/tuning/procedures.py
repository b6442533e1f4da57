"""The simplified-model procedure of section 2 (spec §6): the smallest ω meeting the permitted
steady-state errors, then ω raised while the simulated torques stay acceptable."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ddarm.control.gains import (computed_torque_error_external, computed_torque_error_mass, pd_gravity_error,
                                 smallest_omega)
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import (EpisodeError, EpisodeSpec, episode_motion, gains_from_omega, model_arm, plan_episode,
                                  plant_arm)


# The raising step simulates one episode per ω: far more than any useful procedure, refused before any work.
MAX_OMEGA_STEPS = 10_000


@dataclass(frozen=True)
class OmegaStep:
    """One simulated ω of the raising step, and why it was accepted or not."""

    omega: float
    max_torque_ratio_to_limit: float  # max_i max_j |P_i| / limit_i
    max_torque_ratio_to_nominal: float  # max_i max_j |P_i| / max_j |P_i^nom|
    diverged: bool
    accepted: bool
    indices: dict


@dataclass(frozen=True)
class OmegaChoice:
    omega_min: float
    steady_state_error_at_min: np.ndarray  # rad, per joint
    omega: float | None  # None: even ω_min breaks the torque conditions
    kp: np.ndarray | None
    kv: np.ndarray | None
    steps: list


def steady_state_error_per_unit_gain(spec: EpisodeSpec) -> tuple[np.ndarray, np.ndarray]:
    """(c, g) with the steady-state error e_i = c_i / (g_i ω²) of the ω rule at q_f (spec §6).

    The disturbance is the spec's constant P^z and its plant/model mass mismatch; both may act.
    """
    model, plant = model_arm(spec), plant_arm(spec)
    q_final = episode_motion(spec).qf
    external = np.zeros(model.dof) if spec.external_torque is None else np.array(spec.external_torque)
    unit = np.ones(model.dof)
    if spec.controller == 'computed_torque':
        mass = model.mass_matrix(q_final)
        error = (computed_torque_error_external(plant.mass_matrix(q_final), unit, external)
                 + computed_torque_error_mass(mass, plant.gravity(q_final), model.gravity(q_final), unit))
        return error, unit
    error = pd_gravity_error(plant.gravity(q_final), model.gravity(q_final), external, unit)
    return error, np.diag(model.mass_matrix(q_final))


def omega_procedure(spec: EpisodeSpec, permitted_error: np.ndarray, torque_factor: float = 2.0,
                    omega_step: float = 0.5, omega_max: float = 100.0) -> OmegaChoice:
    """Section 2's procedure for the controller, disturbance and mismatch of `spec` (its gains are ignored).

    Step 1: ω_min, the smallest ω whose steady-state errors are within `permitted_error` (rad).
    Step 2: from ω_min up in `omega_step`s to `omega_max`, simulate the episode (with the
    disturbance) and keep raising while the largest torque of every joint stays within the
    actuator limit (the spec's limit, the paper's 2 x max nominal if it has none) and within
    `torque_factor` times that joint's largest nominal torque. The last accepted ω is chosen.
    """
    if not (np.isfinite(torque_factor) and torque_factor > 0):
        raise EpisodeError(f'torque factor must be finite and positive, got {torque_factor!r}')
    if not (0 < omega_step <= omega_max and np.isfinite(omega_max)):
        raise EpisodeError(f'need 0 < omega step <= omega max, got {omega_step!r}, {omega_max!r}')
    error_unit, gain_scale = steady_state_error_per_unit_gain(spec)
    permitted = np.broadcast_to(np.asarray(permitted_error, dtype=float), error_unit.shape)
    omega_min = smallest_omega(error_unit, gain_scale, permitted)
    if not np.any(error_unit):
        raise EpisodeError('no external torque and no mass mismatch: the steady-state errors are zero at every ω, '
                           'so the permitted error bounds nothing (give a disturbance and/or a mass error)')
    unlimited = dataclasses.replace(spec, torque_limit='none')
    steps, chosen, chosen_gains = [], None, (None, None)
    # A disturbance-free arm needs no minimum: the raising then starts from one step.
    start = max(omega_min, omega_step)
    if not start <= omega_max * (1 + 1e-12):
        raise EpisodeError(f'ω_min = {omega_min:.6g} from the permitted errors is above omega max {omega_max!r}: '
                           'no ω to try (permit larger errors or raise omega max)')
    # Each ω a product of the step, never a running sum: a step below ω's last bit would leave ω where it was.
    raises = (omega_max - start) / omega_step
    if raises > MAX_OMEGA_STEPS:
        raise EpisodeError(f'from ω = {start:.6g} to omega max {omega_max!r} in steps of {omega_step!r} is more than '
                           f'{MAX_OMEGA_STEPS} episodes: take a larger omega step or a smaller omega max')
    # The actuator limit of the raising step: the spec's, or the paper's (2 x max nominal) if it has none.
    limit = plan_episode(dataclasses.replace(spec, torque_limit='paper' if spec.torque_limit == 'none'
                                             else spec.torque_limit)).torque_limit
    for raised in range(int(np.floor(max(raises, 0.0) + 1e-9)) + 1):
        omega = start + raised * omega_step
        kp, kv = gains_from_omega(spec, omega)
        result = run_episode(dataclasses.replace(unlimited, kp=kp, kv=kv))
        largest = np.max(np.abs(result.scored('torque')), axis=0)
        nominal = np.max(np.abs(result.plan.nominal), axis=0)
        to_limit, to_nominal = float(np.max(largest / limit)), float(np.max(largest / nominal))
        diverged = bool(result.diverged[0])
        accepted = not diverged and to_limit <= 1.0 and to_nominal <= torque_factor
        steps.append(OmegaStep(float(omega), to_limit, to_nominal, diverged, accepted, result.indices()))
        if not accepted:
            break
        chosen, chosen_gains = float(omega), (kp, kv)
    return OmegaChoice(omega_min, error_unit / (gain_scale * omega_min**2), chosen, *chosen_gains, steps)
