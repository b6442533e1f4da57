"""Small and middling batches on one thread against two: where sharing a batch out over threads starts to pay.

    .venv/bin/python bench/thread_share.py [--sizes 6 8 12 16 24 32 48 64] [--rounds 9] [--panda]

For each batch size B, the best of `rounds` calls of a kept BatchRunner on the paper's arm (or the Panda with
--panda), computed torque at the ω = 15 rule gains perturbed, on one thread and on two (the engine's threshold
lowered so that two are used whatever B), alternating call by call in one process, so the ratio holds whatever the
machine's load. The engine's MIN_MEMBERS_PER_THREAD and MIN_MEMBERS_PER_THREAD_UNVECTORISED come from this.
"""

from __future__ import annotations

import argparse
import time

from ddarm.episodes import engine
from ddarm.episodes.bench import MANY_JOINT_ARM, perturbed_gains, reference_case
from ddarm.episodes.engine import BatchRunner
from ddarm.physics.arm import config_file


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--sizes', type=int, nargs='+', default=[6, 8, 12, 16, 24, 32, 48, 64])
    parser.add_argument('--rounds', type=int, default=9)
    parser.add_argument('--panda', action='store_true', help='the Panda (7 joints) instead of the paper\'s arm')
    options = parser.parse_args()
    template = reference_case(*(str(config_file(*parts)) for parts in MANY_JOINT_ARM)) if options.panda else (
        reference_case())
    runner = BatchRunner(template)
    runner(*perturbed_gains(template, 1, seed=1), threads=1)  # compiles the arm's dynamics, or loads them
    engine.MIN_MEMBERS_PER_THREAD = engine.MIN_MEMBERS_PER_THREAD_UNVECTORISED = 1
    print(f"{'B':>4}  {'1 thread ms':>11}  {'2 threads ms':>12}  {'ratio':>6}")
    for size in options.sizes:
        kp, kv = perturbed_gains(template, size, seed=1)
        best = {1: float('inf'), 2: float('inf')}
        for _ in range(options.rounds):
            for threads in best:
                started = time.perf_counter()
                runner(kp, kv, threads=threads)
                best[threads] = min(best[threads], time.perf_counter() - started)
        print(f'{size:>4}  {1e3 * best[1]:>11.2f}  {1e3 * best[2]:>12.2f}  {best[1] / best[2]:>6.2f}')


if __name__ == '__main__':
    main()
