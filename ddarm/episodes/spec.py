"""What defines an episode (EpisodeSpec) and what it needs before it starts (EpisodePlan)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ddarm.control.gains import omega_rule_gains
from ddarm.control.laws import CONTROLLERS, GainError, checked_delay, checked_gains
from ddarm.errors import DdarmError
from ddarm.motion.programmed import (ProgrammedMotion, checked_tau, disturbed_start, nominal_torque,
                                     paper_torque_limit, paper_trajectory, sample_count, sample_times)
from ddarm.physics.arm import ModelError, load_arm
from ddarm.physics.plant import DEFAULT_SUBSTEPS, PlantError, PlantOptions, checked_mass_scale

# Refused before any work: far beyond any episode this project runs (FAULTS.md 6).
MAX_SAMPLES = 1_000_000


class EpisodeError(DdarmError, ValueError):
    """An episode specification that cannot be run."""


def _optional_tuple(values) -> tuple[float, ...] | None:
    return None if values is None else tuple(float(v) for v in values)


@dataclass(frozen=True)
class EpisodeSpec:
    """Everything that defines an episode; its defaults are the spec's (§14; and the user's delay of 1)."""

    controller: str
    kp: tuple[float, ...]
    kv: tuple[float, ...]
    trajectory: int = 1
    duration: float = 1.0
    period: float = 0.01
    delay: int = 1
    tau: float = 0.0
    torque_limit: str | tuple[float, ...] = 'none'  # 'none', 'paper' (2 x max nominal) or N/m per joint
    external_torque: tuple[float, ...] | None = None
    viscous_friction: tuple[float, ...] | None = None
    coulomb_friction: tuple[float, ...] | None = None
    mass_scale: tuple[float, ...] | None = None  # the plant's links against the controller's model
    substeps: int = DEFAULT_SUBSTEPS
    urdf: str | None = None

    def __post_init__(self) -> None:
        for name in ('kp', 'kv', 'external_torque', 'viscous_friction', 'coulomb_friction', 'mass_scale'):
            object.__setattr__(self, name, _optional_tuple(getattr(self, name)))
        if not isinstance(self.torque_limit, str):
            object.__setattr__(self, 'torque_limit', _optional_tuple(self.torque_limit))
        elif self.torque_limit not in ('none', 'paper'):
            raise EpisodeError(f"torque_limit must be 'none', 'paper' or one number per joint, "
                               f'got {self.torque_limit!r}')
        if self.controller not in CONTROLLERS:
            raise EpisodeError(f'controller must be one of {CONTROLLERS}, got {self.controller!r}')
        try:
            checked_tau(self.tau, self.duration)
            checked_delay(self.delay)
            if sample_count(self.duration, self.period) > MAX_SAMPLES:
                raise EpisodeError(f'{self.duration} s at {self.period} s is more than {MAX_SAMPLES} samples')
        except (GainError, ValueError) as error:
            raise EpisodeError(str(error)) from error

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class EpisodePlan:
    """What an episode needs before it starts: samples, programmed motion, nominal torque, limits, start."""

    times: np.ndarray
    q_ref: np.ndarray
    v_ref: np.ndarray
    a_ref: np.ndarray
    nominal: np.ndarray
    torque_limit: np.ndarray | None
    q0: np.ndarray
    v0: np.ndarray
    motion: ProgrammedMotion | None = None  # None for a plan read back from a recording

    @property
    def k_max(self) -> int:
        return len(self.times) - 1


def plan_episode(spec: EpisodeSpec) -> EpisodePlan:
    """The paper's programmed motion for `spec`, sampled at j Δ for j = 0 … T/Δ."""
    motion = paper_trajectory(spec.trajectory, spec.duration)
    return plan_motion(spec, motion, sample_times(spec.duration, spec.period))


def plan_motion(spec: EpisodeSpec, motion: ProgrammedMotion, times: np.ndarray) -> EpisodePlan:
    """The motion at the sample times, P^nom from the nominal model, limits and the τ-disturbed start."""
    model = load_arm(spec.urdf)
    if motion.dof != model.dof:
        raise EpisodeError(f'the programmed motion has {motion.dof} joints, the URDF {model.dof}')
    q_ref, v_ref, a_ref = motion.sample(times)
    nominal = nominal_torque(model, motion, times)
    if spec.torque_limit == 'none':
        limit = None
    elif spec.torque_limit == 'paper':
        limit = paper_torque_limit(nominal)
    else:
        limit = np.array(spec.torque_limit)
    q0, v0 = disturbed_start(motion, spec.tau)
    return EpisodePlan(times, q_ref, v_ref, a_ref, nominal, limit, q0, v0, motion)


def gains_from_omega(controller: str, omega: float, urdf: str | None = None,
                     final_position: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ω rule of section 2 for `controller`; PD + gravity takes m_ii of the model at q_f."""
    if not (np.isfinite(omega) and omega > 0):
        raise EpisodeError(f'omega must be finite and positive, got {omega!r}')
    try:
        return omega_rule_gains(controller, load_arm(urdf), omega, final_position)
    except GainError as error:
        raise EpisodeError(str(error)) from error


def plant_options(spec: EpisodeSpec, plan: EpisodePlan, dof: int) -> PlantOptions:
    """The plant options `spec` runs with (its torque limit resolved by `plan`), checked for a `dof`-joint arm."""
    return PlantOptions(period=spec.period, substeps=spec.substeps, torque_limit=plan.torque_limit,
                        viscous_friction=spec.viscous_friction, coulomb_friction=spec.coulomb_friction,
                        external_torque=spec.external_torque).checked(dof)


def check_episode(spec: EpisodeSpec) -> EpisodePlan:
    """Plan `spec` and check everything a run would refuse (gains, per-joint options), before any work starts."""
    plan = plan_episode(spec)
    dof = load_arm(spec.urdf).dof
    try:
        checked_gains(spec.kp, spec.kv, dof)
        plant_options(spec, plan, dof)
        if spec.mass_scale is not None:
            checked_mass_scale(spec.mass_scale, dof)
    except (GainError, PlantError, ModelError) as error:
        raise EpisodeError(str(error)) from error
    return plan
