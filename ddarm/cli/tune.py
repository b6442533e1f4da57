"""`ddarm tune`: gains optimised in-process for an index, then checked once through the ROS graph."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys

from ddarm.cli.arguments import absolute_path, episode_spec, finite
from ddarm.cli.output import format_vector, print_json
from ddarm.episodes.indices import INDICES, PAPER_EQUATIONS
from ddarm.episodes.spec import check_episode, gains_from_omega, loop_stability_warnings
from ddarm.reporting.progress import Progress
from ddarm.tuning.robust import AGGREGATES


def index_name(text: str) -> str:
    """An index by its name, or by the paper's equation number (2.5 is I1, 3.2 is I)."""
    name = PAPER_EQUATIONS.get(text, text)
    if name not in INDICES:
        raise argparse.ArgumentTypeError(f'{text!r} is not an index: one of {", ".join(INDICES)} (or 2.5, 3.2)')
    return name


def comma_numbers(text: str) -> tuple[float, ...]:
    """A number, or numbers separated by commas (one per joint): `0,20,5`."""
    try:
        return tuple(finite(part) for part in text.split(','))
    except (argparse.ArgumentTypeError, ValueError):
        raise argparse.ArgumentTypeError(f'{text!r} is not a finite number or finite numbers separated by '
                                         'commas') from None


def add_robust_arguments(parser: argparse.ArgumentParser) -> None:
    """The scenario grid of a robust tuning: every combination of the values given is one scenario."""
    parser.add_argument('--robust-tau', type=finite, nargs='+', action='extend', metavar='T',
                        help='τ of the disturbance (3.1) in s, one per scenario (default: --tau)')
    parser.add_argument('--robust-mass-scale', type=comma_numbers, nargs='+', action='extend', metavar='S',
                        help='plant link mass / model link mass, one per scenario: a number (every link) or one '
                             'per joint, comma-separated (1.0,1.1,1.1) (default: --mass-scale)')
    parser.add_argument('--robust-external-torque', type=comma_numbers, nargs='+', action='extend', metavar='PZ',
                        help='constant external torques P^z in N m, one per joint comma-separated (0,20,5), one '
                             'vector per scenario; one starting with a minus as --robust-external-torque=-5,0,0 '
                             '(default: --external-torque)')
    parser.add_argument('--robust-urdf', nargs='+', action='extend', metavar='FILE',
                        help="the plant's URDF, one per scenario (the controller's model stays --model-urdf or "
                             '--urdf): e.g. the samples of an identification, ddarm identify --samples')
    parser.add_argument('--objective', choices=AGGREGATES,
                        help='what the gains minimise over the scenarios: the worst case (default) or the mean')


def robust_scenarios(args: argparse.Namespace, template):
    """The scenarios the --robust-* options define, or None without them."""
    from ddarm.tuning.robust import RobustError, scenario_grid

    urdfs = None if args.robust_urdf is None else [absolute_path(path) for path in args.robust_urdf]
    axes = (args.robust_tau, args.robust_mass_scale, args.robust_external_torque, urdfs)
    if all(axis is None for axis in axes):
        if args.objective is not None:
            raise RobustError('--objective needs scenarios to aggregate over: give --robust-tau, '
                              '--robust-mass-scale, --robust-external-torque and/or --robust-urdf')
        return None
    return scenario_grid(template, *axes)


def command_tune(args: argparse.Namespace) -> int:
    from ddarm.tuning.outputs import check_outputs, finish_tuning, run_folder
    from ddarm.tuning.tune import check_tune, tune

    check_outputs(args.out, args.runs, args.run)
    template = episode_spec(args)
    for warning in check_episode(template).warnings:  # refusals first: nothing is searched before they are fixed
        print(f'ddarm tune: WARNING: {warning}', file=sys.stderr)
    for omega in args.omegas:
        kp, kv = gains_from_omega(template, omega)
        start = dataclasses.replace(template, kp=tuple(kp), kv=tuple(kv))
        for warning in loop_stability_warnings(start, f'the ω-rule start gains at ω = {omega:g}'):
            print(f'ddarm tune: WARNING: {warning}', file=sys.stderr)
    scenarios = robust_scenarios(args, template)
    objective = args.objective or 'worst'
    check_tune(template, args.index, args.method, args.budget, args.omegas, scenarios, objective)  # before the nodes
    progress = None if args.json else sys.stderr
    if progress:
        budget = (f'budget {args.budget} episodes' if scenarios is None else
                  f'{args.budget} episodes on the nominal episode, then {args.budget} over {len(scenarios)} '
                  f'scenarios ({objective} {args.index})')
        print(f'searching ({args.method}, {budget}, starts ω = {args.omegas}) …', file=progress, flush=True)
    label = 'search' if scenarios is None else f'robust search ({len(scenarios)} scenarios)'
    with graph_with_nodes(template) as session:
        with Progress(args.budget, label, quiet=args.json, index_name=args.index) as bar:
            tuning = tune(template, args.index, args.method, args.budget, args.omegas, args.seed,
                          progress=bar.update, scenarios=scenarios, aggregate=objective, measure_batch_rate=True)
        best_gains = dataclasses.replace(template, kp=tuple(tuning.search.kp), kv=tuple(tuning.search.kv))
        tuning = dataclasses.replace(tuning, warnings=tuple(tuning.warnings) + tuple(loop_stability_warnings(
            best_gains, 'the tuned gains')))
        with run_folder('tune', args.controller, args.runs, args.run, shlex.join(['ddarm', *args.argv])) as run:
            session.keep_files_in(run.path / 'nodes')
            best_spec = template.with_gains(tuning.search.kp, tuning.search.kv)
            if progress:
                best = args.index if scenarios is None else f'{objective} {args.index} over the scenarios'
                print(f'best {best} = {tuning.search.index:.6g} after {tuning.search.episodes} episodes; '
                      f'checking {"it" if scenarios is None else "its nominal episode"} through the ROS graph …',
                      file=progress, flush=True)
            scored = check_through_graph(session, run, best_spec, args.storage)
            report = finish_tuning(run, template, best_spec, tuning, scored, index=args.index, method=args.method,
                                   seed=args.seed, out=args.out)
            session.close()
    if args.json:
        print_json(report)
    else:
        print_tuning(report, tuning)
    return 0 if report['agree'] else 2


