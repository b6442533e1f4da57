"""`ddarm validate`: a controller YAML run on a robot (MuJoCo) beside ddarm's prediction of it, in-process.

The prediction is the episode the YAML describes on ddarm's plant (its URDF, its motion); the measurement is the
same law, gains and motion against the robot's MJCF. Side by side they say how far the robot is from the URDF the
gains were tuned on. A side that diverged or saturated is said to have done so beside its numbers: its indices
cover only the samples before the divergence, and no ratio is formed from them.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
from pathlib import Path

import numpy as np

from ddarm.cli.arguments import (absolute_path, add_robot_arguments, add_run_arguments, add_torque_limit_arguments,
                                 finite, robot_joints, torque_limit)
from ddarm.cli.output import print_json
from ddarm.episodes.engine import run_episode
from ddarm.episodes.indices import INDICES, PAPER_EQUATIONS
from ddarm.episodes.result import Episodes
from ddarm.episodes.spec import EpisodeError, check_episode, episode_robot, loop_stability_warnings
from ddarm.motion.programmed import PAPER_TRAJECTORIES
from ddarm.recording.gains_file import GainsFile, read_gains_file, validation_spec
from ddarm.recording.runs import RunFolder, write_new_file
from ddarm.reporting.text import figure_text, markdown_code, markdown_text

FIGURE_NAME, PAGE_NAME = 'errors.png', 'validation.md'
SIDES = ('predicted', 'measured')
ROBOT_MODES = ('lockstep', 'realtime')  # ddarm.ros.robot_session.MODES, without loading ROS to list them
DPI = 110
# An applied torque this far (relative) below the law's command was cut by a limit: a motor's ctrl = τ / (gear ·
# gain) and its force gear · gain · ctrl differ from τ by rounding alone, many orders of magnitude less.
SATURATION_TOLERANCE = 1e-9
# The indices as the paper numbers them: I1 (2.5), I (3.2).
EQUATION_LABELS = {index: f'{index} ({equation})' for equation, index in PAPER_EQUATIONS.items()}


def add_validate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--gains', required=True, metavar='YAML',
                        help='the controller YAML (as `ddarm tune --out` writes it: gains keyed by joint, or kp and '
                             'kv), with the urdf and motion it names')
    add_robot_arguments(parser)
    parser.add_argument('--trajectory', type=int, choices=PAPER_TRAJECTORIES,
                        help="the paper's motion, for a YAML that names no motion (default 1)")
    parser.add_argument('--tau', type=finite, default=0.0,
                        help='initial velocity disturbance (3.1): q̇(0) = -q̇^d(τ) (default 0)')
    add_torque_limit_arguments(parser, "the YAML URDF's <limit effort> of each joint")
    measure = parser.add_mutually_exclusive_group()
    measure.add_argument('--ros', action='store_true',
                         help='measure through the ROS graph (the plant node stepping the robot, the controller node, '
                              'lockstep) and keep its bag in the run folder (bags/measured)')
    measure.add_argument('--robot', nargs='?', const='lockstep', choices=ROBOT_MODES, metavar='MODE',
                         help='measure as on a ros2_control robot: `ddarm robot` and the controller node in robot mode '
                              '(a timer, the efforts as a Float64MultiArray); lockstep (the default: exact, on the '
                              "robot's /clock) or realtime (both free-running on the wall clock); keeps its bag in "
                              'the run folder (bags/measured)')
    add_run_arguments(parser, 'validate')


def saturated_joints(result: Episodes) -> list[str]:
    """The joints whose applied torque fell short of the law's command at some scored sample: cut by ddarm's torque
    limit or, on a robot, by its own actuator ranges (which the episode's saturated_joints, from ddarm's limit
    alone, does not see)."""
    command, torque = result.scored('command'), result.scored('torque')
    cut = np.abs(command - torque) > SATURATION_TOLERANCE * np.maximum(np.abs(command), 1.0)
    return [name for name, hit in zip(result.joint_names, cut.any(axis=0)) if hit]


def ratio(measured: float | None, predicted: float | None) -> float | None:
    """measured / predicted, or None where either is missing (a side that diverged) or the prediction is 0."""
    if measured is None or predicted is None or predicted == 0:
        return None
    return measured / predicted


def comparison_rows(report: dict, prismatic: tuple[bool, ...]) -> list[tuple[str, float | None, float | None]]:
    """(label, predicted, measured) for I1, I2, I and each joint's peak |e| (deg, or mm for a prismatic joint); None
    for a peak over no sample (a side that diverged at sample 0)."""
    predicted, measured = report['predicted'], report['measured']
    rows = [(EQUATION_LABELS.get(index, index), predicted[index], measured[index]) for index in INDICES]
    for j, joint in enumerate(predicted['joint_names']):
        scale, unit = (1e3, 'mm') if prismatic[j] else (np.degrees(1.0), 'deg')
        peaks = [None if summary['max_abs_error'] is None else summary['max_abs_error'][j] * scale
                 for summary in (predicted, measured)]
        rows.append((f'max |e| {joint} ({unit})', *peaks))
    return rows


def outcome(summary: dict, saturated: list[str]) -> str:
    """What happened on one side, in a few words for a table cell."""
    words = []
    if summary['diverged']:
        words.append(f"DIVERGED at sample {summary['diverged_at']}")
    if saturated:
        words.append(f'saturated ({len(saturated)} joint{"s" if len(saturated) > 1 else ""})')
    return ', '.join(words) or 'ran to T'


def side_notes(report: dict, period: float) -> list[str]:
    """A sentence per side that diverged or saturated, naming the sample and the joints."""
    notes = []
    for side in SIDES:
        summary = report[side]
        if summary['diverged']:
            at = summary['diverged_at']
            notes.append(f"{side}: DIVERGED at sample {at} (t = {at * period:g} s): its indices and peaks (*) cover "
                         f"only the {summary['samples_scored']} samples before it; no ratio is formed from them")
        if report['saturated'][side]:
            notes.append(f"{side}: saturated: {', '.join(report['saturated'][side])} (the torque applied fell short "
                         "of the law's command)")
    return notes


def _number(value: float | None, partial: bool = False) -> str:
    return '-' if value is None else f'{value:.6g}' + ('*' if partial else '')


def table_cells(report: dict, prismatic: tuple[bool, ...]) -> list[list[str]]:
    """The comparison as text cells: label, predicted, measured, measured / predicted; the figures of a side that
    diverged marked *, and its outcome beside them."""
    partial = [report[side]['diverged'] for side in SIDES]
    whole = not any(partial)
    cells = [[label, _number(p, partial[0]), _number(m, partial[1]), _number(ratio(m, p) if whole else None)]
             for label, p, m in comparison_rows(report, prismatic)]
    cells.append(['outcome', *(outcome(report[side], report['saturated'][side]) for side in SIDES), ''])
    return cells


def print_validation(report: dict, gains: GainsFile, prismatic: tuple[bool, ...]) -> None:
    spec, robot = report['measured']['spec'], report['measured']['robot']
    motion = spec['motion'] or f"the paper's trajectory {spec['trajectory']}"
    print(f"{gains.controller} gains from {gains.path}: delay {spec['delay']}, Δ = {spec['period']} s")
    print(f"  predicted: ddarm's plant on {spec['urdf'] or 'config/ddarm.urdf'}, motion {motion}, T = "
          f"{spec['duration']} s, τ = {spec['tau']} s, torque limit {spec['torque_limit']}")
    print(f"  measured: {robot['mjcf']} ({robot['engine']}, {robot['integrator']}, {robot['steps_per_period']} steps "
          f"of {robot['timestep']:g} s per period, torques through {robot['torque_through']})")
    header = ['', *SIDES, 'measured/predicted']
    cells = table_cells(report, prismatic)
    widths = [max(len(row[i]) for row in [header, *cells]) for i in range(len(header))]
    for row in [header, *cells]:
        print('  ' + row[0].ljust(widths[0]) + ''.join('  ' + cell.rjust(width)
                                                       for cell, width in zip(row[1:], widths[1:])))
    for note in side_notes(report, spec['period']):
        print(f'  {note}')
    for warning in report['warnings']:
        print(f'  WARNING: {warning}')
    print(f"  run folder {report['run']}")


def error_figure(path: Path, predicted: Episodes, measured: Episodes, title: str) -> None:
    """One subplot per joint: the tracking error e = q^d - q over time, predicted and measured, each over its scored
    samples; degrees for a revolute joint, mm for a prismatic one. Joint names and `title` come from files: drawn
    as the text they are."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # matplotlib only for a command that draws
    from matplotlib.figure import Figure

    joints, prismatic = predicted.joint_names, predicted.plan.prismatic
    figure = Figure(figsize=(9, 1.8 * len(joints) + 1.0), dpi=DPI)
    FigureCanvasAgg(figure)
    axes = figure.subplots(len(joints), 1, sharex=True, squeeze=False)[:, 0]
    for side, result, style in (('predicted (ddarm)', predicted, {'color': 'k', 'linestyle': '--'}),
                                ('measured (robot)', measured, {'color': 'tab:red'})):
        count = int(result.samples_scored[0])
        times, errors = result.plan.times[:count], result.scored('errors')
        label = side + (f', DIVERGED at t = {result.plan.times[count]:g} s' if result.diverged[0] else '')
        for j, axis in enumerate(axes):
            scale = 1e3 if prismatic[j] else np.degrees(1.0)
            axis.plot(times, errors[:, j] * scale, linewidth=1.0, label=label, **style)
    for j, (axis, joint) in enumerate(zip(axes, joints)):
        axis.axhline(0.0, color='0.6', linewidth=0.8)
        axis.set_title(figure_text(joint), parse_math=False, fontsize=9)
        axis.set_ylabel(f"e ({'mm' if prismatic[j] else 'deg'})")
        axis.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel('time t (s)')
    figure.suptitle(figure_text(title), parse_math=False)
    figure.tight_layout(rect=(0, 0, 1, 0.97))
    write_new_file(path, lambda file: figure.savefig(file, format='png'))


