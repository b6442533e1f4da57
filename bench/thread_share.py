"""Small and middling batches on one thread against two: where sharing a batch out over threads starts to pay.

    .venv/bin/python bench/thread_share.py [--sizes 6 8 12 16 24 32 48 64] [--rounds 9] [--panda]

For each batch size B, the best of `rounds` calls of a kept BatchRunner on the paper's arm (or the Panda with
--panda), computed torque at the ω = 15 rule gains perturbed, on one thread and on two (the engine's threshold
lifted so that two are used whatever B), alternating call by call in one process, so the ratio holds whatever the
machine's load. The engine's sharing out by SIMD vectors (`_shares`) comes from this.
"""

from __future__ import annotations

import time

from ddarm.episodes import engine
from ddarm.episodes.bench import perturbed_gains

import small_batch_case


def main() -> None:
    options = small_batch_case.options(__doc__.splitlines()[0], [6, 8, 12, 16, 24, 32, 48, 64], 9)
    template, runner = small_batch_case.compiled_runner(options.panda)
    engine._shares = lambda size, dof: size
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
