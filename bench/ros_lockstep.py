"""Benchmark: lockstep samples per second through the ROS graph against the bare DDS round trip, side by side.

Alternates a recorded lockstep episode of the reference case (plant and controller processes, the driver in
this process) with round trips of a 3-joint JointState between two bare rclpy processes, and prints each
round's rates and their ratio as JSON (what `ddarm bench --ros` adds to its figures). Run from the repository:
    .venv/bin/python bench/ros_lockstep.py [--rounds 3] [--duration 20] [--round-trips 2000]
"""

import argparse
import json
import os

from ddarm.ros.bench import LOCKSTEP_DURATION, ROUND_TRIPS, lockstep_and_round_trips


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--duration', type=float, default=LOCKSTEP_DURATION, help='simulated s per lockstep episode')
    parser.add_argument('--round-trips', type=int, default=ROUND_TRIPS)
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    print(json.dumps(lockstep_and_round_trips(args.rounds, args.duration, args.round_trips), indent=2))


if __name__ == '__main__':
    main()