def _row(values) -> str:
    return '| ' + ' | '.join(values) + ' |'


def write_page(run: RunFolder, report: dict, prismatic: tuple[bool, ...], title: str) -> Path:
    """validation.md: the YAML, the prediction and the robot, the comparison table, what diverged or saturated,
    the warnings and the figure. Every text from a file or the command line is escaped (ddarm.reporting.text)."""
    spec, robot = report['measured']['spec'], report['measured']['robot']
    motion = spec['motion'] or f"the paper's trajectory {spec['trajectory']}"
    lines = [f'# {markdown_text(title)}', '', f"Command: {markdown_code(run.summary['command'])}", '',
             f"- gains: {markdown_code(report['gains'])} ({markdown_text(spec['controller'])}, compute delay d = "
             f"{spec['delay']}, Δ = {spec['period']:g} s)",
             f"- predicted: ddarm's plant on {markdown_code(spec['urdf'] or 'config/ddarm.urdf')}, motion "
             f"{markdown_code(motion)}, T = {spec['duration']:g} s, τ = {spec['tau']:g} s, torque limit "
             f"{markdown_text(spec['torque_limit'])}",
             f"- measured: {markdown_code(robot['mjcf'])}, {markdown_text(robot['engine'])}, "
             f"{markdown_text(robot['integrator'])}, {robot['steps_per_period']} steps of {robot['timestep']:g} s per "
             f"period, torques through {markdown_text(robot['torque_through'])}",
             '', '## Prediction and measurement', '',
             _row(['', *SIDES, 'measured / predicted']), _row(['---'] * 4)]
    lines += [_row([markdown_text(cell) for cell in row]) for row in table_cells(report, prismatic)]
    notes = side_notes(report, spec['period'])
    if notes:
        lines.append('')
        lines += [f'- **{markdown_text(note)}**' for note in notes]
    if report['warnings']:
        lines.append('')
        lines += [f'- WARNING: {markdown_text(warning)}' for warning in report['warnings']]
    lines += ['', f'![the tracking error of each joint, predicted and measured]({FIGURE_NAME})', '']
    return run.write_text(PAGE_NAME, '\n'.join(lines))


