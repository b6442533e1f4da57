"""`ddarm stability`: the exact stability boundary ωΔ* of the sampled loop, against the delay d and the damping ζ."""

from __future__ import annotations

import argparse

import numpy as np

from ddarm.cli.arguments import absolute_path, add_arm_arguments, period_seconds, whole_number
from ddarm.cli.output import format_vector, print_json
from ddarm.control.laws import MAX_DELAY
from ddarm.control.stability import ZETA_RANGE, StabilityError, modal_boundary_omega_delta, modal_gains
from ddarm.episodes.spec import PERIOD_RANGE

ARM_OPTIONS = ('urdf', 'model_urdf', 'trajectory', 'motion')


# An argparse type: a compute delay the controllers accept.
_delay = whole_number(0, MAX_DELAY, 'samples')


def _positive(text: str) -> float:
    """An argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f'{text!r} is not finite and positive')
    return value


def _pd_gravity_modes(args: argparse.Namespace) -> tuple[list[str], np.ndarray]:
    """The controlled joints and μ_k of M(q_f)⁻¹ diag(m̂_ii): the plant's inertia, the model's m_ii (the ω rule's),
    at the goal q_f of the motion."""
    from ddarm.episodes.spec import EpisodeSpec, episode_motion, model_arm, plant_arm

    spec = EpisodeSpec(controller='pd_gravity', trajectory=args.trajectory or 1,
                       urdf=absolute_path(args.urdf), model_urdf=absolute_path(args.model_urdf),
                       motion=absolute_path(args.motion))
    goal = episode_motion(spec).qf
    plant, model = plant_arm(spec), model_arm(spec)
    for arm in (plant, model):
        arm.check_inertia(goal, 'the goal q_f')
    return list(plant.joint_names), modal_gains(plant.mass_matrix(goal), np.diag(model.mass_matrix(goal)))


def command_stability(args: argparse.Namespace) -> int:
    if args.controller == 'pd_gravity':
        joint_names, modes = _pd_gravity_modes(args)
    else:
        given = [name for name in ARM_OPTIONS if getattr(args, name) is not None]
        if given:
            raise StabilityError(f"--{given[0].replace('_', '-')} describes the arm of --controller pd_gravity: "
                                 'computed torque with an exact model is the same double integrator on any arm')
        joint_names, modes = None, np.ones(1)
    boundaries = []
    for delay in args.delay:
        for zeta in args.zeta:
            entry = {'delay': delay, 'zeta': zeta, 'omega_delta': modal_boundary_omega_delta(modes, delay, zeta)}
            if args.period is not None:
                entry['omega'] = entry['omega_delta'] / args.period
            boundaries.append(entry)
    if args.json:
        report = {'controller': args.controller, 'boundaries': boundaries}
        if args.period is not None:
            report['period'] = args.period
        if joint_names is not None:
            report.update(joint_names=joint_names, modes=modes.tolist())
        print_json(report)
        return 0
    unit = 'ωΔ*' if args.period is None else f'ωΔ* (ω* in rad/s at Δ = {args.period:g} s)'
    print(f'ddarm stability: {args.controller}, zero-order hold, delay d samples, ω rule with damping ζ: {unit}')
    if joint_names is not None:
        print(f"  linearised at the goal q_f: modes μ of M(q_f)⁻¹ diag(m_ii) ({', '.join(joint_names)}) = "
              f'{format_vector(modes)}')
    header = [f'ζ = {zeta:g}' for zeta in args.zeta]
    cells = [f"{entry['omega_delta']:.6g}" + ('' if args.period is None else f" ({entry['omega']:.4g})")
             for entry in boundaries]
    labels = [f'  d = {delay}' for delay in args.delay]
    # Right-aligned columns with at least two spaces between them, whatever the widest number.
    width = max(len(text) for text in header + cells) + 2
    label_width = max(len(label) for label in labels)
    print(' ' * label_width + ''.join(f'{text:>{width}}' for text in header))
    for row, label in enumerate(labels):
        print(f'{label:<{label_width}}'
              + ''.join(f'{cell:>{width}}' for cell in cells[row * len(args.zeta):(row + 1) * len(args.zeta)]))
    return 0


def add_stability_parser(commands) -> None:
    """Register `ddarm stability` on the `ddarm` command's subparsers."""
    stability = commands.add_parser('stability', help='the exact stability boundary ωΔ* of the sampled loop '
                                                     'against the delay and the damping')
    stability.add_argument('--delay', type=_delay, nargs='+', default=[0, 1, 2], metavar='D',
                           help='compute delays in samples (0 1 2)')
    stability.add_argument('--zeta', type=_positive, nargs='+', default=[1.0], metavar='Z',
                           help='damping ζ of the ω rule, k_v = 2ζω (1, as the ω rules use); each mode\'s ζ√μ_k within '
                                f'[{ZETA_RANGE[0]:g}, {ZETA_RANGE[1]:g}], the range its boundary is computed within')
    stability.add_argument('--controller', choices=('computed_torque', 'pd_gravity'), default='computed_torque',
                           help='computed torque with an exact model, or PD + gravity linearised at the goal q_f '
                                "with the arm's inertia (computed_torque)")
    stability.add_argument('--period', type=period_seconds, metavar='DT',
                           help=f'also ω* = ωΔ*/Δ for this Δ in s, within '
                                f'[{PERIOD_RANGE[0]:g}, {PERIOD_RANGE[1]:g}]')
    add_arm_arguments(stability)  # PD + gravity's arm: linearised at the motion's goal q_f, m_ii from the model
    stability.add_argument('--json', action='store_true', help='print one JSON object')
    stability.set_defaults(handler=command_stability)
