"""`ddarm robot` in lockstep against the plant node in lockstep, on the Panda, in one run (issue 40, item 4).

    .venv/bin/python bench/robot_lockstep.py [--seconds 10] [--rounds 3] [--json]

(a) `ddarm robot -p mode:=lockstep` (MuJoCo's Panda, config/robots/panda/panda.xml) driven by
    `ddarm controller computed_torque` in robot mode (a timer on /clock, use_sim_time; the efforts as a
    Float64MultiArray), two processes: samples per wall second, from the robot's ~/status over `--seconds`;
(b) the plant node in lockstep on the same MuJoCo robot (`mjcf`), driven by the controller node sampling on its
    states, through ddarm's graph session (`ddarm episode --ros`): the plant's samples over its wall time.
Rounds alternate (a) and (b); "× real time" is samples/s × Δ (Δ = 0.01 s).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rclpy
import rclpy.executors
from std_srvs.srv import Trigger

from ddarm.episodes.spec import EpisodeSpec, check_episode, gains_from_omega

ROOT = Path(__file__).resolve().parents[1]
PANDA = ROOT / 'config' / 'robots' / 'panda'
DDARM = str(Path(sys.executable).with_name('ddarm'))
PERIOD = 0.01


def robot_status(executor, client) -> dict:
    future = client.call_async(Trigger.Request())
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    return json.loads(future.result().message)


def robot_rate(seconds: float, start: list[float]) -> float:
    """Samples per wall second of the robot in lockstep with the controller node, over `seconds` once running;
    the robot starts at rest at `start`, the motion's q^d(0)."""
    robot = subprocess.Popen([DDARM, 'robot', '--ros-args', '-p', f'mjcf:={PANDA / "panda.xml"}',
                              '-p', 'mode:=lockstep', '-p', f'initial_position:={start}'],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    controller = subprocess.Popen([DDARM, 'controller', 'computed_torque', '--ros-args',
                                   '-p', f'urdf:={PANDA / "panda-menagerie.urdf"}',
                                   '-p', f'motion:={PANDA / "panda-motion.yaml"}', '-p', 'omega:=15.0',
                                   '-p', 'sampling:=timer', '-p', 'command_type:=float64_multi_array',
                                   '-p', 'command_topic:=/effort_controller/commands', '-p', 'use_sim_time:=true',
                                   '-p', 'clamp_efforts:=false'],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bench_probe', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        client = node.create_client(Trigger, '/robot/status')
        if not client.wait_for_service(timeout_sec=60.0):
            raise SystemExit('the robot never came up')
        deadline = time.monotonic() + 60.0
        while robot_status(executor, client)['sample'] < 100:  # running, past its first second
            if time.monotonic() > deadline:
                raise SystemExit('the robot never ran')
            time.sleep(0.1)
        first, started = robot_status(executor, client), time.monotonic()
        time.sleep(seconds)
        last, ended = robot_status(executor, client), time.monotonic()
        if last['timeouts'] or last['refused_commands']:
            raise SystemExit(f'the robot timed out or refused commands: {last}')
        return (last['sample'] - first['sample']) / (ended - started)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        for process in (controller, robot):
            process.terminate()
            process.wait(timeout=20)


def plant_rate(session, spec, plan, folder: Path, index: int) -> float:
    from ddarm.ros.session import record_and_score

    result, _ = record_and_score(session, spec, folder / f'plant-{index}')
    report = result.plant_report
    return int(report['sample']) / float(report['wall_time_s'])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=10.0, help='wall s each robot measurement lasts')
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--json', action='store_true')
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from ddarm.ros.session import GraphSession

    template = EpisodeSpec(controller='computed_torque', urdf=str(PANDA / 'panda-menagerie.urdf'),
                           motion=str(PANDA / 'panda-motion.yaml'), mjcf=str(PANDA / 'panda.xml'),
                           duration=args.seconds)
    kp, kv = gains_from_omega(template, 15.0)
    spec = template.with_gains(kp, kv)
    plan = check_episode(spec)
    rounds = []
    with tempfile.TemporaryDirectory(prefix='ddarm-bench-') as folder, \
            GraphSession(Path(folder) / 'nodes') as session:
        session.ready(spec)
        session.run(spec, plan)  # the nodes' first episode loads their compiled code: not timed
        for index in range(args.rounds):
            robot = robot_rate(args.seconds, plan.q_ref[0].tolist())
            plant = plant_rate(session, spec, plan, Path(folder), index)
            rounds.append({'robot_samples_per_s': robot, 'robot_x_real_time': robot * PERIOD,
                           'plant_samples_per_s': plant, 'plant_x_real_time': plant * PERIOD,
                           'robot_over_plant': robot / plant})
    figures = {'case': 'Panda (MuJoCo, config/robots/panda/panda.xml), computed torque ω = 15, Δ = 0.01 s',
               'rounds': rounds, **{f'median_{key}': float(np.median([r[key] for r in rounds]))
                                    for key in rounds[0]}}
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    for index, figures_of_round in enumerate(rounds):
        print(f'round {index}: robot {figures_of_round["robot_x_real_time"]:.1f}× real time, plant node '
              f'{figures_of_round["plant_x_real_time"]:.1f}× ({figures_of_round["robot_over_plant"]:.2f})')
    print(f'median: robot {figures["median_robot_x_real_time"]:.1f}× real time, plant node '
          f'{figures["median_plant_x_real_time"]:.1f}×, ratio {figures["median_robot_over_plant"]:.2f}')


if __name__ == '__main__':
    main()
