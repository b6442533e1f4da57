"""Benchmark: real-time episodes at 1/Δ with and without the opt-in scheduling, with the cores free and busy.

Each case is one real-time episode through plant and controller processes over DDS (60 s by default);
it prints, per case, the period jitter and deadline misses the plant measured, the scheduling it
reported running with, the load average before and after (other users' work shows there) and the
CPU time a hypervisor stole meanwhile (a VM's pauses, which no scheduling inside it can prevent).
"Busy" is a CPU hog (a Python busy loop) pinned to one core for the whole episode: core 0, the other
core from nodes pinned to core 1, or core 1, the nodes' own. Run from the repository:
    .venv/bin/python bench/realtime_jitter.py [--duration 60] [--cases plain rt-pinned ...]
"""

import argparse
import json
import os
import subprocess
import sys
import time

from ddarm.episodes.spec import EpisodeSpec
from ddarm.ros.node_parameters import SchedulingOptions
from ddarm.ros.session import run_graph_episode

PRIORITY = 50  # ros2_control's default thread_priority for its control loop
NODE_CORE, OTHER_CORE = 1, 0
# name: (scheduling of the nodes, the core a hog runs on or None)
CASES = {
    'plain': (None, None),
    'plain-no-spin': (SchedulingOptions(spin_margin=0.0), None),
    'plain-busy': (None, OTHER_CORE),
    'plain-no-spin-busy': (SchedulingOptions(spin_margin=0.0), OTHER_CORE),
    'rt-pinned': (SchedulingOptions(PRIORITY, (NODE_CORE,)), None),
    'rt-pinned-no-spin': (SchedulingOptions(PRIORITY, (NODE_CORE,), 0.0), None),
    'rt-pinned-no-spin-busy-other-core': (SchedulingOptions(PRIORITY, (NODE_CORE,), 0.0), OTHER_CORE),
    'rt-pinned-busy-other-core': (SchedulingOptions(PRIORITY, (NODE_CORE,)), OTHER_CORE),
    'rt-pinned-busy-same-core': (SchedulingOptions(PRIORITY, (NODE_CORE,)), NODE_CORE),
    'rt-unpinned-busy': (SchedulingOptions(PRIORITY), OTHER_CORE),
    'pinned-busy-same-core': (SchedulingOptions(affinity=(NODE_CORE,)), NODE_CORE),
}
DEFAULT_CASES = ('plain', 'plain-busy', 'rt-pinned', 'rt-pinned-busy-other-core', 'rt-pinned-busy-same-core',
                 'rt-unpinned-busy')
FIGURES = ('period_jitter_p50_ms', 'period_jitter_p99_ms', 'period_jitter_max_ms', 'tick_lateness_p99_ms',
           'tick_lateness_max_ms', 'deadline_misses', 'stale_commands')


def hog(core: int) -> subprocess.Popen:
    """A busy loop on `core` until killed: the other work of a busy machine."""
    process = subprocess.Popen([sys.executable, '-c', 'while True: pass'], start_new_session=True)
    os.sched_setaffinity(process.pid, {core})
    return process


def steal_ms() -> float:
    """The time a hypervisor took from this machine's CPUs so far (/proc/stat's steal), in ms: a VM's pauses."""
    with open('/proc/stat') as stat:
        fields = stat.readline().split()
    return int(fields[8]) * 1000 / os.sysconf('SC_CLK_TCK') if len(fields) > 8 else float('nan')


def run_case(name: str, duration: float, controller: str) -> dict:
    scheduling, hog_core = CASES[name]
    gains = dict(kp=(225.0,) * 3, kv=(30.0,) * 3) if controller == 'computed_torque' else dict(
        kp=(2800.0, 2700.0, 350.0), kv=(560.0, 540.0, 70.0))
    spec = EpisodeSpec(controller=controller, **gains, duration=duration)
    load_before, stolen = os.getloadavg(), steal_ms()
    busy = hog(hog_core) if hog_core is not None else None
    try:
        result = run_graph_episode(spec, realtime=True, timeout=duration * 2 + 120, scheduling=scheduling)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    report = result.plant_report
    return {**{key: float(report[key]) for key in FIGURES}, 'samples': int(report['sample']),
            'sched_policy': report['sched_policy'], 'sched_priority': int(report['sched_priority']),
            'cpu_affinity': json.loads(report['cpu_affinity']), 'spin_margin_s': float(report['spin_margin_s']),
            'hog_core': hog_core, 'load_before': [round(x, 2) for x in load_before],
            'load_after': [round(x, 2) for x in os.getloadavg()], 'steal_ms': steal_ms() - stolen}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=60.0, help='wall seconds per case (60)')
    parser.add_argument('--cases', nargs='+', choices=CASES, default=DEFAULT_CASES)
    parser.add_argument('--controller', default='computed_torque')
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if len(os.sched_getaffinity(0)) < 2:
        raise SystemExit('this benchmark needs two cores: the nodes on one, a hog on the other')
    figures = {'started': time.strftime('%Y-%m-%d %H:%M:%S'), 'cores': sorted(os.sched_getaffinity(0))}
    for name in args.cases:
        figures[name] = run_case(name, args.duration, args.controller)
        print(json.dumps({name: figures[name]}), file=sys.stderr, flush=True)
    print(json.dumps(figures, indent=2))


if __name__ == '__main__':
    main()
