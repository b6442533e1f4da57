"""`ddarm omega`: section 2's procedure, the ω rule's ω from permitted errors and torques."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys

import numpy as np

from ddarm.cli.arguments import episode_spec
from ddarm.cli.output import format_vector
from ddarm.episodes.spec import EpisodeError, check_episode


def command_omega(args: argparse.Namespace) -> int:
    from ddarm.tuning.outputs import check_outputs, finish_omega, run_folder
    from ddarm.tuning.procedures import omega_procedure

    if args.mass_error is not None and args.mass_scale is not None:
        raise EpisodeError('give --mass-error or --mass-scale, not both')
    if args.disturbance is not None and args.external_torque is not None:
        raise EpisodeError('give --disturbance or --external-torque, not both')
    check_outputs(args.out, args.runs, args.run)
    spec = episode_spec(args)
    dof = len(spec.kp)
    for name, values in (('--max-error', args.max_error), ('--disturbance', args.disturbance),
                         ('--mass-error', args.mass_error)):
        if values is not None and len(values) != dof and not (name == '--max-error' and len(values) == 1):
            raise EpisodeError(f'{name} needs {"one value or " if name == "--max-error" else ""}{dof} values '
                               f'(one per joint), got {len(values)}')
    if args.mass_error is not None:
        spec = dataclasses.replace(spec, mass_scale=tuple(1.0 + e for e in args.mass_error))
    if args.disturbance is not None:
        spec = dataclasses.replace(spec, external_torque=tuple(args.disturbance))
    plan = check_episode(spec)
    for warning in plan.warnings:
        print(f'ddarm omega: WARNING: {warning}', file=sys.stderr)
    # Degrees for a revolute joint, millimetres for a prismatic one: both to SI.
    prismatic = np.array(plan.prismatic, dtype=bool)
    permitted = np.where(prismatic, np.asarray(args.max_error) * 1e-3, np.radians(args.max_error))
    choice = omega_procedure(spec, permitted, args.torque_factor, args.omega_step, args.omega_max)
    with run_folder('omega', args.controller, args.runs, args.run, shlex.join(['ddarm', *args.argv])) as run:
        report = finish_omega(run, spec, plan, choice, args.out)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"{spec.controller}: ω_min = {choice.omega_min:.6g} (steady-state errors at ω_min, deg or mm: "
          f"{format_vector(report['steady_state_error_at_omega_min_deg'])})")
    for step in choice.steps:
        print(f'  ω = {step.omega:8.4g}  max |P| / limit = {step.max_torque_ratio_to_limit:.3f}  '
              f'max |P| / max |P_nom| = {step.max_torque_ratio_to_nominal:.3f}  '
              f"{'diverged ' if step.diverged else ''}{'accepted' if step.accepted else 'rejected'}")
    if choice.omega is None:
        print('  no ω from ω_min up meets the torque conditions')
    else:
        indices = report['indices']
        print(f"  chosen ω = {choice.omega:.6g}: kp = {format_vector(choice.kp)}  kv = {format_vector(choice.kv)}")
        print(f"  I1 (2.5) = {indices['I1']:.6g}   I2 = {indices['I2']:.6g}   I (3.2) = {indices['I']:.6g}")
        print(f"  gains written to {', '.join(report['gains_files'])}")
    return 0
