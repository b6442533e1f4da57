"""`ddarm pareto`: the I1–I2 Pareto front of the gains, in-process through the batch engine, seeded by the
single-index optima of `ddarm tune`'s search."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np

from ddarm.cli.arguments import add_episode_arguments, episode_spec, seed
from ddarm.cli.output import format_vector, print_json
from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.episodes.spec import arm_joints, check_episode
from ddarm.recording.bags import BagError, checked_output_path, folder_problem
from ddarm.reporting.progress import Progress
from ddarm.tuning.methods import (DEFAULT_BUDGET, DEFAULT_METHOD, DEFAULT_POINTS, DEFAULT_POPULATION,
                                  DEFAULT_TUNE_BUDGET, METHODS, ParetoError)

# Episodes of each single-index search: `ddarm tune`'s default budget.
SEED_BUDGET = DEFAULT_TUNE_BUDGET
# The indices whose optima seed the front: (2.5), the front's one end, and (3.2), a point on it.
SEED_INDICES = ('I1', 'I')


def _checked_yaml_dir(text: str | None) -> Path | None:
    if text is None:
        return None
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise ParetoError(f'--yaml-dir {path}: a file, not a folder')
    if path.is_dir() and any(path.iterdir()):
        raise ParetoError(f'--yaml-dir {path}: the folder exists and is not empty; give a new or empty one')
    if not path.exists() and (problem := folder_problem(path.absolute().parent)) is not None:
        raise ParetoError(f'--yaml-dir {path}: {problem}')
    try:  # as every output: no '..' in it and no symlink on the way (each point's file is new, 'x' when written)
        checked_output_path(path / 'point-00.yaml')
    except BagError as error:
        raise ParetoError(f'--yaml-dir {error}') from error
    return path


def _checked_plot(text: str | None) -> Path | None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if text is None:
        return None
    path = Path(text)
    formats = FigureCanvasAgg.get_supported_filetypes()
    if path.suffix[1:].lower() not in formats:
        raise ParetoError(f'--plot {path}: the name must end in one of {", ".join("." + f for f in formats)}')
    try:
        checked_output_path(path)
    except BagError as error:
        raise ParetoError(f'--plot {error}') from error
    if not path.absolute().parent.is_dir():
        raise ParetoError(f'--plot {path}: the folder {path.absolute().parent} does not exist')
    return path


def _check_counts(args: argparse.Namespace) -> None:
    least = len(SEED_INDICES) + DEFAULT_POPULATION
    if args.budget < least:
        raise ParetoError(f'--budget must be at least {least} episodes (the seeds and the first population), '
                          f'got {args.budget}')
    if args.seed < 0:
        raise ParetoError(f'--seed must be 0 or more (a NumPy seed), got {args.seed}')
    if args.points < 3:
        raise ParetoError(f'--points must be at least 3 (both ends and the point of least I are always kept), '
                          f'got {args.points}')


def _seed_search_note(tuning, budget: int) -> str | None:
    """What stopped a single-index search, when it may have been the budget rather than convergence.

    The global search's confidence figure is how many of its local CMA-ES runs reached within 1 % of the
    optimum, whether they stopped on convergence or at the budget. The others stop on convergence or before a batch
    that would exceed the budget, and none asks for more than S (2n + 1) points at once (S starts, n joints):
    with less than that left, the stop may have been the budget's."""
    search = tuning.search
    if search.restarts:
        return f'{search.restarts_within(0.01)} of its {len(search.restarts)} local runs reached it within 1 %'
    largest_batch = len(tuning.start_omegas) * (2 * len(search.kp) + 1)
    if budget - search.episodes < largest_batch:
        return f'its search spent the budget, {search.episodes} of {budget} episodes: it may not have converged'
    return None


