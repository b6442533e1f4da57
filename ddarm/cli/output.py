"""How `ddarm` prints an episode's indices for a person."""

from __future__ import annotations

import contextlib
import sys

from ddarm.reporting.text import TerminalStream
from ddarm.strict_json import json_text


@contextlib.contextmanager
def terminal_streams():
    """sys.stdout and sys.stderr as TerminalStreams within the block; stderr's carries messages only."""
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = TerminalStream(sys.stdout), TerminalStream(sys.stderr, messages=True)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = streams


def print_json(report) -> None:
    print(json_text(report))


def format_vector(values) -> str:
    return '(' + ', '.join('-' if value is None else f'{value:.6g}' for value in values) + ')'


def print_summary(summary: dict) -> None:
    spec = summary['spec']
    motion = spec.get('motion') or f"trajectory {spec['trajectory']}"
    print(f"{spec['controller']}  {motion}  T = {spec['duration']} s  "
          f"Δ = {spec['period']} s  delay {spec['delay']}  τ = {spec['tau']} s  "
          f"torque limit {spec['torque_limit']}")
    if spec.get('urdf') or spec.get('model_urdf'):
        print(f"  arm {spec.get('urdf') or 'config/ddarm.urdf'}"
              + (f"  model {spec['model_urdf']}" if spec.get('model_urdf') else ''))
    if summary.get('robot'):
        robot = summary['robot']
        print(f"  robot {robot['mjcf']} ({robot['engine']}, {robot['integrator']}, {robot['steps_per_period']} steps "
              f"of {robot['timestep']:g} s per period, torques through {robot['torque_through']})")
    print(f"  joints {', '.join(summary.get('joint_names', []))}"
          + (f"; locked {', '.join(f'{name} = {value:g}' for name, value in summary['locked_joints'].items())}"
             if summary.get('locked_joints') else ''))
    print(f"  kp = {format_vector(spec['kp'])}  kv = {format_vector(spec['kv'])}")
    print(f"  I1 (2.5) = {summary['I1']:.6g}   I2 = {summary['I2']:.6g}   I (3.2) = {summary['I']:.6g}")
    if summary['diverged']:
        print(f"  DIVERGED at sample {summary['diverged_at']}: indices cover the "
              f"{summary['samples_scored']} samples before it")
    if summary['max_abs_error_deg'] is not None:
        print(f"  max |e| (deg) = {format_vector(summary['max_abs_error_deg'])}   "
              f"max |P| (N m) = {format_vector(summary['max_abs_torque'])}")
    if summary.get('saturated_joints'):
        print(f"  at their torque limit: {', '.join(summary['saturated_joints'])}")
    for warning in summary.get('warnings', []):
        print(f'  WARNING: {warning}')
