"""The page a tuning leaves in its run folder: report.md and a figure of the best gains' recorded episode.

Everything on it is read from the run's summary and the bag the gains were scored from, so the
page shows the evidence itself, not the search's own view of it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ddarm.episodes.indices import INDICES
from ddarm.recording.bags import bag_result, read_episode_bag
from ddarm.recording.runs import RunFolder, write_new_file
from ddarm.reporting.html import markdown_to_html
from ddarm.reporting.text import figure_text, markdown_code, markdown_text

DPI = 110
FIGURE_NAME = 'best-episode.png'


def episode_figure(path: Path, bag_path: Path | str, title: str) -> None:
    """Per joint: q^d and q, the error, and the applied against the nominal torque (and its limit), from the bag.

    The joint names and `title` come from files (the URDF, the motion): they are drawn as the text they are."""
    episode = bag_result(read_episode_bag(bag_path))
    plan, joints = episode.plan, episode.joint_names
    prismatic = plan.prismatic or (False,) * len(joints)
    count = int(episode.samples_scored[0])
    times, q, torque = plan.times[:count], episode.scored('q'), episode.scored('torque')
    limit = episode.torque_limit()
    figure = Figure(figsize=(12, 2.3 * len(joints) + 0.8), dpi=DPI)
    FigureCanvasAgg(figure)
    axes = figure.subplots(len(joints), 3, sharex=True, squeeze=False)
    for j, joint in enumerate(joints):
        # Angles in degrees, lengths in mm: the units an engineer reads off a robot's pendant.
        scale, unit, effort = (1e3, 'mm', 'N') if prismatic[j] else (np.degrees(1.0), 'deg', 'N m')
        axes[j, 0].plot(plan.times, plan.q_ref[:, j] * scale, 'k--', linewidth=1.0, label='$q^d$')
        axes[j, 0].plot(times, q[:, j] * scale, color='tab:red', label='$q$')
        axes[j, 0].set_ylabel(f'{figure_text(joint)}\nposition ({unit})', parse_math=False)
        axes[j, 1].plot(times, (plan.q_ref[:count, j] - q[:, j]) * scale, color='tab:red')
        axes[j, 1].axhline(0.0, color='0.6', linewidth=0.8)
        axes[j, 1].set_ylabel(f'error ({unit})')
        edges = np.append(times, count * (plan.times[1] - plan.times[0]))
        axes[j, 2].step(edges, np.append(torque[:, j], torque[-1, j]), where='post', color='tab:red', label='$P$')
        axes[j, 2].plot(plan.times, plan.nominal[:, j], 'k--', linewidth=1.0, label='$P^{nom}$')
        label = f'torque ({effort})'
        if limit is not None:
            largest = max(np.max(np.abs(torque[:, j])), np.max(np.abs(plan.nominal[:, j])))
            if limit[j] < 1.5 * largest:  # a limit far off the torques would squash them flat
                for sign in (-1, 1):
                    axes[j, 2].axhline(sign * limit[j], color='tab:orange', linewidth=0.8, linestyle=':')
            else:
                label += f'\nlimit ±{limit[j]:.3g}'
        axes[j, 2].set_ylabel(label)
        for axis in axes[j]:
            axis.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    axes[0, 2].legend(fontsize=8)
    axes[0, 0].set_title('position')
    axes[0, 1].set_title('tracking error $e = q^d - q$')
    axes[0, 2].set_title('applied torque (held over each period)')
    for axis in axes[-1]:
        axis.set_xlabel('time t (s)')
    figure.suptitle(figure_text(title), parse_math=False)
    figure.tight_layout(rect=(0, 0, 1, 0.97))
    write_new_file(path, lambda file: figure.savefig(file, format='png'))


def _row(values) -> str:
    return '| ' + ' | '.join(values) + ' |'


def _index_cell(value: float | None) -> str:
    return 'diverged' if value is None else f'{value:.9g}'


def robustness_section(robust: dict, index: str, joints: list[str]) -> list[str]:
    """The Markdown of a robust tuning: each scenario's index for the robust gains and the nominal optimum."""
    chosen, nominal = robust['chosen'], robust['nominal_optimum']
    lines = ['', '## Robustness', '',
             f"The gains above minimise the {robust['objective']} {index} over {len(robust['scenarios'])} scenarios "
             f"(every combination of τ, plant mass scale and external torque P^z); the nominal optimum minimises "
             f"{index} of the episode above alone ({robust['nominal_search']['episodes']} episodes). Each scenario "
             f"is run alone with each gain set.", '',
             _row(['τ (s)', 'mass scale', 'P^z (N m)', f'robust {index}', f'nominal optimum {index}']),
             _row(['---'] * 5)]
    for scenario, ours, theirs in zip(robust['scenarios'], chosen['per_scenario'], nominal['per_scenario']):
        scale = scenario['mass_scale']
        lines.append(_row([f"{scenario['tau']:g}", ', '.join(f'{s:g}' for s in (scale[:1] if len(set(scale)) == 1
                                                                                 else scale)),
                           'none' if scenario['external_torque'] is None
                           else ', '.join(f'{p:g}' for p in scenario['external_torque']),
                           _index_cell(None if ours['diverged'] else ours[index]),
                           _index_cell(None if theirs['diverged'] else theirs[index])]))
    for name in ('worst', 'mean'):
        lines.append(_row([f'**{name}**', '', '', _index_cell(chosen[name]), _index_cell(nominal[name])]))
    lines += ['', _row(['joint', 'nominal optimum k_p', 'nominal optimum k_v']), _row(['---'] * 3)]
    lines += [_row([markdown_text(name), f'{p:.6g}', f'{d:.6g}'])
              for name, p, d in zip(joints, nominal['kp'], nominal['kv'])]
    return lines


