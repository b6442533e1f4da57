"""`ddarm omega`: section 2's procedure, the ω rule's ω from permitted errors and torques."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys

import numpy as np

from ddarm.cli.arguments import episode_spec
from ddarm.cli.output import format_vector, print_json
from ddarm.episodes.spec import EpisodeError, arm_joints, check_episode, loop_stability_warnings
from ddarm.physics.plant import DEFAULT_MAX_POSITION


def command_omega(args: argparse.Namespace) -> int:
    from ddarm.tuning.outputs import check_outputs, finish_omega, run_folder
    from ddarm.tuning.procedures import omega_procedure

    if args.mass_error is not None and args.mass_scale is not None:
        raise EpisodeError('give --mass-error or --mass-scale, not both')
    if args.disturbance is not None and args.external_torque is not None:
        raise EpisodeError('give --disturbance or --external-torque, not both')
    check_outputs(args.out, args.runs, args.run)
    spec = episode_spec(args)
    dof = len(arm_joints(spec)[0])
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
    check_permitted_errors(args.max_error, prismatic, plan.joint_names)
    permitted = np.where(prismatic, np.asarray(args.max_error) * 1e-3, np.radians(args.max_error))
    choice = omega_procedure(spec, permitted, args.torque_factor, args.omega_step, args.omega_max)
    stability_warnings = () if choice.omega is None else tuple(loop_stability_warnings(
        spec.with_gains(choice.kp, choice.kv),
        f'the gains of the chosen ω = {choice.omega:.6g}'))
    with run_folder('omega', args.controller, args.runs, args.run, shlex.join(['ddarm', *args.argv])) as run:
        report = finish_omega(run, spec, plan, choice, args.out, (*plan.warnings, *stability_warnings))
    for warning in stability_warnings:
        print(f'ddarm omega: WARNING: {warning}', file=sys.stderr)
    if args.json:
        print_json(report)
    else:
        print_choice(spec, choice, report)
    if choice.omega is None:
        print(f'ddarm omega: {no_omega_reason(choice, args.torque_factor)}: no gains written'
              + (f', {args.out} not written' if args.out else '') + f"; the steps are in {report['run']}",
              file=sys.stderr)
        return 1
    return 0


def check_permitted_errors(max_error, prismatic: np.ndarray, joints) -> None:
    """--max-error: each positive and within the plant's bound on a position (100 rad, 100 m), beyond which the
    episode counts as diverged, so no larger error is a requirement; EpisodeError naming the joint, in the user's
    units (deg or mm), otherwise."""
    given = np.broadcast_to(np.asarray(max_error, dtype=float), prismatic.shape)
    bound = np.where(prismatic, DEFAULT_MAX_POSITION * 1e3, np.degrees(DEFAULT_MAX_POSITION))
    for joint, value, largest, linear in zip(joints, given, bound, prismatic):
        if not 0 < value <= largest:
            unit = 'mm' if linear else 'deg'
            raise EpisodeError(f'--max-error for {joint}: {value:g} {unit}, not within (0, {largest:g}] {unit} (the '
                               "plant's bound on a position, beyond which an episode counts as diverged)")


def no_omega_reason(choice, torque_factor: float) -> str:
    """Why the raising step kept no ω: what its first step, at ω_min (or one step), broke."""
    first = choice.steps[0]
    broken = (['it diverged'] if first.diverged else []) + (
        [f'max |P| / limit = {first.max_torque_ratio_to_limit:.3g} > 1'] if first.max_torque_ratio_to_limit > 1
        else []) + ([f'max |P| / max |P_nom| = {first.max_torque_ratio_to_nominal:.3g} > the torque factor '
                     f'{torque_factor:g}'] if first.max_torque_ratio_to_nominal > torque_factor else [])
    return f"no ω meets the torque conditions: at the first, ω = {first.omega:.6g}, {' and '.join(broken)}"


def print_choice(spec, choice, report: dict) -> None:
    print(f"{spec.controller}: ω_min = {choice.omega_min:.6g} (steady-state errors at ω_min, deg or mm: "
          f"{format_vector(report['steady_state_error_at_omega_min_deg'])})")
    for step in choice.steps:
        print(f'  ω = {step.omega:8.4g}  max |P| / limit = {step.max_torque_ratio_to_limit:.3f}  '
              f'max |P| / max |P_nom| = {step.max_torque_ratio_to_nominal:.3f}  '
              f"{'diverged ' if step.diverged else ''}{'accepted' if step.accepted else 'rejected'}")
    if choice.omega is not None:
        indices = report['indices']
        print(f"  chosen ω = {choice.omega:.6g}: kp = {format_vector(choice.kp)}  kv = {format_vector(choice.kv)}")
        print(f"  I1 (2.5) = {indices['I1']:.6g}   I2 = {indices['I2']:.6g}   I (3.2) = {indices['I']:.6g}")
        print(f"  gains written to {', '.join(report['gains_files'])}")
