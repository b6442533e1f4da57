"""Small batches with and without the engine's padding of leftover members to a whole SIMD vector (issue 37).

    .venv/bin/python bench/vector_padding.py [--sizes 1 4 5 7 8 12 15 16 23 24 90] [--rounds 7] [--panda]

For each batch size B, one thread, the best of `rounds` calls of a kept BatchRunner on the paper's arm (or the
Panda with --panda), computed torque at the ω = 15 rule gains perturbed: with padding (engine.PAD_FROM, as shipped)
and without (PAD_FROM above any leftover), alternating call by call in one process, so the ratio holds whatever
the machine's load.
"""

from __future__ import annotations

import time

from ddarm.episodes import engine
from ddarm.episodes.bench import perturbed_gains

import small_batch_case


def main() -> None:
    options = small_batch_case.options(__doc__.splitlines()[0], [1, 4, 5, 7, 8, 12, 15, 16, 23, 24, 90], 7)
    template, runner = small_batch_case.compiled_runner(options.panda)
    shipped = engine.PAD_FROM
    print(f"{'B':>4}  {'padded ms':>10}  {'unpadded ms':>11}  {'ratio':>6}")
    for size in options.sizes:
        kp, kv = perturbed_gains(template, size, seed=1)
        best = {True: float('inf'), False: float('inf')}
        for _ in range(options.rounds):
            for padded in (True, False):
                engine.PAD_FROM = shipped if padded else engine.VECTOR_LANES
                started = time.perf_counter()
                runner(kp, kv, threads=1)
                best[padded] = min(best[padded], time.perf_counter() - started)
        engine.PAD_FROM = shipped
        print(f'{size:>4}  {1e3 * best[True]:>10.2f}  {1e3 * best[False]:>11.2f}  {best[False] / best[True]:>6.2f}')


if __name__ == '__main__':
    main()