def local_runs_text(report: dict) -> str:
    """The global search's confidence figure, from `ddarm tune`'s report: its local runs' bests and how many reached."""
    bests = ', '.join('diverged' if restart['index'] is None else f"{restart['index']:.6g}"
                      for restart in report['restarts'])
    return (f"{len(report['restarts'])} independent runs (differential evolution: {report['evolution_generations']} "
            f"generations in all), best {report['index']} = {bests}: {report['restarts_within_1_percent']} within 1 % "
            'of the best')


def certificate_section(certificate: dict, index: str) -> list[str]:
    """The Markdown of the global search's certificate: its verdict, every independent run's best, the basins."""
    lines = ['', '## Certificate', '',
             ('**Converged**: ' if certificate['converged'] else '**Not converged**: ')
             + markdown_text(certificate['summary']) + '.', '',
             f"Converged means: at least {certificate['required_runs']} independent runs (and a third of them) within "
             '0.5 % of the best, one of them from the ω-rule starts (Nelder-Mead, the polish of its ends) and one a '
             f"global run (differential evolution, wide CMA-ES), after at least {certificate['required_global_runs']} "
             'global runs, and the runs since the best was first reached spent as many episodes as those '
             f"before. {certificate['episodes']} of at most {certificate['budget']} episodes spent.", '',
             _row(['run', f'best {index}', 'episodes']), _row(['---'] * 3)]
    lines += [_row([markdown_text(run['run']), _index_cell(run['index']), str(run['episodes'])])
              for run in certificate['runs']]
    polish = certificate.get('final_polish')  # absent from certificates written before it
    if polish is not None:
        lines += ['', 'The runs left no budget for a final polish of the best point.' if not polish['episodes'] else
                  f"Then a final polish of the best point (not one of the runs above): best {index} "
                  f"{_index_cell(polish['index'])} in {polish['episodes']} episodes."]
    lines += ['', _row(['basin', f'best {index}', 'runs ending in it']), _row(['---'] * 3)]
    lines += [_row([str(number + 1), _index_cell(basin['index']), str(basin['runs'])])
              for number, basin in enumerate(certificate['basins'])]
    return lines


