"""`ddarm transfer`: tune on the URDF, validate on the robot, identify the robot from its own bags, tune again on the
identified URDF and validate that: whether the gains' prediction transfers to the robot, in one run folder."""

from __future__ import annotations

import argparse
import dataclasses
import math
import shlex
import sys
from pathlib import Path

from ddarm.cli.arguments import (absolute_path, add_robot_arguments, add_run_arguments, finite, robot_joints, seed,
                                 whole_number)
from ddarm.cli.output import print_json
from ddarm.cli.tune import index_name
from ddarm.cli.validate import error_figure, saturated_joints
from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.control.laws import CONTROLLERS
from ddarm.episodes.engine import run_episode
from ddarm.episodes.result import Episodes
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, arm_joints, check_episode, gains_from_omega
from ddarm.tuning.methods import DEFAULT_METHOD, DEFAULT_TUNE_BUDGET

# The excitation episodes run under the ω rule at this ω (as docs/robots.md's `ddarm identify` records them): gains
# that need no model of the robot beyond the URDF, so the bags do not depend on the search's outcome.
EXCITATION_OMEGA = 15.0
# The held-out episode starts disturbed (3.1) by this τ: another initial state than the fitted one's.
CHECK_TAU = 0.3


def add_transfer_parser(commands) -> None:
    parser = commands.add_parser('transfer', help='tune on the URDF, identify the robot from its bags, tune again '
                                                  'and say whether the prediction transfers to the robot')
    parser.add_argument('--controller', choices=CONTROLLERS, required=True,
                        help='the law: pd_gravity (PD + gravity, Fig. 1) or computed_torque (Fig. 2)')
    parser.add_argument('--urdf', required=True, metavar='FILE', help='the arm the nominal gains are tuned on')
    parser.add_argument('--motion', required=True, metavar='FILE.yaml', help='the motion the gains are tuned for')
    add_robot_arguments(parser)
    parser.add_argument('--index', type=index_name, default='I', metavar='{I1,I2,I}',
                        help='the index minimised and judged: I1 (2.5), I2, or I (3.2) (default I)')
    parser.add_argument('--budget', type=int, default=DEFAULT_TUNE_BUDGET,
                        help=f'most episodes of each of the two searches ({DEFAULT_TUNE_BUDGET})')
    parser.add_argument('--seed', type=seed, default=0, help='random seed of the searches and the excitation (0)')
    parser.add_argument('--excite-duration', type=finite, default=10.0, metavar='S',
                        help='T of the excitation motion, s (10)')
    parser.add_argument('--tolerance', type=finite, default=0.1,
                        help='largest |measured - predicted| / measured index of the retuned gains that transfers '
                             '(0.1)')
    parser.add_argument('--samples', type=whole_number(0, 100), default=0, metavar='K',
                        help='retune robustly (worst case) over K parameter sets drawn within the identification\'s '
                             'standard deviations, beside the point estimate (0: on the point estimate alone)')
    add_run_arguments(parser, 'transfer')
    parser.set_defaults(handler=command_transfer, starts_ros=True)


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.json:
        print(text, file=sys.stderr, flush=True)


def _excitation(template: EpisodeSpec, duration: float, seed: int, command: str, source: str):
    """The excitation motion of the motion's controlled joints on the URDF, its locked joints held where the motion
    holds them (ddarm motion --excite)."""
    from ddarm.cli.motion import DEFAULT_HARMONICS, DEFAULT_POINT_PERIOD
    from ddarm.motion.excitation import excitation_motion
    from ddarm.physics.arm import load_arm, urdf_joints

    joints, locked = arm_joints(template)
    arm = load_arm(template.urdf, None, joints, locked)
    described = urdf_joints(arm.urdf_path)
    held = {name: value for name, value in arm.locked if described[name].mimic is None}  # a mimic joint follows
    return excitation_motion(arm, duration, DEFAULT_HARMONICS, seed, None, DEFAULT_POINT_PERIOD, held, command,
                             source)


def _tuned(args: argparse.Namespace, template: EpisodeSpec, label: str, scenarios=None):
    """`ddarm tune`'s search (its default method and start ω) on `template`, with its progress bar; with
    `scenarios`, its robust search (worst case)."""
    from ddarm.reporting.progress import Progress
    from ddarm.tuning.tune import tune

    with Progress(args.budget, label, quiet=args.json, index_name=args.index) as bar:
        return tune(template, args.index, DEFAULT_METHOD, args.budget, SEARCH_START_OMEGAS, args.seed,
                    progress=bar.update, scenarios=scenarios)


