"""Episodes: the one result type of every path (in-process, batch, through ROS, from a bag), with an episode axis."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ddarm.episodes.indices import score_series
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec
from ddarm.errors import DdarmError
from ddarm.physics.plant import DEFAULT_MAX_POSITION, DEFAULT_MAX_VELOCITY, beyond_bounds

# How many sample numbers a refusal lists, per kind of missing evidence.
LISTED_SAMPLES = 10


class RecordingError(DdarmError, ValueError):
    """Recorded samples that do not make a scored episode; the text names the samples missing.

    `samples` holds every sample index named. Callers re-raise it as their own error (the ROS
    driver as GraphEpisodeError, the bag scorer as BagError naming the bag).
    """

    def __init__(self, message: str, samples: list[int] | None = None) -> None:
        super().__init__(message)
        self.samples = samples or []


def _listed(samples: list[int]) -> str:
    shown = samples[:LISTED_SAMPLES]
    more = len(samples) - len(shown)
    return f'{shown}' + (f' (and {more} more)' if more else '')


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
        """One recorded episode (B = 1) from its scored samples j = 0 …, scored by the indices' one definition.

        RecordingError unless q, v, command and torque are each (samples, n) for the plan's n joints,
        with the same number of samples, at most k_max + 1.
        """
        q, v, command, torque = (np.asarray(x, dtype=float) for x in (q, v, command, torque))
        dof = plan.q_ref.shape[-1]
        shapes = {'q': q.shape, 'v': v.shape, 'command': command.shape, 'torque': torque.shape}
        if len(set(shapes.values())) != 1 or q.ndim != 2 or q.shape[1] != dof or len(q) > plan.k_max + 1:
            raise RecordingError(f'q, v, command and torque must each have shape (samples, {dof}), the same '
                                 f'number of samples, at most k_max + 1 = {plan.k_max + 1}; got {shapes}')
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

    @classmethod
    def from_recorded(cls, spec: EpisodeSpec, plan: EpisodePlan, states: Mapping[int, tuple],
                      commands: Mapping[int, np.ndarray], plant_report: dict | None = None) -> Episodes:
        """One episode (B = 1) from what a recording holds by sample index n: the one rule for every recording.

        states[n] = (q, v, effort): the state at t_n, and the torque the actuators applied over
        [t_{n-1}, t_n) (None at n = 0); a state at n > 0 without a position (q None) says the plant
        diverged during the period before t_n, and so does one beyond the plant's bounds (`beyond_bounds`), which
        a plant that is not ddarm's may publish without that mark. commands[n]: what the law asked for at sample n.
        States past sample k_max + 1 are not part of the episode.

        The scored samples are j = 0 … k_max, or 0 … j - 1 for a plant that diverged at j
        (diverged_at = j). Sample n's torque is the effort of state n + 1: the plant publishes the
        torque it held over a period with the state that period ends in.

        RecordingError names the samples missing: a state with position and velocity for each
        scored sample, the next state's effort for each, and a command for each.
        """
        if 0 in states and beyond_bounds(*states[0][:2]):
            raise RecordingError(f"the state of sample 0 is beyond the plant's bounds ({DEFAULT_MAX_POSITION:g} rad or "
                                 f'm, {DEFAULT_MAX_VELOCITY:g} rad/s or m/s): no episode starts there', [0])
        diverged_at = next((n for n in sorted(states) if 0 < n <= plan.k_max + 1
                            and (states[n][0] is None or beyond_bounds(*states[n][:2]))), None)
        last = plan.k_max if diverged_at is None else diverged_at - 1
        scored = range(last + 1)

        def has(n: int, field: int) -> bool:
            return n in states and states[n][field] is not None

        missing = {'the states (position and velocity) of samples {}': [
                       n for n in scored if not (has(n, 0) and has(n, 1))],
                   'the torques applied over samples {} (each the effort of the next state)': [
                       n for n in scored if not has(n + 1, 2)],
                   'the commands of samples {}': [n for n in scored if commands.get(n) is None]}
        if any(missing.values()):
            named = '; '.join(kind.format(_listed(samples)) for kind, samples in missing.items() if samples)
            raise RecordingError(f'{named} are missing: the episode is incomplete',
                                 sorted({n for samples in missing.values() for n in samples}))
        return cls.from_samples(spec, plan, q=np.array([states[n][0] for n in scored]),
                                v=np.array([states[n][1] for n in scored]),
                                command=np.array([commands[n] for n in scored]),
                                torque=np.array([states[n + 1][2] for n in scored]),
                                diverged_at=diverged_at, plant_report=plant_report)

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

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.plan.joint_names

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
            largest = np.max(np.abs(errors), axis=0) if scored else None
            # Degrees for angles only: a prismatic joint's error is a length (max_abs_error has it in m).
            angle = ~np.array(self.plan.prismatic or (False,) * errors.shape[1], dtype=bool)
            maxima = {'max_abs_error': largest.tolist() if scored else None,
                      'max_abs_error_deg': [float(np.degrees(e)) if a else None for e, a in zip(largest, angle)]
                      if scored else None,
                      'max_abs_torque': np.max(np.abs(torque), axis=0).tolist() if scored else None}
            if limit is not None and scored:
                # The command beyond its limit: the actuator applied the limit instead.
                beyond = np.max(np.abs(self.scored('command', member)), axis=0) > limit
                maxima['saturated_joints'] = [name for name, hit in zip(self.joint_names, beyond) if hit]
        return {
            **self.indices(member),
            'joint_names': list(self.joint_names),
            'diverged': at >= 0,
            'diverged_at': at if at >= 0 else None,
            'diverged_at_sample': at if at >= 0 else None,  # the deprecated name of diverged_at, for old scripts
            'samples_scored': scored,
            'k_max': self.plan.k_max,
            **maxima,
            'max_abs_nominal_torque': np.max(np.abs(self.plan.nominal), axis=0).tolist(),
            'torque_limit': None if limit is None else limit.tolist(),
            'spec': self.spec(member).to_dict(),
            **({'plant_report': self.plant_report} if self.plant_report is not None else {}),
        }