def write_tuning_report(run: RunFolder, report: dict) -> Path:
    """report.md (and its figure) for a finished `ddarm tune`: the arm, the gains by joint, the evidence.

    Every text from a file or the command line (joint names, paths, the command, warnings) is escaped
    (ddarm.reporting.text): it reads as itself, in report.md and on the page.
    Returns report.md's path; report.html, the same page self-contained (the figure embedded), is written beside it.
    """
    spec = report['spec']
    joints = report['joint_names']
    motion = spec['motion'] or f"the paper's trajectory {spec['trajectory']}"
    title = (f"{report['controller']} on {Path(spec['urdf']).name if spec['urdf'] else 'the paper arm'}, "
             f"{Path(motion).name}: {report['index']} minimised")
    figure = run.path / FIGURE_NAME
    episode_figure(figure, report['bag'], title)
    lines = [f'# {markdown_text(title)}', '', f"Command: {markdown_code(report['command'])}", '',
             f"- plant URDF: {markdown_code(spec['urdf'] or 'config/ddarm.urdf')}"
             + (f"; controller model: {markdown_code(spec['model_urdf'])}" if spec['model_urdf'] else ''),
             f'- motion: {markdown_code(motion)}, T = {spec["duration"]:g} s, Δ = {spec["period"]:g} s, compute '
             f'delay d = {spec["delay"]}, τ = {spec["tau"]:g} s, torque limit {spec["torque_limit"]}',
             f"- search: {report['method']}, {report['episodes']} episodes in {report['wall_time_s']:.2f} s "
             f"({report['episodes_per_s']:.0f} episodes/s), best "
             + (f"{report['robust']['objective']} {report['index']} over the scenarios" if 'robust' in report
                else report['index']) + f" = {report['search_index']:.9g}"
             + (' (**not converged**: see the certificate)' if report.get('converged') is False else
                '' if report.get('converged') else f" (**{markdown_text(report['certainty'])}**)"),
             *([f"- {local_runs_text(report)}"] if report['restarts'] else []),
             '', '## Gains', '', _row(['joint', 'k_p', 'k_v']), _row(['---'] * 3)]
    lines += [_row([markdown_text(name), f'{p:.6g}', f'{d:.6g}'])
              for name, p, d in zip(joints, report['kp'], report['kv'])]
    if 'certificate' in report:
        lines += certificate_section(report['certificate'], report['index'])
    if 'robust' in report:
        lines += robustness_section(report['robust'], report['index'], joints)
    lines += ['', '## Evidence', '', _row(['', *INDICES]), _row(['---'] * (len(INDICES) + 1)),
              _row(['in-process', *(f"{report['in_process'][k]:.9g}" for k in INDICES)]),
              _row(['from the bag', *(f"{report['from_bag'][k]:.9g}" for k in INDICES)]), '',
              f"Largest relative difference {report['max_rel_difference']:.2e}: "
              + ('the bag confirms the search.' if report['agree'] else
                 '**the bag does not confirm the search: no gains were written.**'),
              f"Bag: {markdown_code(report['bag'])}"]
    if report.get('saturated_joints'):
        lines.append('At their torque limit in the recorded episode: '
                     f"{', '.join(markdown_text(name) for name in report['saturated_joints'])}.")
    for warning in report.get('warnings', []):
        lines.append(f'- WARNING: {markdown_text(warning)}')
    if report['gains_files']:
        lines += ['', 'Controller YAML: ' + ', '.join(markdown_code(name) for name in report['gains_files'])]
    lines += ['', f'![the best gains\' recorded episode]({FIGURE_NAME})', '']
    page = run.write_text('report.md', '\n'.join(lines))
    run.log.info('wrote %s', markdown_to_html(page, run.path / 'report.html'))
    return page
