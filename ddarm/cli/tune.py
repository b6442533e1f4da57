"""`ddarm tune`: gains optimised in-process for an index, then checked once through the ROS graph."""

from __future__ import annotations

import argparse
import json
import shlex
import sys

from ddarm.cli.arguments import episode_spec
from ddarm.cli.output import format_vector
from ddarm.episodes.indices import INDICES, PAPER_EQUATIONS
from ddarm.episodes.spec import check_episode


def index_name(text: str) -> str:
    """An index by its name, or by the paper's equation number (2.5 is I1, 3.2 is I)."""
    name = PAPER_EQUATIONS.get(text, text)
    if name not in INDICES:
        raise argparse.ArgumentTypeError(f'{text!r} is not an index: one of {", ".join(INDICES)} (or 2.5, 3.2)')
    return name


def command_tune(args: argparse.Namespace) -> int:
    from ddarm.tuning.outputs import check_outputs, finish_tuning, run_folder
    from ddarm.tuning.tune import tune, with_gains

    check_outputs(args.out, args.runs, args.run)
    template = episode_spec(args)
    for warning in check_episode(template).warnings:  # refusals first: nothing is searched before they are fixed
        print(f'ddarm tune: WARNING: {warning}', file=sys.stderr)
    progress = None if args.json else sys.stderr
    if progress:
        print(f'searching ({args.method}, budget {args.budget} episodes, starts ω = {args.omegas}) …',
              file=progress, flush=True)
    tuning = tune(template, args.index, args.method, args.budget, args.omegas, args.seed)
    # Only now: a refused search leaves nothing behind.
    with run_folder('tune', args.controller, args.runs, args.run, shlex.join(['ddarm', *args.argv])) as run:
        best_spec = with_gains(template, tuning.search.kp, tuning.search.kv)
        if progress:
            print(f'best {args.index} = {tuning.search.index:.6g} after {tuning.search.episodes} episodes; '
                  f'checking it through the ROS graph …', file=progress, flush=True)
        scored = check_through_graph(run, best_spec, args.storage)
        report = finish_tuning(run, template, best_spec, tuning, scored, index=args.index, method=args.method,
                               seed=args.seed, out=args.out)
    if args.json:
        print(json.dumps(report))
    else:
        print_tuning(report, tuning)
    return 0 if report['agree'] else 2


def check_through_graph(run, spec, storage: str) -> dict:
    """`spec` run once through the ROS graph, recorded in the run folder, scored from the bag."""
    from ddarm.ros.session import GraphSession

    with GraphSession(run.path / 'nodes') as session:
        _, scored = session.record_and_score(spec, run.bag_path('best'), command=run.summary['command'],
                                             storage=storage)
    return scored


def print_tuning(report: dict, tuning) -> None:
    print(f"{report['controller']}, index ({report['index']}), {report['method']}: {tuning.search.episodes} "
          f"episodes in {tuning.wall_time_s:.2f} s ({tuning.episodes_per_s:.0f} episodes/s)")
    print(f"  starts (ω rules {format_vector(tuning.start_omegas)}): {report['index']} = "
          f"{format_vector(tuning.start_indices)}")
    width = max(len(name) for name in report['joint_names'])
    for name, gains in report['gains'].items():
        print(f"  {name:<{width}}  kp = {gains['p']:.6g}  kv = {gains['d']:.6g}")
    for label, values in (('in-process', report['in_process']), ('from bag  ', report['from_bag'])):
        print(f"  {label}: I1 = {values['I1']:.9g}  I2 = {values['I2']:.9g}  I = {values['I']:.9g}")
    print(f"  largest relative difference {report['max_rel_difference']:.2e} "
          f"({'agree' if report['agree'] else 'DISAGREE'}); bag {report['bag']}")
    for warning in report['warnings']:
        print(f'  WARNING: {warning}')
    if report['saturated_joints']:
        print(f"  at their torque limit in the recorded episode: {', '.join(report['saturated_joints'])}")
    print(f"  report {report['report']}")
    if report['gains_files']:
        print(f"  gains written to {', '.join(report['gains_files'])}")
    else:
        print('  no gains written: the bag does not confirm the search')
