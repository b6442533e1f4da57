"""Episodes: the one result type of every path (in-process, batch, through ROS, from a bag), with an episode axis."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ddarm.episodes.indices import score_series
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec


@dataclass(frozen=True)
class Episodes:
    """B episodes of one template, member b with its own gains (and τ, torque limit, plant mass scale).

    I1 (2.5), I2 and I (3.2) have shape (B,), divided by k_max; a member that diverged at sample j
    (diverged_at[b] = j, else -1) is scored on its samples before j. The optional series q, q̇,
    command (what the law asked for) and torque (what the actuators applied) have shape
    (B, k_max + 1, n) and hold NaN from samples_scored[b] on. `varied` names the per-member
    variations that replace the template's (tau, torque_limit, mass_scale).
    """

    template: EpisodeSpec
    plan: EpisodePlan
    kp: np.ndarray
    kv: np.ndarray
    I1: np.ndarray
    I2: np.ndarray
    I: np.ndarray  # noqa: E741 (the paper's name)
    diverged_at: np.ndarray
    samples_scored: np.ndarray
    varied: dict = dataclasses.field(default_factory=dict)
    q: np.ndarray | None = None
    v: np.ndarray | None = None
    command: np.ndarray | None = None
    torque: np.ndarray | None = None
    plant_report: dict | None = None  # over ROS: the plant node's end-of-episode diagnostics (B = 1)

    @classmethod
    def from_samples(cls, spec: EpisodeSpec, plan: EpisodePlan, q, v, command, torque,
                     diverged_at: int | None = None, plant_report: dict | None = None) -> Episodes:
        """One recorded episode (B = 1) from its scored samples j = 0 …, scored by the indices' one definition."""
        q, v, command, torque = (np.asarray(x, dtype=float) for x in (q, v, command, torque))
        indices = score_series(plan.q_ref, q, torque, plan.nominal, plan.k_max)
        shape = (1, plan.k_max + 1, q.shape[-1])
        padded = []
        for values in (q, v, command, torque):
            series = np.full(shape, np.nan)
            series[0, :len(values)] = values
            padded.append(series)
        return cls(template=spec, plan=plan, kp=np.array([spec.kp]), kv=np.array([spec.kv]),
                   I1=np.array([indices['I1']]), I2=np.array([indices['I2']]), I=np.array([indices['I']]),
                   diverged_at=np.array([-1 if diverged_at is None else diverged_at]),
                   samples_scored=np.array([len(torque)]), q=padded[0], v=padded[1], command=padded[2],
                   torque=padded[3], plant_report=plant_report)

    @property
    def size(self) -> int:
        return len(self.I)

    @property
    def diverged(self) -> np.ndarray:
        return self.diverged_at >= 0

    def indices(self, member: int = 0) -> dict[str, float]:
        """Member `member`'s I1, I2 and I, under the JSON's keys."""
        return {'I1': float(self.I1[member]), 'I2': float(self.I2[member]), 'I': float(self.I[member])}

    def spec(self, member: int = 0) -> EpisodeSpec:
        """The specification that runs member `member` alone."""
        changes = {'kp': tuple(self.kp[member]), 'kv': tuple(self.kv[member])}
        for name, values in self.varied.items():
            value = values[member]
            changes[name] = float(value) if np.ndim(value) == 0 else tuple(float(x) for x in value)
        return dataclasses.replace(self.template, **changes)

    def torque_limit(self, member: int = 0) -> np.ndarray | None:
        if 'torque_limit' in self.varied:
            return np.array(self.varied['torque_limit'][member], dtype=float)
        return self.plan.torque_limit

    def scored(self, name: str, member: int = 0) -> np.ndarray:
        """The series `name` (q, v, command, torque or errors) over member `member`'s scored samples."""
        count = int(self.samples_scored[member])
        if name == 'errors':
            return self.plan.q_ref[:count] - self.q[member, :count]
        return getattr(self, name)[member, :count]

    def summary(self, member: int = 0) -> dict:
        """The JSON-ready figures: indices, divergence, per-joint maxima, and the spec that made them."""
        at = int(self.diverged_at[member])
        limit = self.torque_limit(member)
        scored = int(self.samples_scored[member])
        maxima = {}
        if self.torque is not None:
            errors, torque = self.scored('errors', member), self.scored('torque', member)
            maxima = {'max_abs_error_deg': np.degrees(np.max(np.abs(errors), axis=0)).tolist() if scored else None,
                      'max_abs_torque': np.max(np.abs(torque), axis=0).tolist() if scored else None}
        return {
            **self.indices(member),
            'diverged': at >= 0,
            'diverged_at_sample': at if at >= 0 else None,
            'samples_scored': scored,
            'k_max': self.plan.k_max,
            **maxima,
            'max_abs_nominal_torque': np.max(np.abs(self.plan.nominal), axis=0).tolist(),
            'torque_limit': None if limit is None else limit.tolist(),
            'spec': self.spec(member).to_dict(),
            **({'plant_report': self.plant_report} if self.plant_report is not None else {}),
        }
