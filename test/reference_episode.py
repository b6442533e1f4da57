"""A deliberately plain reference implementation of one closed-loop episode: the independent check of the compiled loop.

The engine (ddarm.episodes.engine) runs every episode through compiled kernels: the dynamics
of ddarm.physics.dynamics, the laws and the delay of ddarm.control.laws, the plant step of
ddarm.physics.plant and the sums of ddarm.episodes.indices. This module computes the same
episode (spec §3, §5, §7, §8, §11, §12) with none of them: Pinocchio's own algorithms on the
URDF (aba for the plant, crba + nonLinearEffects and computeGeneralizedGravity for the laws,
rnea for the nominal torque), classical RK4 in NumPy, the compute delay as a deque of d + 1
measurements, saturation by np.clip, the divergence bounds, and the indices as NumPy sums.
It is the project's loop as it was before the compiled kernels, kept as test code; it is slow
and meant to stay obviously right. From ddarm it takes only the episode's plan (the sampled
programmed motion and the start state) and the URDF loader.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, plan_episode
from ddarm.physics.arm import Arm

MAX_POSITION, MAX_VELOCITY = 100.0, 1000.0  # rad, rad/s: beyond these the episode has diverged (spec §12)


@lru_cache(maxsize=32)
def _arm(urdf: str | None, mass_scale: tuple[float, ...] | None) -> Arm:
    return Arm.from_urdf(urdf, mass_scale)


@dataclass
class ReferenceEpisode:
    """Samples j = 0 … of the scored part of an episode, its divergence and its indices."""

    spec: EpisodeSpec
    plan: EpisodePlan
    nominal: np.ndarray  # P^nom at every sample, from pin.rnea
    torque_limit: np.ndarray | None
    q: np.ndarray
    v: np.ndarray
    command: np.ndarray
    torque: np.ndarray
    diverged_at: int | None
    indices: dict

    @property
    def errors(self) -> np.ndarray:
        return self.plan.q_ref[:len(self.q)] - self.q

    @property
    def diverged(self) -> bool:
        return self.diverged_at is not None


def rk4_period(arm: Arm, q, v, torque, period, substeps, external, viscous, coulomb):
    """[t_n, t_{n+1}) under the held torque: `substeps` RK4 steps of q̈ = ABA(q, q̇, P + P^z - F(q̇))."""
    def acceleration(q, v):
        return arm.forward_dynamics(q, v, torque + external - viscous * v - coulomb * np.sign(v))

    h = period / substeps
    with np.errstate(all='ignore'):
        for _ in range(substeps):
            a1 = acceleration(q, v)
            q2, v2 = q + 0.5 * h * v, v + 0.5 * h * a1
            a2 = acceleration(q2, v2)
            q3, v3 = q + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = acceleration(q3, v3)
            q4, v4 = q + h * v3, v + h * a3
            a4 = acceleration(q4, v4)
            q = q + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return q, v


def _within_bounds(q, v) -> bool:
    return bool(np.all(np.isfinite(q)) and np.all(np.isfinite(v))
                and np.max(np.abs(q)) <= MAX_POSITION and np.max(np.abs(v)) <= MAX_VELOCITY)


def reference_episode(spec: EpisodeSpec, plan: EpisodePlan | None = None) -> ReferenceEpisode:
    """Run `spec` (on `plan`'s motion and start, if given): P_n from the state of sample n - d, held over a period."""
    plan = plan if plan is not None else plan_episode(spec)
    model = _arm(spec.urdf, None)  # the controller's model: always the unscaled URDF
    plant = _arm(spec.urdf, spec.mass_scale)
    dof = model.dof
    zero = np.zeros(dof)
    external = zero if spec.external_torque is None else np.array(spec.external_torque)
    # The joints' friction: the URDF's <dynamics damping friction>, as Pinocchio's URDF parser reads them, and the
    # spec's beyond them.
    viscous = plant.model.damping + (zero if spec.viscous_friction is None else np.array(spec.viscous_friction))
    coulomb = plant.model.friction + (zero if spec.coulomb_friction is None else np.array(spec.coulomb_friction))
    kp, kv = np.array(spec.kp), np.array(spec.kv)

    nominal = np.array([model.inverse_dynamics(q, v, a) for q, v, a in zip(plan.q_ref, plan.v_ref, plan.a_ref)])
    if spec.torque_limit == 'none':
        limit = None
    elif spec.torque_limit == 'paper':
        limit = 2.0 * np.max(np.abs(nominal), axis=0)
    else:
        limit = np.array(spec.torque_limit)

    samples = plan.k_max + 1
    q, v = np.array(plan.q0, dtype=float), np.array(plan.v0, dtype=float)
    history = deque(maxlen=spec.delay + 1)  # its oldest entry is sample max(n - d, 0)
    recorded = {name: np.empty((samples, dof)) for name in ('q', 'v', 'command', 'torque')}
    diverged_at, scored = None, samples
    for n in range(samples):
        recorded['q'][n], recorded['v'][n] = q, v
        history.append((q, v, plan.q_ref[n], plan.v_ref[n]))
        qm, vm, q_ref_m, v_ref_m = history[0]
        error, error_rate = q_ref_m - qm, v_ref_m - vm
        if spec.controller == 'pd_gravity':  # (2.1)
            command = kp * error + kv * error_rate + model.gravity(plan.q_ref[n])
        else:  # (2.6), with the model's friction F̂ = F
            command = (model.mass_matrix(qm) @ (plan.a_ref[n] + kp * error + kv * error_rate)
                       + model.bias(qm, vm) + viscous * vm + coulomb * np.sign(vm))
        recorded['command'][n] = command
        if not np.all(np.isfinite(command)):
            diverged_at, scored = n, n
            break
        torque = command if limit is None else np.clip(command, -limit, limit)
        recorded['torque'][n] = torque
        if n < plan.k_max:
            q_next, v_next = rk4_period(plant, q, v, torque, spec.period, spec.substeps, external, viscous, coulomb)
            if not _within_bounds(q_next, v_next):
                diverged_at, scored = n + 1, n + 1
                break
            q, v = q_next, v_next

    series = {name: values[:scored] for name, values in recorded.items()}
    errors = plan.q_ref[:scored] - series['q']
    first = np.sum(np.abs(errors) * (360.0 / (2.0 * np.pi))) / plan.k_max  # (2.5), S_i = 360/2π
    weights = 10.0 / np.max(np.abs(nominal), axis=0)  # R_i, from the whole nominal series
    second = np.sum(np.abs(series['torque'] - nominal[:scored]) * weights) / plan.k_max
    indices = {'I1': float(first), 'I2': float(second), 'I': float(first + second)}  # I (3.2) = I1 + I2
    return ReferenceEpisode(spec, plan, nominal, limit, diverged_at=diverged_at, indices=indices, **series)