def _position(point: dict, on_front: bool, front: list[dict]) -> dict:
    """Where a single-index optimum sits: on the front (the reported point it is, if not thinned out), or
    dominated by it (a reported point that dominates it, if one does)."""
    if on_front:
        ranks = [rank for rank, other in enumerate(front) if (other['I1'], other['I2']) == (point['I1'], point['I2'])]
        return {'where': 'on the front' if ranks else 'on the front, thinned out of the reported points',
                'front_point': ranks[0] if ranks else None}
    ranks = [rank for rank, other in enumerate(front) if other['I1'] <= point['I1'] and other['I2'] <= point['I2']]
    return {'where': 'dominated by the front', 'front_point': ranks[0] if ranks else None}


def single_index_optima(args: argparse.Namespace, template, log) -> dict:
    """`ddarm tune`'s in-process search for each of SEED_INDICES: {index: Tuning}. Refused before any is run."""
    from ddarm.tuning.search import SearchError, check_search, omega_starts
    from ddarm.tuning.tune import tune

    start_kp, start_kv = omega_starts(template, SEARCH_START_OMEGAS)
    for index in SEED_INDICES:
        try:
            check_search(template, index=index, start_kp=start_kp, start_kv=start_kv, budget=args.tune_budget,
                         method=args.method)
        except SearchError as error:
            raise ParetoError(f'--tune-budget: {error}') from error
    optima = {}
    for index in SEED_INDICES:
        with Progress(args.tune_budget, f'least {index} ({args.method})', quiet=log is None, index_name=index) as bar:
            optima[index] = tune(template, index, args.method, args.tune_budget, SEARCH_START_OMEGAS, args.seed,
                                 progress=bar.update)
    return optima


def _optimum_entry(tuning, on_front: bool, args: argparse.Namespace, front: list[dict]) -> dict:
    entry = {'method': args.method, 'episodes': tuning.search.episodes, 'budget': args.tune_budget,
             'wall_time_s': tuning.wall_time_s, 'kp': tuning.search.kp.tolist(), 'kv': tuning.search.kv.tolist()}
    if not np.isfinite(tuning.search.index):  # its indices would be those of a diverged episode's first samples
        return {**entry, 'diverged': True, 'note': 'every episode of its search diverged'}
    entry.update(tuning.best, diverged=False, note=_seed_search_note(tuning, args.tune_budget))
    return {**entry, **_position(entry, on_front, front)}


def write_front_yamls(folder: Path, template, front: list[dict], joint_names: list[str], command: str) -> list[str]:
    """Each front point's controller YAML in `folder` (created if new), point-00.yaml at least I1 onwards."""
    from ddarm.recording.runs import controller_yaml, write_new_text

    folder.mkdir(exist_ok=True)
    width = max(2, len(str(len(front) - 1)))
    written = []
    for rank, point in enumerate(front):
        provenance = (f"point {rank} of {len(front)} of the I1-I2 front, by rising I1: I1 = {point['I1']!r}, "
                      f"I2 = {point['I2']!r}\nfrom: {command}")
        text = controller_yaml(template.controller, point['kp'], point['kv'], template.delay, template.period,
                               provenance, joint_names=joint_names, urdf=template.model_urdf or template.urdf,
                               motion=template.motion, duration=template.duration)
        written.append(str(write_new_text(folder / f'point-{rank:0{width}d}.yaml', text)))
    return written


