"""Every number of a fixed set of ddarm commands, written to one JSON file, and two such files compared.

A refactor that should change no number (renames, a schema, a split of the episode) is checked with it: run
`snapshot` before and after, then `compare` (it fails when a number moved by more than 1e-12 relative, or a key
went away). Wall times, rates, paths and dates are left out: they change from run to run.

    python bench/numbers_unchanged.py snapshot before.json [--quick]
    python bench/numbers_unchanged.py compare before.json after.json

The commands run as `python -m ddarm.cli.main`, so PYTHONPATH=<another checkout> snapshots that checkout's code.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ARMS = REPO / 'config' / 'arms'
ROBOTS = REPO / 'config' / 'robots'

# Keys whose values change from run to run (times, rates, machines, places).
VOLATILE = ('time', 'seconds', 'wall', 'rate', 'per_s', 'per_second', 'date', 'path', 'dir', 'folder', 'bag',
            'run', 'file', 'host', 'version', 'created', 'elapsed', 'speed', 'jitter', 'latency', 'commit',
            'out', 'report', 'yaml', 'urdf', 'motion', 'mjcf', 'command')

EPISODES = {
    'ct-default': ['--controller', 'computed_torque', '--omega', '15'],
    'pd-delay0-tau-limited': ['--controller', 'pd_gravity', '--omega', '10', '--delay', '0', '--tau', '0.1',
                              '--limited', '--trajectory', '2'],
    'ct-friction-mass': ['--controller', 'computed_torque', '--kp', '400', '300', '200', '--kv', '40', '30', '20',
                         '--viscous-friction', '0.5', '0.2', '0.1', '--mass-scale', '1.1', '1.0', '0.9',
                         '--period', '0.02', '--duration', '1.5'],
    'panda-ct': ['--controller', 'computed_torque', '--omega', '12', '--urdf', str(ARMS / 'panda' / 'panda.urdf'),
                 '--motion', str(ARMS / 'panda' / 'panda-motion.yaml')],
    'scara-pd': ['--controller', 'pd_gravity', '--omega', '20', '--urdf', str(ARMS / 'scara' / 'scara.urdf'),
                 '--motion', str(ARMS / 'scara' / 'scara-motion.yaml'), '--delay', '2'],
    'panda-mujoco': ['--controller', 'computed_torque', '--omega', '12', '--urdf', str(ARMS / 'panda' / 'panda.urdf'),
                     '--motion', str(ROBOTS / 'panda' / 'panda-motion.yaml'),
                     '--mjcf', str(ROBOTS / 'panda' / 'panda.xml')],
}

TUNES = {
    'ct-I1': ['--controller', 'computed_torque', '--index', 'I1'],
    'pd-I-nm': ['--controller', 'pd_gravity', '--index', 'I', '--delay', '0', '--method', 'nelder-mead',
                '--budget', '3000'],
}


def _ddarm(arguments: list[str], cwd: Path) -> str:
    environment = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    done = subprocess.run([sys.executable, '-m', 'ddarm.cli.main', *arguments], cwd=cwd, env=environment,
                          capture_output=True, text=True, timeout=900)
    if done.returncode != 0:
        raise SystemExit(f'ddarm {" ".join(arguments)}: rc {done.returncode}\n{done.stderr[-2000:]}')
    return done.stdout


def _json_lines(text: str) -> list:
    return [json.loads(line) for line in text.splitlines() if line.strip().startswith('{')]


def snapshot(out: Path, quick: bool) -> None:
    numbers = {}
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        for name, arguments in EPISODES.items():
            numbers[f'episode {name}'] = _json_lines(_ddarm(['episode', *arguments, '--json'], work))
        bag = work / 'bag'
        numbers['episode --ros'] = _json_lines(_ddarm(['episode', *EPISODES['pd-delay0-tau-limited'], '--ros',
                                                       '--bag', str(bag), '--json'], work))
        numbers['score'] = _json_lines(_ddarm(['score', str(bag), '--json'], work))
        for name, arguments in TUNES.items():
            numbers[f'tune {name}'] = _json_lines(_ddarm(['tune', *arguments, '--runs', str(work / 'runs'),
                                                          '--json'], work))
        ur5 = ['--urdf', str(ARMS / 'ur5' / 'ur5.urdf'), '--motion', str(ROBOTS / 'ur5' / 'ur5-motion.yaml')]
        numbers['omega'] = _json_lines(_ddarm(['omega', '--controller', 'computed_torque', *ur5, '--max-error', '0.5',
                                               '--mass-error', *['0.1'] * 6, '--runs', str(work / 'runs'),
                                               '--out', str(work / 'ur5.yaml'),
                                               '--json'], work))
        numbers['validate'] = _json_lines(_ddarm(['validate', '--gains', str(work / 'ur5.yaml'), '--mjcf',
                                                  str(ROBOTS / 'ur5' / 'ur5-payload.xml'), '--runs',
                                                  str(work / 'runs'), '--json'], work))
        numbers['stability'] = _json_lines(_ddarm(['stability', '--controller', 'pd_gravity', '--json'], work))
        if not quick:
            _ddarm(['reproduce', '--out', str(work / 'paper')], work)
            numbers['reproduce'] = json.loads((work / 'paper' / 'results.json').read_text())
    out.write_text(json.dumps(numbers, indent=1))
    print(f'{out}: {len(list(_leaves(numbers)))} numbers')


def _volatile(key: str) -> bool:
    return any(word in key.lower() for word in VOLATILE)


def _leaves(value, path=()):
    if isinstance(value, dict):
        for key, item in value.items():
            if not _volatile(str(key)):
                yield from _leaves(item, (*path, str(key)))
    elif isinstance(value, list):
        for position, item in enumerate(value):
            yield from _leaves(item, (*path, str(position)))
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield '/'.join(path), float(value)
    elif isinstance(value, (str, bool)) or value is None:
        yield '/'.join(path), value


def compare(before: Path, after: Path, tolerance: float) -> int:
    old_sections, new_sections = json.loads(before.read_text()), json.loads(after.read_text())
    common = [name for name in old_sections if name in new_sections]  # a --quick snapshot has no reproduce
    for name in sorted(set(old_sections) ^ set(new_sections)):
        print(f'  in one snapshot only, not compared: {name}')
    old = dict(_leaves({name: old_sections[name] for name in common}))
    new = dict(_leaves({name: new_sections[name] for name in common}))
    gone = sorted(set(old) - set(new))
    added = sorted(set(new) - set(old))
    worst, where, moved = 0.0, '', []
    for key in sorted(set(old) & set(new)):
        a, b = old[key], new[key]
        if isinstance(a, float) and isinstance(b, float):
            if math.isnan(a) and math.isnan(b):
                continue
            change = abs(a - b) / max(abs(a), abs(b), 1e-300) if a != b else 0.0
            if change > worst:
                worst, where = change, key
            if change > tolerance:
                moved.append(f'{key}: {a!r} -> {b!r}')
        elif a != b:
            moved.append(f'{key}: {a!r} -> {b!r}')
    numeric = sum(isinstance(value, float) for value in old.values())
    print(f'{len(old)} values ({numeric} numbers) compared; largest relative change {worst:.3g}'
          + (f' ({where})' if where else ''))
    for line in moved:
        print(f'  moved: {line}')
    for key in gone:
        print(f'  gone: {key}')
    for key in added:
        print(f'  new: {key}')
    return 1 if moved or gone else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest='command', required=True)
    take = commands.add_parser('snapshot')
    take.add_argument('out', type=Path)
    take.add_argument('--quick', action='store_true', help='leave out ddarm reproduce (about a minute)')
    check = commands.add_parser('compare')
    check.add_argument('before', type=Path)
    check.add_argument('after', type=Path)
    check.add_argument('--tolerance', type=float, default=1e-12)
    arguments = parser.parse_args()
    if arguments.command == 'snapshot':
        snapshot(arguments.out, arguments.quick)
    else:
        raise SystemExit(compare(arguments.before, arguments.after, arguments.tolerance))


if __name__ == '__main__':
    main()
