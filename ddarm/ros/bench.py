"""`ddarm bench --ros`: lockstep samples per second through the graph against the bare DDS round trip, side by side.

Rounds alternate the two measurements, so that a machine whose load changes (these are noisy)
moves both; each round's ratio compares runs made seconds apart.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from ddarm.episodes.bench import REFERENCE
from ddarm.episodes.spec import check_episode

# A lockstep episode this long (simulated s, at Δ = 0.01 s) and this many round trips make each measurement.
LOCKSTEP_DURATION = 20.0
ROUND_TRIPS = 2000


def lockstep_and_round_trips(rounds: int = 3, duration: float = LOCKSTEP_DURATION,
                             round_trips: int = ROUND_TRIPS) -> dict:
    """`rounds` alternations of one recorded lockstep episode of the reference case (`duration` s) and
    `round_trips` bare round trips (`ddarm.ros.round_trip`) of JointState messages and of their CDR bytes; each
    round's figures and the median ratios.

    `ratio` is to the round trip of messages (the issue's ceiling); `serialized_ratio` to that of bytes, which
    takes rclpy's message conversion out of the ceiling too, as the nodes take it out of their loop.

    Lockstep samples/s is the plant's own count over its wall time from sample 0 to the last
    (what DDS carries); `episode_samples_per_s` divides by the whole episode as the driver ran it
    (configuration, reset and the last messages included).
    """
    from ddarm.ros.round_trip import round_trips_in_process
    from ddarm.ros.session import GraphSession, record_and_score

    spec = dataclasses.replace(REFERENCE, duration=duration)
    plan = check_episode(spec)
    figures = []
    with tempfile.TemporaryDirectory(prefix='ddarm-bench-') as folder, GraphSession(Path(folder) / 'nodes') as session:
        session.ready(spec)
        session.run(spec, plan)  # the nodes' first episode loads their compiled code: not timed
        for round_number in range(rounds):
            bare = round_trips_in_process(round_trips)
            serialized = round_trips_in_process(round_trips, serialized=True)
            started = time.perf_counter()
            result, score = record_and_score(session, spec, Path(folder) / f'lockstep-{round_number}')
            episode_s = time.perf_counter() - started
            report = result.plant_report
            samples = int(report['sample'])
            lockstep = samples / float(report['wall_time_s'])
            figures.append({'round_trips_per_s': bare['round_trips_per_s'],
                            'round_trip_p50_ms': bare['latency_p50_ms'],
                            'round_trip_p99_ms': bare['latency_p99_ms'],
                            'serialized_round_trips_per_s': serialized['round_trips_per_s'],
                            'serialized_round_trip_p50_ms': serialized['latency_p50_ms'],
                            'lockstep_samples_per_s': lockstep,
                            'episode_samples_per_s': samples / episode_s,
                            'ratio': lockstep / bare['round_trips_per_s'],
                            'serialized_ratio': lockstep / serialized['round_trips_per_s'],
                            'bag_I': score['I']})
    return {'case': 'reference case (computed torque, ω = 15 rule), recorded in lockstep',
            'lockstep_duration_s': duration, 'samples': int(round(duration / spec.period)),
            'round_trips': round_trips, 'rounds': figures,
            'median_ratio': float(np.median([round_figures['ratio'] for round_figures in figures])),
            'median_serialized_ratio': float(np.median([round_figures['serialized_ratio']
                                                        for round_figures in figures]))}
