"""How `ddarm` prints an episode's indices for a person."""

from __future__ import annotations


def format_vector(values) -> str:
    return '(' + ', '.join(f'{value:.6g}' for value in values) + ')'


def print_summary(summary: dict) -> None:
    spec = summary['spec']
    print(f"{spec['controller']}  trajectory {spec['trajectory']}  T = {spec['duration']} s  "
          f"Δ = {spec['period']} s  delay {spec['delay']}  τ = {spec['tau']} s  "
          f"torque limit {spec['torque_limit']}")
    print(f"  kp = {format_vector(spec['kp'])}  kv = {format_vector(spec['kv'])}")
    print(f"  I1 (2.5) = {summary['I1']:.6g}   I2 = {summary['I2']:.6g}   I (3.2) = {summary['I']:.6g}")
    if summary['diverged']:
        print(f"  DIVERGED at sample {summary['diverged_at_sample']}: indices cover the "
              f"{summary['samples_scored']} samples before it")
    if summary['max_abs_error_deg'] is not None:
        print(f"  max |e| (deg) = {format_vector(summary['max_abs_error_deg'])}   "
              f"max |P| (N m) = {format_vector(summary['max_abs_torque'])}")
    for warning in summary.get('warnings', []):
        print(f'  WARNING: {warning}')