def command_pareto(args: argparse.Namespace) -> int:
    from ddarm.tuning.pareto import pareto_front

    _check_counts(args)
    yaml_dir, plot = _checked_yaml_dir(args.yaml_dir), _checked_plot(args.plot)
    template = episode_spec(args)
    for warning in check_episode(template).warnings:  # refusals first: nothing is searched before they are fixed
        print(f'ddarm pareto: WARNING: {warning}', file=sys.stderr)
    log = None if args.json else sys.stderr
    optima = single_index_optima(args, template, log)
    if log:
        print(f'the front (budget {args.budget} episodes) …', file=log, flush=True)
    with Progress(args.budget, 'front', quiet=args.json) as bar:
        result = pareto_front(template, budget=args.budget, seed=args.seed, points=args.points,
                              seeds=[(tuning.search.kp, tuning.search.kv) for tuning in optima.values()],
                              progress=bar.update)
    joint_names = list(arm_joints(template)[0])
    front = [{'I1': point.I1, 'I2': point.I2, 'kp': point.kp.tolist(), 'kv': point.kv.tolist()}
             for point in result.front]
    command = shlex.join(['ddarm', *args.argv])
    report = {
        'controller': template.controller, 'joint_names': joint_names, 'front': front,
        'least_I_point': min(range(len(front)), key=lambda rank: result.front[rank].I),
        'front_size': result.front_size,
        'single_index_optima': {index: _optimum_entry(tuning, on_front, args, front)
                                for (index, tuning), on_front in zip(optima.items(), result.seeds_on_front)},
        'episodes': result.episodes, 'diverged_episodes': result.diverged, 'batches': result.batches,
        'nsga2_generations': result.generations, 'searches': result.searches,
        'searches_converged': result.searches_converged, 'wall_time_s': result.wall_time_s,
        'method': result.method, 'budget': args.budget, 'seed': args.seed, 'spec': template.to_dict(),
        'command': command, 'yaml_files': [], 'plot': None,
    }
    if yaml_dir is not None:
        report['yaml_files'] = write_front_yamls(yaml_dir, template, front, joint_names, command)
    if plot is not None:
        front_figure(plot, report)
        report['plot'] = str(plot)
    if args.json:
        print_json(report)
    else:
        print_front(report)
    return 0