def _tuned_gains(args: argparse.Namespace, run, template: EpisodeSpec, phase: str, command: str, scenarios=None):
    """The search on `template` (_tuned) and its gains written to the run folder as `<phase>.yaml`, as `ddarm tune
    --out` writes them: the YAML's path and the tuning."""
    from ddarm.tuning.outputs import search_doubt, write_gains

    tuning = _tuned(args, template, f'{phase} search', scenarios)
    kp, kv = tuning.search.kp, tuning.search.kv
    (path, *_) = write_gains(run, kp, kv, template.with_gains(kp, kv),
                             f'{args.index} = {tuning.best[args.index]!r} on {template.urdf}'
                             f'{search_doubt(tuning.search)}\nfrom: {command}', name=f'{phase}.yaml')
    return Path(path), tuning


def _validated(gains_path: Path, args: argparse.Namespace) -> tuple[dict, Episodes, Episodes]:
    """The controller YAML as `ddarm validate` runs it: the prediction on its URDF, the measurement on the robot
    (in-process). Returns the phase's record and both episodes."""
    from ddarm.recording.gains_file import read_gains_file, validation_spec
    from ddarm.tuning.transfer import side_record

    gains = read_gains_file(gains_path)
    predicted_spec = validation_spec(gains, tau=0.0, torque_limit='none')
    measured_spec = dataclasses.replace(predicted_spec, mjcf=absolute_path(args.mjcf),
                                        mjcf_joints=robot_joints(args, gains.joint_names))
    predicted, measured = run_episode(predicted_spec), run_episode(measured_spec)
    record = {'gains': str(gains_path),
              'predicted': {**side_record(predicted), 'saturated': saturated_joints(predicted)},
              'measured': {**side_record(measured), 'saturated': saturated_joints(measured)}}
    return record, predicted, measured


def _identified(urdf: str, fit: Path, check: Path, out: Path, command: str, samples: int) -> dict:
    """`ddarm identify FIT --validate CHECK --urdf URDF --out OUT --samples K`, its report."""
    from ddarm.cli.identify import identify_bags
    from ddarm.recording.bags import read_episode_bag

    return identify_bags(urdf, [read_episode_bag(fit)], [read_episode_bag(check)], out, command, samples=samples)


