"""`ddarm episode`: one closed-loop episode, in-process or through the ROS graph, and its indices."""

from __future__ import annotations

import argparse
import shlex
import time

from ddarm.cli.arguments import episode_spec
from ddarm.cli.output import print_json, print_summary
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeError, check_episode, episode_robot, loop_stability_warnings, model_arm


def episode_scheduling(args: argparse.Namespace):
    """--realtime-priority, --cpu-affinity and --spin-margin as the nodes' SchedulingOptions (None: none given);
    refused before any node starts when they cannot apply (no graph; a core this process may not use)."""
    given = [option for option, value in (('--realtime-priority', args.realtime_priority),
                                          ('--cpu-affinity', args.cpu_affinity), ('--spin-margin', args.spin_margin))
             if value is not None]
    if not given:
        return None
    if not (args.ros or args.realtime):
        raise EpisodeError(f'{given[0]} sets the node processes of an episode through ROS: add --realtime (or --ros)')
    if args.spin_margin is not None and not 0 <= args.spin_margin < args.period:
        raise EpisodeError(f'--spin-margin {args.spin_margin}: not in [0, the period {args.period})')
    from ddarm.realtime import checked_affinity
    from ddarm.ros.node_parameters import SchedulingOptions

    # The nodes inherit this process's cores: a core it may not use, they may not either.
    affinity = None if args.cpu_affinity is None else checked_affinity(args.cpu_affinity, parameter='--cpu-affinity')
    return SchedulingOptions(args.realtime_priority, affinity, args.spin_margin)


def command_episode(args: argparse.Namespace) -> int:
    if args.bag and not (args.ros or args.realtime):
        raise EpisodeError('--bag records an episode run through ROS: add --ros (or --realtime)')
    scheduling = episode_scheduling(args)
    spec = episode_spec(args)
    warnings = list(check_episode(spec).warnings) + loop_stability_warnings(spec)
    started = time.perf_counter()
    if args.ros or args.realtime:
        from ddarm.ros.driver import realtime_warnings  # ROS only when asked for
        from ddarm.ros.session import run_graph_episode

        result = run_graph_episode(spec, realtime=args.realtime, bag=args.bag, storage=args.storage,
                                   command=shlex.join(['ddarm', *args.argv]), scheduling=scheduling)
        transport = 'ros-realtime' if args.realtime else 'ros-lockstep'
        if args.realtime:
            warnings += realtime_warnings(result.plant_report)
    else:
        result = run_episode(spec)
        transport = 'in-process'
    robot = {}
    if spec.mjcf is not None:
        loaded = episode_robot(spec, result.plan)
        robot = {'robot': loaded.description()}
        warnings += loaded.warnings()
    summary = {**result.summary(), **robot, 'locked_joints': dict(model_arm(spec).locked), 'transport': transport,
               'wall_time_s': time.perf_counter() - started,
               'command': shlex.join(['ddarm', *args.argv]), 'warnings': warnings}
    if args.json:
        print_json(summary)
    else:
        print_summary(summary)
    return 0