def command_validate(args: argparse.Namespace) -> int:
    from ddarm.tuning.outputs import check_outputs, run_folder

    gains = read_gains_file(args.gains)
    if not args.mjcf:
        raise EpisodeError('--mjcf FILE is required: the robot (an MJCF, or a URDF MuJoCo compiles) the YAML is '
                           'validated on')
    predicted_spec = validation_spec(gains, trajectory=args.trajectory, tau=args.tau,
                                     torque_limit=torque_limit(args))
    measured_spec = dataclasses.replace(predicted_spec, mjcf=absolute_path(args.mjcf),
                                        mjcf_joints=robot_joints(args, gains.joint_names))
    if args.robot and measured_spec.motion is None:
        raise EpisodeError('--robot runs the controller node in robot mode, which reads its reference from a motion '
                           'file: the YAML names none (give it a motion)')
    check_outputs(None, args.runs, args.run)
    predicted_plan, measured_plan = check_episode(predicted_spec), check_episode(measured_spec)
    warnings = []
    if gains.motion is None and args.trajectory is None:
        warnings.append(f"the YAML names no motion: validated on the paper's trajectory {predicted_spec.trajectory} "
                        '(assumed; --trajectory gives another)')
    warnings += list(predicted_plan.warnings) + loop_stability_warnings(predicted_spec, "the YAML's gains")
    warnings += episode_robot(measured_spec, measured_plan).warnings()
    robot_name = Path(measured_spec.mjcf).name
    title = f'{gains.controller} gains of {Path(gains.path).name} on {robot_name}: predicted and measured'
    command = shlex.join(['ddarm', *args.argv])
    with run_folder('validate', gains.controller, args.runs, args.run, command) as run:
        predicted = run_episode(predicted_spec, predicted_plan)
        bag = None  # in-process: nothing crossed ROS
        transport = 'in-process'
        if args.ros or args.robot:
            bag = run.path / 'bags' / 'measured'
            bag.parent.mkdir()
        if args.ros:
            from ddarm.ros.session import run_graph_episode  # ROS only when asked for

            measured = run_graph_episode(measured_spec, bag=bag, command=command)
            transport = 'ros-lockstep'
        elif args.robot:
            from ddarm.ros.robot_session import counted_faults, record_robot_episode

            measured, _, counters = record_robot_episode(measured_spec, bag, args.robot, command=command)
            transport = f'ros-robot-{args.robot}'
            warnings += [f'measured through ddarm robot ({args.robot}): {fault}' for fault in counted_faults(counters)]
        else:
            measured = run_episode(measured_spec, measured_plan)
        whole = not (predicted.diverged[0] or measured.diverged[0])  # else the indices cover different samples
        predicted_indices, measured_indices = predicted.indices(), measured.indices()
        report = {
            'predicted': predicted.summary(),
            'measured': {**measured.summary(), 'robot': episode_robot(measured_spec, measured_plan).description(),
                         'transport': transport},
            'bag': None if bag is None else str(bag),
            'ratio': {index: ratio(measured_indices[index], predicted_indices[index]) if whole else None
                      for index in INDICES},
            'saturated': {'predicted': saturated_joints(predicted), 'measured': saturated_joints(measured)},
            'gains': gains.path,
            'warnings': warnings,
            'run': str(run.path),
        }
        error_figure(run.path / FIGURE_NAME, predicted, measured, title)
        write_page(run, report, predicted_plan.prismatic, title)
        run.finish('complete', **report)
    if args.json:
        print_json(report)
    else:
        print_validation(report, gains, predicted_plan.prismatic)
    return 0
