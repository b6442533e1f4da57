"""`ddarm bench`: the batch engine's speed on the reference case, one batch call against one call per episode."""

from __future__ import annotations

import argparse
from pathlib import Path

from ddarm.cli.arguments import absolute_path, seed, whole_number
from ddarm.cli.output import print_json
from ddarm.episodes.bench import (BATCH_SIZES, BENCH_EPISODES, GAIN_SPREAD, MANY_JOINT_ARM, SCALAR_EPISODES,
                                  batch_rates, reference_case, run_bench)
from ddarm.physics.arm import config_file


def _count(name: str):
    """An argparse type: a whole number in [1, ddarm.episodes.engine.<name>]."""
    def parse(text: str) -> int:
        from ddarm.episodes import engine

        largest = getattr(engine, name)
        value = int(text)
        if not 1 <= value <= largest:
            raise argparse.ArgumentTypeError(f'{value} is not in [1, {largest}]')
        return value
    return parse


def command_bench(args: argparse.Namespace) -> int:
    template = reference_case(absolute_path(args.urdf), absolute_path(args.motion))
    figures = run_bench(args.episodes, args.seed, args.scalar_episodes, args.threads, template)
    figures['batch_sizes'] = batch_rates(template, BATCH_SIZES, args.seed, args.threads)
    urdf, motion = (str(config_file(*parts)) for parts in MANY_JOINT_ARM)
    arm = reference_case(urdf, motion)
    figures['many_joint_arm'] = {'urdf': urdf, 'motion': motion, 'joints': len(arm.kp),
                                 'batch_sizes': batch_rates(arm, BATCH_SIZES, args.seed, args.threads)}
    if args.ros:
        from ddarm.ros.bench import lockstep_and_round_trips

        figures['ros'] = lockstep_and_round_trips(args.ros_rounds)
    if args.json:
        print_json(figures)
        return 0
    print(f"ddarm bench: {figures['case']}; gains x exp({GAIN_SPREAD} N(0, 1)) per episode (seed "
          f"{figures['seed']}); {figures['substeps']} RK4 substeps")
    print(f"  batch engine : {figures['B']:6d} episodes in {figures['batch_s']:7.3f} s = "
          f"{figures['batch_episodes_per_s']:8.1f} episodes/s (one call; the first call, "
          f"{figures['warmup_s']:.2f} s of compiling or cache loading, not counted)")
    print(f"  one per call : {figures['scalar_episodes']:6d} episodes in {figures['scalar_s']:7.3f} s = "
          f"{figures['scalar_episodes_per_s']:8.1f} episodes/s (the first {figures['scalar_episodes']} "
          f"of the batch's episodes)")
    print(f"  ratio        : {figures['ratio']:.1f} x")
    print(f"  largest relative difference of I1, I2, I on the {figures['scalar_episodes']} episodes both ran: "
          f"{figures['max_rel_index_diff']:.2e}; divergence flags disagree on "
          f"{figures['divergence_disagreements']}")
    print(f"  peak RSS     : {figures['peak_rss_mib']:.0f} MiB")
    many = figures['many_joint_arm']
    for label, rates in ((f"this case ({figures['joints']} joints)", figures['batch_sizes']),
                         (f"{many['joints']}-joint arm ({Path(many['urdf']).name}, ω = 15 rule)", many['batch_sizes'])):
        print(f"  batch sizes, {label}: " + ', '.join(f"B = {rate['B']}: {rate['episodes_per_s']:.0f}"
                                                     for rate in rates) + ' episodes/s')
    if args.ros:
        ros = figures['ros']
        print(f"  ROS lockstep : {ros['case']}, {ros['samples']} samples, against {ros['round_trips']} bare round "
              'trips of a 3-joint JointState between two processes, alternately:')
        for number, round_figures in enumerate(ros['rounds']):
            print(f"    round {number}: {round_figures['lockstep_samples_per_s']:7.0f} samples/s "
                  f"({round_figures['episode_samples_per_s']:.0f} over the whole episode) against "
                  f"{round_figures['round_trips_per_s']:7.0f} round trips/s (p50 {round_figures['round_trip_p50_ms']:.3f}"
                  f" ms): ratio {round_figures['ratio']:.2f}; against "
                  f"{round_figures['serialized_round_trips_per_s']:7.0f} round trips/s of its CDR bytes: ratio "
                  f"{round_figures['serialized_ratio']:.2f}")
        print(f"    median ratio {ros['median_ratio']:.2f} (messages), {ros['median_serialized_ratio']:.2f} (bytes)")
    return 0


def add_bench_parser(commands) -> None:
    """Register `ddarm bench` on the `ddarm` command's subparsers."""
    bench = commands.add_parser('bench', help='episodes per second of the batch engine: one batch call against one call per episode')
    bench.add_argument('--episodes', type=_count('MAX_BATCH'), default=BENCH_EPISODES, metavar='N',
                       help=f'episodes in the batch ({BENCH_EPISODES})')
    bench.add_argument('--scalar-episodes', type=_count('MAX_BATCH'), default=SCALAR_EPISODES, metavar='M',
                       help=f'of them, how many also run one per call ({SCALAR_EPISODES})')
    bench.add_argument('--seed', type=seed, default=0, help='seed of the gain perturbation (0)')
    bench.add_argument('--threads', type=_count('MAX_THREADS'), metavar='T',
                       help='threads of the batch engine (the cores available)')
    bench.add_argument('--urdf', metavar='FILE', help="another arm (default: the paper's); with --motion")
    bench.add_argument('--motion', metavar='FILE.yaml', help="the motion on that arm (default: the paper's "
                       'trajectory 1)')
    bench.add_argument('--ros', action='store_true',
                       help='also lockstep samples/s through the ROS graph against the bare DDS round trip, '
                            'alternately (about a minute)')
    bench.add_argument('--ros-rounds', type=whole_number(1, 100), default=3, metavar='R',
                       help='rounds of the ROS comparison (3)')
    bench.add_argument('--json', action='store_true', help='print one JSON object')
    bench.set_defaults(handler=command_bench)