def graph_with_nodes(template):
    """A graph session with `template`'s nodes starting, so that they come up while the search runs; in a folder of
    its own, kept in the run folder once there is one (a refused search leaves nothing behind)."""
    from ddarm.ros.session import GraphSession

    session = GraphSession()
    try:
        session.prepare(template)
    except BaseException:
        session.close()
        raise
    return session


def check_through_graph(session, run, spec, storage: str) -> dict:
    """`spec` run once through the session's graph, recorded in the run folder, scored from the bag; then the
    session's nodes told to stop (closing the session waits for them, and keeps their files in the run folder)."""
    _, scored = session.record_and_score(spec, run.bag_path('best'), command=run.summary['command'], storage=storage)
    session.stop_nodes()
    return scored


def print_tuning(report: dict, tuning) -> None:
    from ddarm.tuning.report import local_runs_text

    print(f"{report['controller']}, index ({report['index']}), {report['method']}: {tuning.search.episodes} "
          f"episodes in {tuning.wall_time_s:.2f} s ({tuning.episodes_per_s:.0f} episodes/s; the engine's batch rate "
          f"on this episode: {tuning.batch_episodes_per_s:.0f})")
    print(f"  starts (ω rules {format_vector(tuning.start_omegas)}): {report['index']} = "
          f"{format_vector(tuning.start_indices)}")
    if report['restarts']:
        print(f'  {local_runs_text(report)}')
    print(f"  {'' if report['converged'] else 'WARNING: '}{report['certainty']}")
    width = max(len(name) for name in report['joint_names'])
    for name, gains in report['gains'].items():
        print(f"  {name:<{width}}  kp = {gains['p']:.6g}  kv = {gains['d']:.6g}")
    for label, values in (('in-process', report['in_process']), ('from bag  ', report['from_bag'])):
        print(f"  {label}: I1 = {values['I1']:.9g}  I2 = {values['I2']:.9g}  I = {values['I']:.9g}")
    print(f"  largest relative difference {report['max_rel_difference']:.2e} "
          f"({'agree' if report['agree'] else 'DISAGREE'}); bag {report['bag']}")
    if 'robust' in report:
        print_robustness(report['robust'], report['index'])
    for warning in report['warnings']:
        print(f'  WARNING: {warning}')
    if report['saturated_joints']:
        print(f"  at their torque limit in the recorded episode: {', '.join(report['saturated_joints'])}")
    print(f"  report {report['report']}")
    if report['gains_files']:
        print(f"  gains written to {', '.join(report['gains_files'])}")
    else:
        print('  no gains written: the bag does not confirm the search')


def _cell(value: float | None) -> str:
    return 'diverged' if value is None else f'{value:.6g}'


def print_robustness(robust: dict, index: str) -> None:
    """The scenarios, each with the index of the robust gains and of the nominal optimum; then worst and mean."""
    chosen, nominal = robust['chosen'], robust['nominal_optimum']
    search = robust['nominal_search']
    print(f"  robust over {len(robust['scenarios'])} scenarios ({robust['objective']} {index}), against the nominal "
          f"optimum (its search: {search['episodes']} episodes in {search['wall_time_s']:.2f} s)")
    if not search['converged']:
        print(f"    WARNING: the nominal optimum's search: {search['certainty']}")
    print(f"    nominal optimum  kp = {format_vector(nominal['kp'])}  kv = {format_vector(nominal['kv'])}")
    rows = [(f"τ = {scenario['tau']:g} s",
             'mass scale ' + (f"{scenario['mass_scale'][0]:g}" if len(set(scenario['mass_scale'])) == 1
                              else format_vector(scenario['mass_scale'])),
             'P^z ' + ('none' if scenario['external_torque'] is None else format_vector(scenario['external_torque'])),
             _cell(None if ours['diverged'] else ours[index]), _cell(None if theirs['diverged'] else theirs[index]))
            for scenario, ours, theirs in zip(robust['scenarios'], chosen['per_scenario'], nominal['per_scenario'])]
    rows += [('worst', '', '', _cell(chosen['worst']), _cell(nominal['worst'])),
             ('mean', '', '', _cell(chosen['mean']), _cell(nominal['mean']))]
    header = ('scenario', '', '', f'robust {index}', f'nominal {index}')
    widths = [max(len(row[column]) for row in (header, *rows)) for column in range(5)]
    for row in (header, *rows):
        print('    ' + '  '.join(cell.ljust(width) if column < 3 else cell.rjust(width)
                                 for column, (cell, width) in enumerate(zip(row, widths))).rstrip())
