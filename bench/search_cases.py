"""How close `ddarm tune`'s default search comes to the best known minima of a set of cases, and how fast.

Each case is a `ddarm tune` command with the best minimum an independent search found (`objective`), as in
../shared/search-cases.json. For each case this runs the search that command runs (in-process, as `ddarm tune`
does, without the recording) and prints the best known and found minima side by side, the gap, the search's
wall time and episodes, and its certificate when it gives one. The best known gains are also scored by ddarm's own
episode (`rescored`), and the gap is measured against that (a case without gains is measured against its
`objective`, NaN if unknown): a file written before a change of the model (the Panda's
URDF `<dynamics>`, say) can hold a value ddarm no longer gives for those gains.

`bench/search-cases-own.json` holds the project's own cases, on the Z1, the UR5 and the SCARA with other laws,
indices, periods and delays than the shared ones. Their best known minima come from long runs on this machine
(2026-12-06, at fd7d82d): `ddarm tune`'s global search with a budget of 300,000 from seeds 0 and 1, and
`--method nelder-mead` from ten ω between 4 and 40 with 150,000; each case lists every run's best. They are not
independent of ddarm's search as the shared cases' are. (The Z1 at Δ = 0.02 s was tried and dropped: every gain
diverged, its joint6 being stopped by its damping within a substep, as `ddarm episode` warns.)

    .venv/bin/python bench/search_cases.py ../shared/search-cases.json ../shared/search-cases-arms.json \
        bench/search-cases-own.json
    .venv/bin/python bench/search_cases.py CASES.json --only 0 3 --json results.json
    .venv/bin/python bench/search_cases.py ../shared/search-cases.json --only 2 3 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from ddarm.cli.arguments import episode_spec
from ddarm.cli.main import build_parser
from ddarm.episodes.engine import simulate_batch, warm_up
from ddarm.tuning.tune import tune


def run_case(case: dict, budget: int | None = None, seed: int | None = None) -> dict:
    words = (shlex.split(case['command']) + ([] if budget is None else ['--budget', str(budget)])
             + ([] if seed is None else ['--seed', str(seed)]))
    args = build_parser().parse_args(words[1:])
    template = episode_spec(args)
    started = time.perf_counter()
    tuning = tune(template, args.index, args.method, args.budget, args.omegas, args.seed)
    wall = time.perf_counter() - started
    search = tuning.search
    certificate = getattr(search, 'certificate', None)
    known = case.get('best_known')  # a case kept aside may give no gains, its minimum unknown (NaN)
    rescored = (float(getattr(simulate_batch(template, [known['kp']], [known['kv']]), search.index_name)[0])
                if known is not None else float('nan'))
    return {
        'command': case['command'], 'seed': args.seed, 'best_known': case['objective'], 'rescored': rescored,
        'found': float(search.index),
        'gap': float(search.index) / (rescored if known is not None else case['objective']) - 1.0,
        'wall_time_s': wall, 'episodes': search.episodes,
        'episodes_per_s': search.episodes / wall,
        'certificate': None if certificate is None else certificate.to_dict(),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('cases', nargs='+', type=Path, help='JSON files of cases')
    parser.add_argument('--only', type=int, nargs='+', help='the cases to run, by their number in the listing')
    parser.add_argument('--json', type=Path, help='write the results here too')
    parser.add_argument('--budget', type=int, help="each case's --budget (default: its command's, or ddarm tune's)")
    parser.add_argument('--seeds', type=int, nargs='+',
                        help="run each case once from each of these --seed (default: its command's, or ddarm tune's)")
    options = parser.parse_args()
    cases = [case for path in options.cases for case in json.loads(path.read_text())]
    warm_up()
    results = []
    print(f"{'#':>2}  {'seed':>4}  {'best known':>12}  {'rescored':>12}  {'found':>12}  {'gap':>8}  {'wall s':>7}  "
          f"{'episodes':>8}  certificate")
    for number, case in enumerate(cases):
        if options.only is not None and number not in options.only:
            continue
        for seed in [None] if options.seeds is None else options.seeds:
            result = run_case(case, options.budget, seed)
            results.append(result)
            certificate = result['certificate']
            print(f"{number:>2}  {result['seed']:>4}  {result['best_known']:>12.6g}  {result['rescored']:>12.6g}  "
                  f"{result['found']:>12.6g}  {100 * result['gap']:>7.2f}%  "
                  f"{result['wall_time_s']:>7.1f}  {result['episodes']:>8}  "
                  f"{'' if certificate is None else certificate['summary']}", flush=True)
    gaps = np.array([result['gap'] for result in results])
    gaps = gaps[np.isfinite(gaps)]  # the cases with a known minimum
    if len(gaps):
        print(f'within 1 %: {int(np.sum(gaps <= 0.01))} of {len(gaps)} searches with a known minimum; '
              f'worst gap {100 * gaps.max():.2f} %')
    if options.json is not None:
        options.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
