"""Episodes per second with MuJoCo as the plant beside ddarm's own plant, on the Panda (issue 34, item 6).

    .venv/bin/python bench/mujoco_plant.py [--seconds 3] [--json]

The same episode (computed torque, ω = 15, the Panda motion, T = 1 s, Δ = 0.01 s, delay 1: 101 samples) run as
(a) ddarm's plant, one episode per call (`run_episode`, the batch engine with B = 1);
(b) ddarm's plant in batches of 256 (`simulate_batch`, all cores): the rate a search sees;
(c) ddarm's plant through the stepwise loop the MuJoCo episode runs (`run_stepwise`): the loop's own cost;
(d) MuJoCo's Panda (`config/robots/panda/panda.xml`, implicitfast, 5 timesteps per period) in process
    (`run_episode` of the spec with `mjcf`);
(e) MuJoCo alone: the 500 mj_step calls of one episode with no law, the floor of (d).
Each rate is the best of three runs of `--seconds` each; the ratios are against (a), measured in the same run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import mujoco
import numpy as np

from ddarm.episodes.engine import run_episode, simulate_batch
from ddarm.episodes.spec import EpisodeSpec, check_episode, gains_from_omega, plant_chain
from ddarm.episodes.stepwise import run_stepwise
from ddarm.physics.plant import Plant, PlantOptions

ROOT = Path(__file__).resolve().parents[1]
BATCH = 256


def rate(work, episodes_per_call: int, seconds: float) -> float:
    """Episodes per second of `work` (one call), the best of three runs of about `seconds`."""
    work()
    best = 0.0
    for _ in range(3):
        calls, started = 0, time.perf_counter()
        while time.perf_counter() - started < seconds:
            work()
            calls += 1
        best = max(best, calls * episodes_per_call / (time.perf_counter() - started))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=3.0)
    parser.add_argument('--json', action='store_true')
    args = parser.parse_args()
    template = EpisodeSpec(controller='computed_torque',
                           urdf=str(ROOT / 'config/arms/panda/panda.urdf'),
                           motion=str(ROOT / 'config/arms/panda/panda-motion.yaml'))
    kp, kv = gains_from_omega(template, 15.0)
    spec = template.with_gains(kp, kv)
    robot = dataclasses.replace(spec, mjcf=str(ROOT / 'config/robots/panda/panda.xml'))
    plan, robot_plan = check_episode(spec), check_episode(robot)
    chain = plant_chain(spec)
    gains = np.tile(kp, (BATCH, 1)), np.tile(kv, (BATCH, 1))
    model = mujoco.MjModel.from_xml_path(robot.mjcf)
    data = mujoco.MjData(model)

    def mujoco_alone():
        mujoco.mj_resetData(model, data)
        for _ in range(plan.k_max * 5):
            mujoco.mj_step(model, data)

    rates = {
        'ddarm_plant_one_per_call': rate(lambda: run_episode(spec, plan), 1, args.seconds),
        f'ddarm_plant_batch_{BATCH}': rate(lambda: simulate_batch(spec, *gains, plan=plan), BATCH, args.seconds),
        'ddarm_plant_stepwise': rate(lambda: run_stepwise(spec, plan, Plant(chain, PlantOptions(), plan.q0, plan.v0)),
                                     1, args.seconds),
        'mujoco_in_process': rate(lambda: run_episode(robot, robot_plan), 1, args.seconds),
        'mujoco_steps_alone': rate(mujoco_alone, 1, args.seconds),
    }
    baseline = rates['ddarm_plant_one_per_call']
    result = {'case': 'Panda, computed torque, ω = 15, T = 1 s, Δ = 0.01 s, delay 1 (101 samples)',
              'episodes_per_s': rates, 'ratio_to_ddarm_plant_one_per_call': {
                  name: value / baseline for name, value in rates.items()}}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(result['case'])
    for name, value in rates.items():
        print(f'  {name:28s} {value:10.1f} episodes/s   {value / baseline:7.3f} x (a)')


if __name__ == '__main__':
    main()
