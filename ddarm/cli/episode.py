"""`ddarm episode`: one closed-loop episode, in-process or through the ROS graph, and its indices."""

from __future__ import annotations

import argparse
import json
import shlex
import time

from ddarm.cli.arguments import episode_spec
from ddarm.cli.output import print_summary
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeError, check_episode, model_arm


def command_episode(args: argparse.Namespace) -> int:
    if args.bag and not (args.ros or args.realtime):
        raise EpisodeError('--bag records an episode run through ROS: add --ros (or --realtime)')
    spec = episode_spec(args)
    warnings = list(check_episode(spec).warnings)
    started = time.perf_counter()
    if args.ros or args.realtime:
        from ddarm.ros.driver import realtime_warnings  # ROS only when asked for
        from ddarm.ros.session import run_graph_episode

        result = run_graph_episode(spec, realtime=args.realtime, bag=args.bag, storage=args.storage,
                                   command=shlex.join(['ddarm', *args.argv]))
        transport = 'ros-realtime' if args.realtime else 'ros-lockstep'
        if args.realtime:
            warnings += realtime_warnings(result.plant_report)
    else:
        result = run_episode(spec)
        transport = 'in-process'
    summary = {**result.summary(), 'locked_joints': dict(model_arm(spec).locked), 'transport': transport,
               'wall_time_s': time.perf_counter() - started,
               'command': shlex.join(['ddarm', *args.argv]), 'warnings': warnings}
    if args.json:
        print(json.dumps(summary))
    else:
        print_summary(summary)
    return 0
