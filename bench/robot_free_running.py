"""A free-running robot against the lockstep one: the indices' spread over repeated runs (issue 40, item 2).

    .venv/bin/python bench/robot_free_running.py [--runs 5] [--omega 15] [--json]

The Panda (MuJoCo, config/robots/panda/panda.xml), computed torque with the ω-rule gains on panda-menagerie.urdf,
its motion (T = 1 s, Δ = 0.01 s, delay 1), measured as `ddarm validate --robot` measures: `ddarm robot` and the
controller node in robot mode, recorded and scored from the bag. Once in lockstep (the in-process episode, to
1e-12), then `--runs` times free-running on the wall clock, where the two nodes' ticks are unsynchronised: each
run's I1, I2 and I, what the nodes counted (late periods, stale ticks, timeouts), and the spread.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec, gains_from_omega

ROOT = Path(__file__).resolve().parents[1]
PANDA = ROOT / 'config' / 'robots' / 'panda'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--omega', type=float, default=15.0)
    parser.add_argument('--json', action='store_true')
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from ddarm.ros.robot_session import counted_faults, record_robot_episode

    template = EpisodeSpec(controller='computed_torque', urdf=str(PANDA / 'panda-menagerie.urdf'),
                           motion=str(PANDA / 'panda-motion.yaml'), mjcf=str(PANDA / 'panda.xml'))
    kp, kv = gains_from_omega(template, args.omega)
    spec = template.with_gains(kp, kv)
    in_process = run_episode(spec).indices()
    runs = []
    with tempfile.TemporaryDirectory(prefix='ddarm-bench-') as folder:
        _, lockstep, counters = record_robot_episode(spec, Path(folder) / 'lockstep', 'lockstep')
        lockstep_faults = counted_faults(counters)
        for index in range(args.runs):
            _, score, counters = record_robot_episode(spec, Path(folder) / f'free-{index}', 'realtime')
            runs.append({**{key: score[key] for key in ('I1', 'I2', 'I')}, 'faults': counted_faults(counters)})
    values = np.array([run['I'] for run in runs])
    figures = {'case': f'Panda (MuJoCo), computed torque ω = {args.omega:g}, T = 1 s, Δ = 0.01 s, delay 1',
               'in_process': in_process, 'lockstep': {key: lockstep[key] for key in ('I1', 'I2', 'I')},
               'lockstep_faults': lockstep_faults, 'free_running': runs,
               'I_mean': float(values.mean()), 'I_std': float(values.std(ddof=1)) if len(values) > 1 else 0.0,
               'I_min': float(values.min()), 'I_max': float(values.max()),
               'I_mean_over_lockstep': float(values.mean() / lockstep['I'])}
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    print(f"in-process I = {in_process['I']:.6g}; lockstep I = {lockstep['I']:.6g} {lockstep_faults or ''}")
    for index, run in enumerate(runs):
        print(f"free-running {index}: I1 = {run['I1']:.4g}, I2 = {run['I2']:.4g}, I = {run['I']:.4g} "
              f"{'; '.join(run['faults'])}")
    print(f"free-running I: mean {figures['I_mean']:.4g} ± {figures['I_std']:.2g} (min {figures['I_min']:.4g}, "
          f"max {figures['I_max']:.4g}), {figures['I_mean_over_lockstep']:.3f} × lockstep")


if __name__ == '__main__':
    main()
