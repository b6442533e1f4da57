"""The Python time of a small batch call before its episodes run (issue 37): per call, planned anew against planned
once per search.

    .venv/bin/python bench/batch_overhead.py [--calls 300] [--batch 8]

For the paper's arm and the Panda (computed torque, ω = 15 rule gains perturbed), B episodes per call:
(a) `simulate_batch(template, kp, kv, plan=plan)`, which prepares the template's batch at every call (the chains,
the compiled dynamics, the reference's gravity, the weights), as every search did before; (b) one `BatchRunner`
kept for all the calls, as the searches now do. The time inside the compiled loop is measured in the same calls
(the loop is wrapped by a timer), so each call's overhead is its wall time minus that. Both run alternately in
one process, so the ratio holds whatever the machine's load.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ddarm.episodes import engine
from ddarm.episodes.bench import MANY_JOINT_ARM, perturbed_gains, reference_case
from ddarm.episodes.engine import BatchRunner, simulate_batch
from ddarm.episodes.spec import check_episode
from ddarm.physics.arm import config_file


class Timed:
    """A function with the seconds spent in it added up (here engine._run_chunks; bench/search_rate.py's the batch
    calls), and each call's in `durations`."""

    def __init__(self, function) -> None:
        self.function, self.seconds, self.durations = function, 0.0, []

    def __call__(self, *arguments, **keywords):
        started = time.perf_counter()
        try:
            return self.function(*arguments, **keywords)
        finally:
            self.durations.append(time.perf_counter() - started)
            self.seconds += self.durations[-1]


def per_call(call, calls: int, timer: Timed) -> dict:
    """Median wall time of `calls` calls and the median overhead (wall minus the compiled loop), in ms."""
    walls, overheads = [], []
    for _ in range(calls):
        timer.seconds = 0.0
        started = time.perf_counter()
        call()
        wall = time.perf_counter() - started
        walls.append(wall)
        overheads.append(wall - timer.seconds)
    return {'wall_ms': 1e3 * float(np.median(walls)), 'overhead_ms': 1e3 * float(np.median(overheads))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--calls', type=int, default=300)
    parser.add_argument('--batch', type=int, default=8)
    options = parser.parse_args()
    timer = Timed(engine._run_chunks)
    engine._run_chunks = timer
    urdf, motion = (str(config_file(*parts)) for parts in MANY_JOINT_ARM)
    # One thread: the loop time of a call on two would be the sum of both threads' (a Panda batch of 8 shares out).
    print(f'B = {options.batch}, {options.calls} calls each, medians; one thread')
    print(f"{'arm':<12} {'per call: planned anew':>24} {'BatchRunner kept':>18} {'overhead ratio':>15}")
    for name, template in (('paper arm', reference_case()), ('panda', reference_case(urdf, motion))):
        plan = check_episode(template)
        kp, kv = perturbed_gains(template, options.batch, seed=1)
        runner = BatchRunner(template, plan)
        runner(kp, kv, threads=1)
        before = per_call(lambda: simulate_batch(template, kp, kv, plan=plan, threads=1), options.calls, timer)
        after = per_call(lambda: runner(kp, kv, threads=1), options.calls, timer)
        print(f"{name:<12} {before['overhead_ms']:>8.3f} ms of {before['wall_ms']:>6.3f} ms "
              f"{after['overhead_ms']:>6.3f} of {after['wall_ms']:>6.3f} "
              f"{before['overhead_ms'] / after['overhead_ms']:>14.1f}x")


if __name__ == '__main__':
    main()