def command_transfer(args: argparse.Namespace) -> int:
    from ddarm.tuning.outputs import check_outputs, run_folder
    from ddarm.tuning.transfer import improvement, verdict, write_transfer_page

    if args.budget < 1:
        raise EpisodeError(f'--budget must be a positive number of episodes, got {args.budget}')
    if not (math.isfinite(args.tolerance) and args.tolerance >= 0):
        raise EpisodeError(f'--tolerance must be a number >= 0, got {args.tolerance!r}')
    if not (math.isfinite(args.excite_duration) and args.excite_duration > 0):
        raise EpisodeError(f'--excite-duration must be a positive number of seconds, got {args.excite_duration!r}')
    command = shlex.join(['ddarm', *args.argv])
    # Every refusal before the searches: the URDF and the motion, the robot against the motion's joints, the
    # excitation (a few seconds, and the one step that needs the URDF's limits), the run folder.
    template = EpisodeSpec(controller=args.controller, urdf=absolute_path(args.urdf), motion=absolute_path(args.motion))
    joints = arm_joints(template)[0]
    robot = dict(mjcf=absolute_path(args.mjcf), mjcf_joints=robot_joints(args, joints))
    if robot['mjcf'] is None:
        raise EpisodeError('--mjcf FILE is required: the robot (an MJCF, or a URDF MuJoCo compiles) the gains are '
                           'validated on and identified from')
    check_episode(template)
    check_episode(dataclasses.replace(template, **robot))
    check_outputs(None, args.runs, args.run)
    _say(args, f'excitation motion ({args.excite_duration:g} s) of {", ".join(joints)} …')
    excitation = _excitation(template, args.excite_duration, args.seed, command, 'excite.yaml')
    law = args.controller
    with run_folder('transfer', law, args.runs, args.run, command) as run:
        excite = run.write_text('excite.yaml', excitation.text)
        # 1. the nominal tuning on the URDF
        _say(args, f'1/7 tuning {law} on {args.urdf} ({args.budget} episodes, index {args.index}) …')
        nominal_gains, nominal_tuning = _tuned_gains(args, run, template, 'nominal', command)
        # 2. the nominal gains on the robot
        _say(args, '2/7 validating the nominal gains on the robot …')
        nominal, *nominal_episodes = _validated(nominal_gains, args)
        nominal.update(nominal_tuning.search.certainty_fields())
        # 3, 4. the excitation recorded on the robot through the graph, twice
        excite_spec = dataclasses.replace(template, motion=str(excite.absolute()), duration=None, **robot)
        kp, kv = gains_from_omega(excite_spec, EXCITATION_OMEGA)
        excite_spec = excite_spec.with_gains(kp, kv)
        from ddarm.ros.session import run_graph_episode  # ROS only once the searches it does not need are done

        bags = {}
        for name, tau in (('fit', 0.0), ('check', CHECK_TAU)):
            _say(args, f'3-4/7 recording the excitation on the robot through ROS (τ = {tau:g} s): bags/{name} …')
            bags[name] = run.bag_path(name)
            run_graph_episode(dataclasses.replace(excite_spec, tau=tau), bag=bags[name], command=command)
        # 5. identification from the fitted bag, residuals on the held-out one
        _say(args, '5/7 identifying the robot from bags/fit (bags/check held out) …')
        identified = run.path / 'identified.urdf'
        identification = _identified(template.urdf, bags['fit'], bags['check'], identified, command, args.samples)
        # 6. the same search on the identified URDF (robust over its samples, if asked)
        retuned_template = dataclasses.replace(template, urdf=str(identified))
        scenarios = None
        if args.samples:
            from ddarm.tuning.robust import scenario_grid

            scenarios = scenario_grid(retuned_template, urdfs=[str(identified), *identification['samples_written']])
        _say(args, f'6/7 tuning {law} on identified.urdf{f" and {args.samples} samples" if args.samples else ""} …')
        retuned_gains, retuned_tuning = _tuned_gains(args, run, retuned_template, 'retuned', command, scenarios)
        # 7. the retuned gains on the robot
        _say(args, '7/7 validating the retuned gains on the robot …')
        retuned, *retuned_episodes = _validated(retuned_gains, args)
        retuned.update(retuned_tuning.search.certainty_fields())
        transfers, reason = verdict(retuned, args.index, args.tolerance)
        report = {
            'nominal': nominal,
            'identification': {
                'urdf': str(identified), 'condition_number': identification['condition_number'],
                'joints': identification['joints'], 'validation_residual': identification['validation_residual'][0],
                'fit_residual': identification['fit_residual'],
                'excitation': {'motion': str(excite), 'condition_number': excitation.condition,
                               'gains': f'{law}, ω rule at ω = {EXCITATION_OMEGA:g} on the URDF',
                               'check_tau': CHECK_TAU}},
            'retuned': {**retuned, 'predicted_worst': None if retuned_tuning.robust is None
                        else retuned_tuning.robust.chosen.worst,
                        'samples': identification['samples_written']},
            'transfers': transfers, 'verdict': reason, 'index': args.index, 'tolerance': args.tolerance,
            'improvement_I1': improvement(nominal, retuned),
            'bags': [str(bags['fit']), str(bags['check'])], 'run': str(run.path),
        }
        title = f'{law} gains of {Path(args.urdf).name} on {Path(args.mjcf).name}: tune, identify, re-tune'
        figures = {}
        for phase, (predicted, measured) in (('nominal', nominal_episodes), ('retuned', retuned_episodes)):
            figures[phase] = f'errors-{phase}.png'
            error_figure(run.path / figures[phase], predicted, measured, f'{phase} gains: {title}')
        write_transfer_page(run, report, args.index, figures, title)
        run.finish('complete', **report)
    if args.json:
        print_json(report)
    else:
        print_transfer(report)
    return 0


def print_transfer(report: dict) -> None:
    from ddarm.tuning.transfer import improvement_sentence, index_rows

    header = ['gains', 'index', 'predicted', 'measured', 'measured/predicted']
    rows = index_rows(report)
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        print('  ' + '  '.join(cell.ljust(width) if i < 2 else cell.rjust(width)
                               for i, (cell, width) in enumerate(zip(row, widths))))
    identification = report['identification']
    residuals = [value for key, value in identification['validation_residual'].items() if key != 'bag']
    print(f"  identified {identification['urdf']}: condition number {identification['condition_number']:.4g}, "
          f"held-out torque residual {min(residuals):.3%} to {max(residuals):.3%}")
    retuned = report['retuned']
    if retuned['samples']:
        worst = retuned['predicted_worst']
        print(f"  retuned robustly over the estimate and {len(retuned['samples'])} samples: predicted worst "
              f"{report['index']} {'- (diverged in a sample)' if worst is None else f'{worst:.6g}'}, measured "
              f"{retuned['measured'][report['index']]:.6g}")
    for phase in ('nominal', 'retuned'):
        if not report[phase]['converged']:
            print(f"  WARNING: the {phase} search: {report[phase]['certainty']}")
    print(f"  {report['verdict']}")
    print(f"  {improvement_sentence(report['improvement_I1'])}")
    print(f"  run folder {report['run']}")

