"""One episode run sample by sample against a plant object: the loop for a plant the batch engine cannot compile.

The pieces are the ones every episode runs: the law and its delay (SampledController, the controller node's),
the plant's calls (`saturate`, `advance`: ddarm's Plant or the MuJoCo robot's) and the indices' one rule
(Episodes.from_samples). With ddarm's own plant this loop gives the batch engine's episode (test_mujoco_plant.py
shows it), so that a MuJoCo episode differs from ddarm's by the plant alone.
"""

from __future__ import annotations

import numpy as np

from ddarm.control.laws import LAWS, Measurement, ReferencePoint, SampledController, gravity_feedforward, make_law
from ddarm.episodes.result import Episodes
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, model_arm, model_chain
from ddarm.physics.plant import SampledPlant


def run_stepwise(spec: EpisodeSpec, plan: EpisodePlan, plant: SampledPlant) -> Episodes:
    """Run `spec` on `plan` against `plant`, which starts at the plan's q0, q̇0 (spec §5: P_n from the state of
    sample n - d, the applied torque held over [t_n, t_{n+1}), a non-finite command ending the scored samples at n,
    a state out of bounds after the period from n at n + 1)."""
    law = LAWS[spec.controller]
    controller = SampledController(make_law(spec.controller, model_chain(spec), spec.kp, spec.kv,
                                            spec.viscous_friction, spec.coulomb_friction), spec.delay)
    gravity_ref = gravity_feedforward(model_arm(spec), plan.q_ref) if law.gravity_feedforward else None
    q, v, command, torque = [], [], [], []
    diverged_at = None
    for k in range(plan.k_max + 1):
        state_q, state_v = plant.q, plant.v
        commanded = controller.step(Measurement(state_q, state_v, plan.q_ref[k], plan.v_ref[k]),
                                    ReferencePoint(plan.q_ref[k], plan.v_ref[k], plan.a_ref[k]),
                                    None if gravity_ref is None else gravity_ref[k])
        if not np.all(np.isfinite(commanded)):
            diverged_at = k
            break
        applied = plant.saturate(commanded)
        q.append(state_q)
        v.append(state_v)
        command.append(commanded)
        torque.append(applied)
        if k == plan.k_max:
            break
        if not plant.advance(applied):
            diverged_at = k + 1
            break
    dof = plan.q_ref.shape[1]
    series = [np.array(values, dtype=float).reshape(-1, dof) for values in (q, v, command, torque)]
    return Episodes.from_samples(spec, plan, *series, diverged_at=diverged_at)
