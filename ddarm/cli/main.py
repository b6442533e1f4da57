"""The `ddarm` command: run episodes and print their indices."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import time

import numpy as np

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.control.laws import CONTROLLERS
from ddarm.errors import DdarmError
from ddarm.physics.plant import DEFAULT_SUBSTEPS
from ddarm.motion.programmed import TRAJECTORY_ENDPOINTS, paper_trajectory
from ddarm.episodes.bench import add_bench_parser
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, gains_from_omega, run_episode
from ddarm.interrupts import Interrupted, critical_section, stop_on_signals


def _finite(text: str) -> float:
    value = float(text)
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f'{text!r} is not a finite number')
    return value


def add_episode_arguments(parser: argparse.ArgumentParser, gains: bool = True) -> None:
    """The options that define an episode (MODEL.md's defaults); `gains` adds --omega / --kp --kv."""
    parser.add_argument('--controller', choices=CONTROLLERS, required=True)
    parser.add_argument('--trajectory', type=int, choices=sorted(TRAJECTORY_ENDPOINTS), default=1)
    parser.add_argument('--duration', type=_finite, default=1.0, metavar='T', help='T in s (default 1)')
    parser.add_argument('--period', type=_finite, default=0.01, metavar='DT',
                        help='sampling period Δ in s (default 0.01)')
    if gains:
        choice = parser.add_mutually_exclusive_group(required=True)
        choice.add_argument('--omega', type=_finite, metavar='W',
                            help='gains from the ω rule of section 2 (PD + gravity: m_ii at q_f)')
        choice.add_argument('--kp', type=_finite, nargs='+', metavar='K', help='K_p diagonal, one per joint')
        parser.add_argument('--kv', type=_finite, nargs='+', metavar='V', help='K_v diagonal, with --kp')
    parser.add_argument('--delay', type=int, default=1, metavar='D',
                        help='compute delay in samples (default 1; the paper uses 0 for PD + gravity)')
    parser.add_argument('--tau', type=_finite, default=0.0,
                        help='initial velocity disturbance (3.1): q̇(0) = -q̇^d(τ) (default 0)')
    limits = parser.add_mutually_exclusive_group()
    limits.add_argument('--limited', action='store_true',
                        help="the paper's torque limits: 2 x max nominal torque per joint")
    limits.add_argument('--torque-limit', type=_finite, nargs='+', metavar='N',
                        help='torque limits in N m, one per joint')
    parser.add_argument('--external-torque', type=_finite, nargs='+', metavar='PZ',
                        help='constant external joint torques P^z in N m')
    parser.add_argument('--viscous-friction', type=_finite, nargs='+', metavar='B')
    parser.add_argument('--coulomb-friction', type=_finite, nargs='+', metavar='C')
    parser.add_argument('--mass-scale', type=_finite, nargs='+', metavar='S',
                        help="plant link mass / model link mass, per link (default 1: model = plant)")
    parser.add_argument('--substeps', type=int, default=DEFAULT_SUBSTEPS,
                        help=f'RK4 steps per sampling period (default {DEFAULT_SUBSTEPS})')


def episode_spec(args: argparse.Namespace) -> EpisodeSpec:
    if not hasattr(args, 'omega'):  # commands that choose the gains themselves start from a placeholder
        kp = kv = (1.0,) * len(paper_trajectory(args.trajectory, args.duration).q0)
    elif args.omega is not None:
        if args.kv is not None:
            raise EpisodeError('--kv goes with --kp; --omega sets both gains from the ω rule')
        final = paper_trajectory(args.trajectory, args.duration).qf
        kp, kv = gains_from_omega(args.controller, args.omega, final_position=final)
    else:
        if args.kv is None:
            raise EpisodeError('--kp needs --kv')
        kp, kv = args.kp, args.kv
    return EpisodeSpec(
        controller=args.controller, kp=kp, kv=kv, trajectory=args.trajectory, duration=args.duration,
        period=args.period, delay=args.delay, tau=args.tau,
        torque_limit='paper' if args.limited else (args.torque_limit or 'none'),
        external_torque=args.external_torque, viscous_friction=args.viscous_friction,
        coulomb_friction=args.coulomb_friction, mass_scale=args.mass_scale, substeps=args.substeps)


def _format_vector(values) -> str:
    return '(' + ', '.join(f'{value:.6g}' for value in values) + ')'


def print_summary(summary: dict) -> None:
    spec = summary['spec']
    print(f"{spec['controller']}  trajectory {spec['trajectory']}  T = {spec['duration']} s  "
          f"Δ = {spec['period']} s  delay {spec['delay']}  τ = {spec['tau']} s  "
          f"torque limit {spec['torque_limit']}")
    print(f"  kp = {_format_vector(spec['kp'])}  kv = {_format_vector(spec['kv'])}")
    print(f"  I1 (2.5) = {summary['I1']:.6g}   I2 = {summary['I2']:.6g}   I (3.2) = {summary['I']:.6g}")
    if summary['diverged']:
        print(f"  DIVERGED at sample {summary['diverged_at_sample']}: indices cover the "
              f"{summary['samples_scored']} samples before it")
    if summary['max_abs_error_deg'] is not None:
        print(f"  max |e| (deg) = {_format_vector(summary['max_abs_error_deg'])}   "
              f"max |P| (N m) = {_format_vector(summary['max_abs_torque'])}")
    for warning in summary.get('warnings', []):
        print(f'  WARNING: {warning}')


def command_episode(args: argparse.Namespace) -> int:
    from ddarm.episodes.spec import check_episode

    if args.bag and not (args.ros or args.realtime):
        raise EpisodeError('--bag records an episode run through ROS: add --ros (or --realtime)')
    spec = episode_spec(args)
    check_episode(spec)
    started = time.perf_counter()
    warnings = []
    if args.ros or args.realtime:
        from ddarm.ros.driver import realtime_warnings, run_graph_episode  # ROS only when asked for

        result = run_graph_episode(spec, realtime=args.realtime, bag=args.bag, storage=args.storage,
                                   command=shlex.join(['ddarm', *args.argv]))
        transport = 'ros-realtime' if args.realtime else 'ros-lockstep'
        if args.realtime:
            warnings = realtime_warnings(result.plant_report)
    else:
        result = run_episode(spec)
        transport = 'in-process'
    summary = {**result.summary(), 'transport': transport, 'wall_time_s': time.perf_counter() - started,
               'command': shlex.join(['ddarm', *args.argv]), 'warnings': warnings}
    if args.json:
        print(json.dumps(summary))
    else:
        print_summary(summary)
    return 0


def command_score(args: argparse.Namespace) -> int:
    from ddarm.recording.bags import BagError, score_bag

    failures = 0
    for bag in args.bags:
        try:
            summary = score_bag(bag)
        except BagError as error:
            failures += 1
            print(f'ddarm score: {error}', file=sys.stderr)
            continue
        if args.json:
            print(json.dumps(summary))
        else:
            print(bag)
            print_summary(summary)
    return 2 if failures else 0


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse an --out or run folder that cannot be written as asked, before any search or episode."""
    from pathlib import Path

    from ddarm.recording.bags import BagError, checked_output_path
    from ddarm.recording.runs import RunFolder

    if args.out:
        out = checked_output_path(args.out)
        if not out.parent.is_dir():
            raise BagError(f'--out {out}: the folder {out.parent} does not exist')
    if args.run:
        RunFolder.checked_path(args.run, Path(args.runs))
    else:
        RunFolder.checked_root(Path(args.runs))


def _run_folder(args: argparse.Namespace, kind: str):
    from ddarm.recording.runs import RunFolder

    name = args.run or time.strftime(f'{kind}-{args.controller}-%Y%m%d-%H%M%S')
    return RunFolder(name, args.runs, command=shlex.join(['ddarm', *args.argv]))


def _write_gains(run, args, kp, kv, spec: EpisodeSpec, provenance: str) -> list[str]:
    """The controller YAML in the run folder, and at --out if given (never overwriting)."""
    from ddarm.recording.bags import checked_output_path
    from ddarm.recording.runs import controller_yaml

    text = controller_yaml(spec.controller, kp, kv, spec.delay, spec.period, provenance)
    written = [str(run.write_text(f'{spec.controller}.yaml', text))]
    if args.out:
        checked_output_path(args.out).write_text(text)
        written.append(args.out)
    return written


def command_omega(args: argparse.Namespace) -> int:
    from ddarm.episodes.spec import check_episode
    from ddarm.tuning.procedures import omega_procedure

    if args.mass_error is not None and args.mass_scale is not None:
        raise EpisodeError('give --mass-error or --mass-scale, not both')
    if args.disturbance is not None and args.external_torque is not None:
        raise EpisodeError('give --disturbance or --external-torque, not both')
    _check_outputs(args)
    spec = episode_spec(args)
    dof = len(spec.kp)
    for name, values in (('--max-error', args.max_error), ('--disturbance', args.disturbance),
                         ('--mass-error', args.mass_error)):
        if values is not None and len(values) != dof and not (name == '--max-error' and len(values) == 1):
            raise EpisodeError(f'{name} needs {"one value or " if name == "--max-error" else ""}{dof} values '
                               f'(one per joint), got {len(values)}')
    if args.mass_error is not None:
        spec = dataclasses.replace(spec, mass_scale=tuple(1.0 + e for e in args.mass_error))
    if args.disturbance is not None:
        spec = dataclasses.replace(spec, external_torque=tuple(args.disturbance))
    check_episode(spec)
    choice = omega_procedure(spec, np.radians(args.max_error), args.torque_factor, args.omega_step,
                             args.omega_max)
    with _run_folder(args, 'omega') as run:
        return _report_omega(args, spec, choice, run)


def _report_omega(args: argparse.Namespace, spec: EpisodeSpec, choice, run) -> int:
    steps = [dataclasses.asdict(step) for step in choice.steps]
    report = {'omega_min': choice.omega_min,
              'steady_state_error_at_omega_min_deg': np.degrees(choice.steady_state_error_at_min).tolist(),
              'omega': choice.omega, 'kp': None if choice.kp is None else choice.kp.tolist(),
              'kv': None if choice.kv is None else choice.kv.tolist(),
              'indices': choice.steps[-2 if not choice.steps[-1].accepted else -1].indices
              if choice.omega is not None else None,
              'steps': steps, 'spec': spec.to_dict(), 'command': run.summary['command']}
    if choice.omega is not None:
        report['gains_files'] = _write_gains(run, args, choice.kp, choice.kv, spec,
                                             f"ω = {choice.omega} from: {report['command']}")
    run.summary['omega'] = report
    run.finish('complete' if choice.omega is not None else 'no omega meets the torque conditions')
    report['run'] = str(run.path)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"{spec.controller}: ω_min = {choice.omega_min:.6g} (steady-state errors at ω_min, deg: "
          f"{_format_vector(report['steady_state_error_at_omega_min_deg'])})")
    for step in choice.steps:
        print(f'  ω = {step.omega:8.4g}  max |P| / limit = {step.max_torque_ratio_to_limit:.3f}  '
              f'max |P| / max |P_nom| = {step.max_torque_ratio_to_nominal:.3f}  '
              f"{'diverged ' if step.diverged else ''}{'accepted' if step.accepted else 'rejected'}")
    if choice.omega is None:
        print('  no ω from ω_min up meets the torque conditions')
    else:
        indices = report['indices']
        print(f"  chosen ω = {choice.omega:.6g}: kp = {_format_vector(choice.kp)}  kv = {_format_vector(choice.kv)}")
        print(f"  I1 (2.5) = {indices['I1']:.6g}   I2 = {indices['I2']:.6g}   I (3.2) = {indices['I']:.6g}")
        print(f"  gains written to {', '.join(report['gains_files'])}")
    return 0


def command_tune(args: argparse.Namespace) -> int:
    from ddarm.tuning.tune import INDEX_KEYS, tune

    _check_outputs(args)
    template = episode_spec(args)
    key = INDEX_KEYS[args.index]
    progress = None if args.json else sys.stderr
    if progress:
        print(f'searching ({args.method}, budget {args.budget} episodes, starts ω = {args.omegas}) …',
              file=progress, flush=True)
    tuning = tune(template, args.index, args.method, args.budget, args.omegas, args.seed)
    with _run_folder(args, 'tune') as run:  # only now: a refused search leaves nothing behind
        return _check_tuning(args, template, tuning, run, progress)


def _check_tuning(args: argparse.Namespace, template: EpisodeSpec, tuning, run, progress) -> int:
    """The tuned gains run once through the ROS graph, recorded and scored from the bag; the YAML only if they agree."""
    from ddarm.ros.driver import GraphSession, record_and_score
    from ddarm.tuning.tune import INDEX_KEYS, with_gains

    key = INDEX_KEYS[args.index]
    best_spec = with_gains(template, tuning.search.kp, tuning.search.kv)
    if progress:
        print(f'best {key} = {tuning.search.index:.6g} after {tuning.search.episodes} episodes; '
              f'checking it through the ROS graph …', file=progress, flush=True)
    with GraphSession(run.path / 'nodes') as session:
        graph, scored = record_and_score(session, best_spec, run.bag_path('best'), args.storage,
                                         run.summary['command'])
    in_process = tuning.best
    difference = max(abs(scored[k] - in_process[k]) / max(abs(in_process[k]), 1e-300) for k in ('I1', 'I2', 'I'))
    report = {
        'controller': template.controller, 'index': args.index, 'method': args.method, 'seed': args.seed,
        'kp': tuning.search.kp.tolist(), 'kv': tuning.search.kv.tolist(),
        'search_index': tuning.search.index, 'in_process': in_process,
        'from_bag': {k: scored[k] for k in ('I1', 'I2', 'I')}, 'max_rel_difference': difference,
        'agree': difference <= 1e-9, 'bag': scored['bag'],
        'start_omegas': list(tuning.start_omegas), 'start_indices': tuning.start_indices,
        'episodes': tuning.search.episodes, 'batches': tuning.search.batches,
        'wall_time_s': tuning.wall_time_s, 'episodes_per_s': tuning.episodes_per_s,
        'spec': best_spec.to_dict(), 'command': run.summary['command'],
    }
    if report['agree']:  # gains whose evidence disagrees with the search are not handed to a robot
        report['gains_files'] = _write_gains(
            run, args, tuning.search.kp, tuning.search.kv, best_spec,
            f"{key} = {scored[key]!r} (scored from {scored['bag']})\nfrom: {report['command']}")
    else:
        report['gains_files'] = []
    run.summary['tune'] = report
    run.finish('complete' if report['agree'] else 'in-process and bag indices disagree')
    report['run'] = str(run.path)
    if args.json:
        print(json.dumps(report))
    else:
        print(f"{template.controller}, index ({args.index}), {args.method}: {tuning.search.episodes} episodes in "
              f"{tuning.wall_time_s:.2f} s ({tuning.episodes_per_s:.0f} episodes/s)")
        print(f"  starts (ω rules {_format_vector(tuning.start_omegas)}): {key} = "
              f"{_format_vector(tuning.start_indices)}")
        print(f"  kp = {_format_vector(tuning.search.kp)}  kv = {_format_vector(tuning.search.kv)}")
        for label, values in (('in-process', in_process), ('from bag  ', report['from_bag'])):
            print(f"  {label}: I1 = {values['I1']:.9g}  I2 = {values['I2']:.9g}  I = {values['I']:.9g}")
        print(f"  largest relative difference {difference:.2e} ({'agree' if report['agree'] else 'DISAGREE'}); "
              f"bag {scored['bag']}")
        if report['gains_files']:
            print(f"  gains written to {', '.join(report['gains_files'])}")
        else:
            print('  no gains written: the bag does not confirm the search')
    return 0 if report['agree'] else 2


def command_reproduce(args: argparse.Namespace) -> int:
    from ddarm.recording.bags import checked_output_path
    from ddarm.paper.experiments import Budget, Reproduction
    from ddarm.paper.report import write_report
    from ddarm.ros.driver import GraphSession
    from ddarm.recording.runs import RunFolder

    out = checked_output_path(args.out)
    started = time.perf_counter()
    command = shlex.join(['ddarm', *args.argv])

    def progress(message: str) -> None:
        print(f'[{time.perf_counter() - started:6.1f} s] {message}', file=sys.stderr, flush=True)

    # The folder's summary.json says `running` until the report is written: an interrupted or
    # killed reproduction is never taken for a finished one.
    with RunFolder(out.name, out.parent, command=command) as run:
        reproduction = Reproduction(out, Budget.quick() if args.quick else Budget.full(), command, progress)
        gains = reproduction.search_all()
        progress('running every reported episode through the ROS graph (lockstep), recording each')
        with GraphSession(out / 'nodes') as session:
            reproduction.run_episodes(session, gains)
        reproduction.judge_claims()
        results = reproduction.results
        results['wall_time_s'] = time.perf_counter() - started
        # Every episode is done: a stop now waits for the report (plotting code turns a stop into errors of its own).
        with critical_section():
            (out / 'results.json').write_text(json.dumps(results, indent=2))
            written = write_report(out, results)
            run.finish('complete', report=str(out / 'REPORT.md'))
    progress(f'done: {out / "REPORT.md"} ({len(written)} files), results in {out / "results.json"}')
    for claim in results['claims']:
        print(f"{'REPRODUCED    ' if claim['reproduced'] else 'NOT REPRODUCED'}  {claim['claim']}: "
              f"{claim['evidence']}")
    return 0


def command_plant(args: argparse.Namespace) -> int:
    from ddarm_sim.node import main as plant_main

    return plant_main(['ddarm-plant', *args.ros_arguments])


def command_controller(args: argparse.Namespace) -> int:
    from ddarm_control.node import main as controller_main

    return controller_main(['ddarm-controller', *args.ros_arguments], args.law)


def command_tuner(args: argparse.Namespace) -> int:
    from ddarm_tuner.node import main as tuner_main

    return tuner_main(['ddarm-tuner', *args.ros_arguments])


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--runs', default='runs', help='folder of run folders (runs)')
    parser.add_argument('--run', metavar='NAME', help='run folder name (default: <command>-<law>-<time>)')
    parser.add_argument('--out', metavar='FILE.yaml', help='also write the controller YAML here (new file)')
    parser.add_argument('--json', action='store_true', help='print one JSON object')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='ddarm', description='Feedback-gain selection for the direct-drive arm (Kowalska).')
    commands = parser.add_subparsers(dest='command', required=True)
    episode = commands.add_parser('episode', help='run one closed-loop episode and print its indices')
    add_episode_arguments(episode)
    episode.add_argument('--json', action='store_true', help='print one JSON object')
    episode.add_argument('--ros', action='store_true',
                         help='run through the ROS 2 graph: plant and controller processes, lockstep over DDS')
    episode.add_argument('--realtime', action='store_true',
                         help='run through the ROS 2 graph on the wall clock (implies --ros)')
    episode.add_argument('--bag', metavar='DIR', help='record the ROS episode as a rosbag2 bag in DIR (new)')
    episode.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap', help='bag storage (mcap)')
    episode.set_defaults(handler=command_episode)
    omega = commands.add_parser('omega', help="section 2's procedure: the ω rule's ω from permitted errors "
                                             'and torques')
    add_episode_arguments(omega, gains=False)
    omega.add_argument('--max-error', type=_finite, nargs='+', required=True, metavar='DEG',
                       help='permitted steady-state error in degrees (one, or one per joint)')
    omega.add_argument('--disturbance', type=_finite, nargs='+', metavar='PZ',
                       help='constant external joint torques P^z in N m (same as --external-torque)')
    omega.add_argument('--mass-error', type=_finite, nargs='+', metavar='E',
                       help='relative link mass error of the plant: plant mass = model mass x (1 + E)')
    omega.add_argument('--torque-factor', type=_finite, default=1.5, metavar='F',
                       help='largest torque allowed, as a multiple of the largest nominal torque (1.5)')
    omega.add_argument('--omega-step', type=_finite, default=0.5, help='ω increment when raising (0.5)')
    omega.add_argument('--omega-max', type=_finite, default=100.0, help='largest ω tried (100)')
    add_output_arguments(omega)
    omega.set_defaults(handler=command_omega)
    tune = commands.add_parser('tune', help='optimise the gains for index (2.5) or (3.2), then check them '
                                           'through the ROS graph')
    add_episode_arguments(tune, gains=False)
    tune.add_argument('--index', choices=('2.5', '3.2'), required=True)
    tune.add_argument('--method', choices=('nelder-mead', 'cma'), default='nelder-mead',
                      help='multi-start Nelder-Mead (the paper-style default) or CMA-ES')
    tune.add_argument('--budget', type=int, default=3000, help='most episodes evaluated (3000)')
    tune.add_argument('--omegas', type=_finite, nargs='+', default=list(SEARCH_START_OMEGAS),
                      metavar='W', help='ω of the ω-rule start gains (8 12 15 20 30)')
    tune.add_argument('--seed', type=int, default=0, help="CMA-ES's random seed (0)")
    tune.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    add_output_arguments(tune)
    tune.set_defaults(handler=command_tune)
    reproduce = commands.add_parser('reproduce', help="reproduce the paper's Tables 2-4 and section 2 through "
                                                     'the ROS graph, with a report')
    reproduce.add_argument('--out', default='runs/paper', help='output folder, new (runs/paper)')
    reproduce.add_argument('--quick', action='store_true',
                           help='small search budgets and three τ values: a first look in well under a minute')
    reproduce.set_defaults(handler=command_reproduce)
    score = commands.add_parser('score', help='score recorded episodes from their bags alone')
    score.add_argument('bags', nargs='+', metavar='BAG', help='rosbag2 folders written by ddarm')
    score.add_argument('--json', action='store_true', help='one JSON object per bag, one per line')
    score.set_defaults(handler=command_score)
    plant = commands.add_parser('plant', help='start the plant node (then --ros-args ...)')
    plant.set_defaults(handler=command_plant, takes_ros_arguments=True)
    controller = commands.add_parser('controller', help='start a controller node (then --ros-args ...)')
    controller.add_argument('law', choices=CONTROLLERS)
    controller.set_defaults(handler=command_controller, takes_ros_arguments=True)
    tuner = commands.add_parser('tuner', help='start the tuner node: a recorded sweep on running nodes '
                                             '(then --ros-args ...)')
    tuner.set_defaults(handler=command_tuner, takes_ros_arguments=True)
    add_bench_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args, ros_arguments = parser.parse_known_args(argv)
    if ros_arguments and not getattr(args, 'takes_ros_arguments', False):
        parser.error(f'unrecognized arguments: {" ".join(ros_arguments)}')
    args.ros_arguments, args.argv = ros_arguments, argv
    if getattr(args, 'takes_ros_arguments', False):
        return args.handler(args)  # a node: it handles SIGINT and SIGTERM as ROS nodes do
    try:
        with stop_on_signals():
            return args.handler(args)
    except Interrupted as stop:
        print(f'ddarm {args.command}: {stop}; stopped cleanly (bags under way marked incomplete)',
              file=sys.stderr, flush=True)
        return stop.exit_code
    except DdarmError as error:  # refused input or an untrustworthy run; anything else is a bug: its traceback shows
        print(f'ddarm {args.command}: {error}', file=sys.stderr)
        return 2
    except OSError as error:  # a path the user gave that the system refuses (permissions, a full disk)
        print(f'ddarm {args.command}: {error.filename or ""}: {error.strerror or error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
