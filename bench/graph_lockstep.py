"""Benchmark: plant and controller as separate processes over DDS, in lockstep and in real time.

Prints lockstep throughput (samples per second, multiple of real time) and, in real time at
1/Δ, the period jitter and deadline misses the plant measured. Run from the repository:
    .venv/bin/python bench/graph_lockstep.py [--lockstep-duration 20] [--realtime-duration 30]
"""

import argparse
import json
import os

from ddarm.episodes.spec import EpisodeSpec
from ddarm.ros.session import run_graph_episode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--lockstep-duration', type=float, default=20.0, help='simulated seconds (lockstep)')
    parser.add_argument('--realtime-duration', type=float, default=30.0, help='wall seconds (real time)')
    parser.add_argument('--controller', default='computed_torque')
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    gains = dict(kp=(225.0,) * 3, kv=(30.0,) * 3) if args.controller == 'computed_torque' else dict(
        kp=(2800.0, 2700.0, 350.0), kv=(560.0, 540.0, 70.0))
    figures = {}
    for mode, duration in (('lockstep', args.lockstep_duration), ('realtime', args.realtime_duration)):
        spec = EpisodeSpec(controller=args.controller, **gains, duration=duration)
        result = run_graph_episode(spec, realtime=mode == 'realtime', timeout=duration * 3 + 60)
        report = result.plant_report
        samples = int(report['sample'])
        wall = float(report['wall_time_s'])
        figures[mode] = {'samples': samples, 'wall_time_s': wall, 'samples_per_s': samples / wall,
                         'multiple_of_real_time': samples * spec.period / wall,
                         **{key: float(report[key]) for key in report if key.startswith(('period_jitter', 'deadline',
                                                                                   'stale'))}}
    print(json.dumps(figures, indent=2))


if __name__ == '__main__':
    main()