def front_figure(path: Path, report: dict) -> None:
    """The front in the I1–I2 plane (log axes), with the single-index optima and the line I = least I."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    from ddarm.recording.runs import write_new_file
    from ddarm.reporting.text import figure_text

    figure = Figure(figsize=(7.5, 5.5), dpi=120)
    FigureCanvasAgg(figure)
    axis = figure.subplots()
    I1 = np.array([point['I1'] for point in report['front']])
    I2 = np.array([point['I2'] for point in report['front']])
    axis.plot(I1, I2, '-o', color='tab:blue', markersize=4, label=f"front ({len(I1)} of {report['front_size']} "
                                                                   'non-dominated episodes)')
    least = report['front'][report['least_I_point']]
    least_I = least['I1'] + least['I2']
    line = np.geomspace(I1.min(), I1.max(), 200)
    # Only down to the front's least I2: the line falls to I2 = 0 at I1 = least I, far below the front.
    shown = least_I - line >= 0.8 * I2.min()
    axis.plot(line[shown], least_I - line[shown], ':', color='0.5', label=f'I1 + I2 = {least_I:.6g}')
    axis.plot(least['I1'], least['I2'], '*', color='tab:blue', markersize=12, label="the front's least I")
    markers = {'I1': ('s', 'tab:red', 'least I1 (2.5)'), 'I': ('D', 'tab:green', 'least I = I1 + I2 (3.2)')}
    for index, optimum in report['single_index_optima'].items():
        if optimum['diverged']:
            continue
        marker, colour, name = markers[index]
        axis.plot(optimum['I1'], optimum['I2'], marker, color=colour, markersize=9, markerfacecolor='none',
                  markeredgewidth=1.8, label=f"{name} by ddarm tune's search ({optimum['method']})")
    axis.set_xscale('log')
    axis.set_yscale('log')
    for scale in (axis.xaxis, axis.yaxis):  # plain numbers at 1, 2, 5 x 10^k: the defaults print 6x10^-1
        scale.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        scale.set_major_formatter(FormatStrFormatter('%g'))
        scale.set_minor_formatter(NullFormatter())
    axis.set_xlabel('I1 (2.5), tracking error')
    axis.set_ylabel('I2, torque deviation from nominal')
    spec = report['spec']
    motion = Path(spec['motion']).name if spec.get('motion') else f"trajectory {spec['trajectory']}"
    axis.set_title(figure_text(f"{report['controller']}, {motion}: {report['episodes']} episodes"), parse_math=False)
    axis.grid(True, which='both', alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    write_new_file(path, lambda file: figure.savefig(file, format=path.suffix[1:].lower()))


def print_front(report: dict) -> None:
    searches_s = sum(optimum['wall_time_s'] for optimum in report['single_index_optima'].values())
    print(f"{report['controller']}: I1-I2 front of {len(report['front'])} points (of {report['front_size']} "
          f"non-dominated), {report['episodes']} episodes ({report['diverged_episodes']} diverged) in "
          f"{report['wall_time_s']:.1f} s, after {searches_s:.1f} s of single-index searches")
    print(f"  method: {report['method']}")
    if report['searches_converged'] < report['searches']:
        print(f"  {report['searches'] - report['searches_converged']} of the {report['searches']} refining searches "
              f"stopped at the budget, not converged: a larger --budget may still move the front")
    for index, optimum in report['single_index_optima'].items():
        if optimum['diverged']:
            print(f"  least {index} by the {optimum['method']} search: none ({optimum['note']})")
            continue
        note = f" ({optimum['note']})" if optimum['note'] else ''
        rank = '' if optimum['front_point'] is None else f" (point {optimum['front_point']})"
        print(f"  least {index} by the {optimum['method']} search: I1 = {optimum['I1']:.6g}  I2 = {optimum['I2']:.6g}  "
              f"I = {optimum['I']:.6g}{note}; {optimum['where']}{rank}")
    names = ', '.join(report['joint_names'])
    print(f"  {'#':>3}  {'I1':>11}  {'I2':>11}  {'I':>11}  kp ({names})  kv")
    for rank, point in enumerate(report['front']):
        marks = [label for label, condition in (('least I1', rank == 0), ('least I2', rank == len(report['front']) - 1),
                                                ('least I', rank == report['least_I_point'])) if condition]
        print(f"  {rank:>3}  {point['I1']:11.6g}  {point['I2']:11.6g}  {point['I1'] + point['I2']:11.6g}  "
              f"{format_vector(point['kp'])}  {format_vector(point['kv'])}"
              + (f"  <- {', '.join(marks)}" if marks else ''))
    if report['yaml_files']:
        print(f"  controller YAMLs: {Path(report['yaml_files'][0]).parent}/point-NN.yaml, one per point")
    if report['plot']:
        print(f"  plot {report['plot']}")


def add_pareto_parser(commands) -> None:
    """Register `ddarm pareto` on the `ddarm` command's subparsers."""
    pareto = commands.add_parser(
        'pareto', help='the I1-I2 Pareto front of the gains, in-process through the batch engine (no ROS)',
        description='The gains for which neither I1 (2.5) nor I2 can be lowered without raising the other, '
                    'found in-process through the batch engine (unlike ddarm tune, nothing runs through the '
                    'ROS graph): NSGA-II and scalarised CMA-ES searches, seeded by the least-I1 and least-I '
                    "gains of ddarm tune's search.")
    add_episode_arguments(pareto, gains=False)
    pareto.add_argument('--budget', type=int, default=DEFAULT_BUDGET, metavar='N',
                        help=f'most episodes evaluated for the front, after the single-index searches ({DEFAULT_BUDGET})')
    pareto.add_argument('--method', choices=METHODS, default=DEFAULT_METHOD,
                        help=f'the single-index searches of the seeds, as ddarm tune --method ({DEFAULT_METHOD})')
    pareto.add_argument('--tune-budget', type=int, default=SEED_BUDGET, metavar='N',
                        help=f'most episodes of each single-index search ({SEED_BUDGET})')
    pareto.add_argument('--seed', type=seed, default=0, help='random seed of the searches (0)')
    pareto.add_argument('--points', type=int, default=DEFAULT_POINTS, metavar='N',
                        help=f'most points reported, spread along the front ({DEFAULT_POINTS})')
    pareto.add_argument('--plot', metavar='FILE.png', help='draw the front in the I1-I2 plane here (new file)')
    pareto.add_argument('--yaml-dir', metavar='DIR',
                        help='write each point\'s controller YAML here, point-00.yaml (least I1) onwards '
                             '(a new or empty folder)')
    pareto.add_argument('--json', action='store_true', help='print one JSON object')
    pareto.set_defaults(handler=command_pareto)
