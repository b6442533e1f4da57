"""What `ddarm omega` and `ddarm tune` leave behind: the run folder, its report, and the controller YAML,
written only when the evidence supports the gains. No ROS: the graph episode that checks tuned gains is
run by the caller, which hands over the scores of its bag."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from ddarm.episodes.indices import INDICES
from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, arm_joints
from ddarm.recording.bags import BagError, checked_output_location
from ddarm.recording.runs import RunFolder, controller_yaml, write_new_text
from ddarm.tuning.report import write_tuning_report
from ddarm.tuning.robust import describe_scenario

# How far (relative) the bag's indices may differ from the in-process search's for the bag to confirm it.
AGREEMENT = 1e-9


def check_outputs(out: str | None, runs: str, run: str | None) -> None:
    """Refuse an `out` YAML or run folder that cannot be written as asked, before any search or episode: every
    value given is checked, an empty one too (None: not given)."""
    if out is not None:
        try:
            checked_output_location(out)
        except BagError as error:
            raise BagError(f'--out {error}' if out else '--out is empty: give the file to write') from error
    if run is not None:
        RunFolder.checked_path(run, Path(runs))
    else:
        RunFolder.checked_root(Path(runs))


def run_folder(kind: str, controller: str, runs: str, run: str | None, command: str) -> RunFolder:
    """The run folder `run` under `runs`, or <kind>-<controller>-<time> when not named."""
    name = run or time.strftime(f'{kind}-{controller}-%Y%m%d-%H%M%S')
    return RunFolder(name, runs, command=command)


def write_gains(run: RunFolder, kp, kv, spec: EpisodeSpec, provenance: str, out: str | None = None,
                name: str | None = None) -> list[str]:
    """The controller YAML in the run folder (as `name`, default <controller>.yaml), and at `out` if given (never
    overwriting)."""
    text = controller_yaml(spec.controller, kp, kv, spec.delay, spec.period, provenance,
                           joint_names=arm_joints(spec)[0], urdf=spec.model_urdf or spec.urdf, motion=spec.motion,
                           duration=spec.duration)
    written = [str(run.write_text(name or f'{spec.controller}.yaml', text))]
    if out:
        write_new_text(out, text)
        written.append(out)
    return written


def finish_omega(run: RunFolder, spec: EpisodeSpec, plan: EpisodePlan, choice, out: str | None = None,
                 warnings: tuple[str, ...] = ()) -> dict:
    """Section 2's procedure done: its report in the run's summary, the gains written if an ω was chosen.

    Returns the report (the JSON of `ddarm omega`).
    """
    steps = [dataclasses.asdict(step) for step in choice.steps]
    report = {'omega_min': choice.omega_min,
              # deg for revolute joints, mm for prismatic ones (the units of --max-error); SI beside them
              'steady_state_error_at_omega_min_deg': np.where(
                  np.array(plan.prismatic, dtype=bool), choice.steady_state_error_at_min * 1e3,
                  np.degrees(choice.steady_state_error_at_min)).tolist(),
              'steady_state_error_at_omega_min': choice.steady_state_error_at_min.tolist(),
              'joint_names': list(plan.joint_names),
              'omega': choice.omega, 'kp': None if choice.kp is None else choice.kp.tolist(),
              'kv': None if choice.kv is None else choice.kv.tolist(),
              'indices': choice.steps[-2 if not choice.steps[-1].accepted else -1].indices
              if choice.omega is not None else None,
              'steps': steps, 'spec': spec.to_dict(), 'command': run.summary['command'], 'warnings': list(warnings)}
    if choice.omega is not None:
        report['gains_files'] = write_gains(run, choice.kp, choice.kv, spec,
                                            f"ω = {choice.omega} from: {report['command']}", out)
    run.summary['omega'] = report
    run.finish('complete' if choice.omega is not None else 'no omega meets the torque conditions')
    report['run'] = str(run.path)
    return report


def relative_difference(in_process: dict, from_bag: dict) -> float:
    """The largest relative difference of the compared indices between the in-process run and the bag."""
    return max(abs(from_bag[k] - in_process[k]) / max(abs(in_process[k]), 1e-300) for k in INDICES)


def search_doubt(search, hint: bool = True) -> str:
    """What a gains file's header adds after its index when the search that found the gains is not sure of them
    (`hint` as SearchResult.certainty takes it): '' when its certificate holds."""
    if search.converged is False:
        return f'; the search did not converge ({search.certainty(hint)})'
    return '' if search.converged else f'; {search.certainty(hint)}'


def finish_tuning(run: RunFolder, template: EpisodeSpec, best_spec: EpisodeSpec, tuning, scored: dict, *,
                  index: str, method: str, seed: int, out: str | None = None) -> dict:
    """A search for `index` (I1, I2 or I) done, and its best gains' episode scored from its bag (`scored`):
    the report in the run's summary.

    The gains are written only if the bag agrees with the in-process indices: gains whose evidence
    disagrees with the search are not handed to a robot. Returns the report (the JSON of `ddarm
    tune`); its `agree` says whether the bag confirmed the search. A robust tuning adds `robust`
    (Robustness.to_dict); the bag is then of the robust gains' nominal episode.
    """
    in_process = tuning.best
    difference = relative_difference(in_process, scored)
    report = {
        'controller': template.controller, 'index': index, 'method': method, 'seed': seed,
        'kp': tuning.search.kp.tolist(), 'kv': tuning.search.kv.tolist(),
        'search_index': tuning.search.index, 'in_process': in_process,
        'from_bag': {k: scored[k] for k in INDICES}, 'max_rel_difference': difference,
        'agree': difference <= AGREEMENT, 'bag': scored['bag'],
        'start_omegas': list(tuning.start_omegas), 'start_indices': tuning.start_indices,
        'episodes': tuning.search.episodes, 'batches': tuning.search.batches,
        'wall_time_s': tuning.wall_time_s, 'episodes_per_s': tuning.episodes_per_s,
        'batch_episodes_per_s': tuning.batch_episodes_per_s,
        'restarts': [{**dataclasses.asdict(restart), 'index': restart.index if np.isfinite(restart.index) else None}
                     for restart in tuning.search.restarts],
        'restarts_within_1_percent': tuning.search.restarts_within(0.01) if tuning.search.restarts else None,
        'evolution_generations': tuning.search.evolution_generations,
        **tuning.search.certainty_fields(),
        'spec': best_spec.to_dict(), 'command': run.summary['command'],
        'joint_names': scored['joint_names'],
        'gains': {name: {'p': p, 'd': d} for name, p, d in zip(scored['joint_names'], tuning.search.kp.tolist(),
                                                                tuning.search.kv.tolist())},
        'saturated_joints': scored.get('saturated_joints', []), 'warnings': list(tuning.warnings),
    }
    if tuning.search.certificate is not None:
        report['certificate'] = tuning.search.certificate.to_dict()
    provenance = f"{index} = {scored[index]!r} (scored from {scored['bag']})"
    provenance += search_doubt(tuning.search)
    if tuning.robust is not None:
        report['robust'] = tuning.robust.to_dict()
        objective, chosen = tuning.robust.aggregate, tuning.robust.chosen
        diverging = [describe_scenario(scenario, len(chosen.kp)) for scenario, scores
                     in zip(tuning.robust.scenarios, chosen.per_scenario) if scores['diverged']]
        if diverging:
            report['warnings'].append(f"the robust gains diverge in {len(diverging)} of "
                                      f"{len(tuning.robust.scenarios)} scenarios: {'; '.join(diverging)}")
        value = chosen.aggregate(objective)
        provenance = (f"robust over {len(tuning.robust.scenarios)} scenarios ("
                      + (f'{objective} {index} = {value!r}' if value is not None else 'diverging in some')
                      + f"); its nominal episode {provenance}")
    if report['agree']:
        report['gains_files'] = write_gains(run, tuning.search.kp, tuning.search.kv, best_spec,
                                            f"{provenance}\nfrom: {report['command']}", out)
    else:
        report['gains_files'] = []
    report['report'] = str(write_tuning_report(run, report))
    run.summary['tune'] = report
    run.finish('complete' if report['agree'] else 'in-process and bag indices disagree')
    report['run'] = str(run.path)
    return report
