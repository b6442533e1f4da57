"""`ddarm plant`, `ddarm robot`, `ddarm controller LAW`, `ddarm tuner`: the ROS 2 nodes, started with the --ros-args given."""

from __future__ import annotations

import argparse

from ddarm.cli.arguments import absolute_path


def command_plant(args: argparse.Namespace) -> int:
    from ddarm_sim.node import main as plant_main

    return plant_main(['ddarm-plant', *args.ros_arguments])


def command_robot(args: argparse.Namespace) -> int:
    from ddarm_sim.robot_node import main as robot_main

    given = ['--ros-args', '-p', f'mjcf:={absolute_path(args.mjcf)}'] if args.mjcf else []
    return robot_main(['ddarm-robot', *args.ros_arguments, *given])


def command_controller(args: argparse.Namespace) -> int:
    from ddarm_control.node import main as controller_main

    return controller_main(['ddarm-controller', *args.ros_arguments], args.law)


def command_tuner(args: argparse.Namespace) -> int:
    from ddarm_tuner.node import main as tuner_main

    return tuner_main(['ddarm-tuner', *args.ros_arguments])
