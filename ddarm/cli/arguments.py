"""The options every `ddarm` command that runs episodes shares, and the EpisodeSpec they define."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from ddarm.control.laws import CONTROLLERS
from ddarm.episodes.spec import (EPISODE_DEFAULTS, PERIOD_RANGE, EpisodeError, EpisodeSpec, arm_joints,
                                 gains_from_omega)
from ddarm.motion.programmed import PAPER_TRAJECTORIES
from ddarm.physics.plant import DEFAULT_SUBSTEPS


def finite(text: str) -> float:
    value = float(text)
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f'{text!r} is not a finite number')
    return value


def number_within(low: float, high: float, unit: str):
    """An argparse type: a number in [low, high], in `unit`."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f'{text!r} is not in [{low:g}, {high:g}] {unit}')
        return value
    return parse


# The sampling period Δ of `ddarm stability`, which builds no episode to refuse it (ddarm.episodes.spec's bound).
period_seconds = number_within(*PERIOD_RANGE, 's')


def seed(text: str) -> int:
    """An argparse type: a NumPy seed, a whole number of 0 or more."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a whole number') from None
    if value < 0:
        raise argparse.ArgumentTypeError(f'{value} is not 0 or more (a NumPy seed)')
    return value


def whole_number(low: int, high: int, unit: str = ''):
    """An argparse type: a whole number in [low, high]; `unit` (e.g. 'samples') says what it counts when refused."""
    noun = f'a whole number of {unit}' if unit else 'a whole number'

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not {noun}') from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f'{value} is not in [{low}, {high}]')
        return value
    return parse


def add_arm_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that name the arm and its motion: --urdf, --model-urdf, and --trajectory or --motion."""
    parser.add_argument('--urdf', metavar='FILE', help="the plant's arm (default: the paper's, config/ddarm.urdf)")
    parser.add_argument('--model-urdf', metavar='FILE',
                        help="the controller's model of the arm, when it differs from the plant (default: --urdf)")
    motion = parser.add_mutually_exclusive_group()
    motion.add_argument('--trajectory', type=int, choices=PAPER_TRAJECTORIES,
                        help="the paper's motion (default 1, without --motion)")
    motion.add_argument('--motion', metavar='FILE.yaml',
                        help='a motion file: the controlled joints and their motion (the others are locked)')


def add_episode_arguments(parser: argparse.ArgumentParser, gains: bool = True) -> None:
    """The options that define an episode (the spec's defaults, §14); `gains` adds --omega / --kp --kv."""
    parser.add_argument('--controller', choices=CONTROLLERS, required=True,
                        help='the law: pd_gravity (PD + gravity, Fig. 1) or computed_torque (Fig. 2)')
    add_arm_arguments(parser)
    parser.add_argument('--duration', type=finite, metavar='T',
                        help="T in s (default: the motion's; the paper's is 1); a bang-bang motion is stretched to "
                             "T, waypoints are held after their last point")
    parser.add_argument('--period', type=finite, default=EPISODE_DEFAULTS['period'], metavar='DT',
                        help=f'sampling period Δ in s, within [{PERIOD_RANGE[0]:g}, {PERIOD_RANGE[1]:g}] '
                             f"(default {EPISODE_DEFAULTS['period']:g})")
    if gains:
        choice = parser.add_mutually_exclusive_group(required=True)
        choice.add_argument('--omega', type=finite, metavar='W',
                            help='gains from the ω rule of section 2 (PD + gravity: m_ii at q_f)')
        choice.add_argument('--kp', type=finite, nargs='+', metavar='K', help='K_p diagonal, one per joint')
        parser.add_argument('--kv', type=finite, nargs='+', metavar='V', help='K_v diagonal, with --kp')
    parser.add_argument('--delay', type=int, default=EPISODE_DEFAULTS['delay'], metavar='D',
                        help=f"compute delay in samples (default {EPISODE_DEFAULTS['delay']}; the paper uses 0 for "
                             'PD + gravity)')
    parser.add_argument('--tau', type=finite, default=EPISODE_DEFAULTS['tau'],
                        help='initial velocity disturbance (3.1): q̇(0) = -q̇^d(τ) '
                             f"(default {EPISODE_DEFAULTS['tau']:g})")
    add_torque_limit_arguments(parser, "the plant URDF's <limit effort> of each joint")
    parser.add_argument('--external-torque', type=finite, nargs='+', metavar='PZ',
                        help='constant external joint torques P^z in N m')
    parser.add_argument('--viscous-friction', type=finite, nargs='+', metavar='B')
    parser.add_argument('--coulomb-friction', type=finite, nargs='+', metavar='C')
    parser.add_argument('--mass-scale', type=finite, nargs='+', metavar='S',
                        help="plant link mass / model link mass, per link (default 1: model = plant)")
    parser.add_argument('--substeps', type=int, default=DEFAULT_SUBSTEPS,
                        help=f'RK4 steps per sampling period (default {DEFAULT_SUBSTEPS})')


def joint_pair(text: str) -> tuple[str, str]:
    """An argparse type: URDF_JOINT=MJCF_JOINT."""
    ours, equals, theirs = text.partition('=')
    if not (equals and ours and theirs):
        raise argparse.ArgumentTypeError(f'{text!r} is not URDF_JOINT=MJCF_JOINT')
    return ours, theirs


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """--mjcf: a MuJoCo robot as the plant, and --joint-map for its joints' names."""
    parser.add_argument('--mjcf', metavar='FILE',
                        help="the plant is this MuJoCo robot (an MJCF file, or a URDF MuJoCo compiles), its joints "
                             "the motion's, the law's model the URDF's (pip install 'ddarm[mujoco]')")
    parser.add_argument('--joint-map', type=joint_pair, nargs='+', metavar='URDF_JOINT=MJCF_JOINT',
                        help="the MJCF's name of each joint whose name differs from the URDF's")


def robot_joints(args: argparse.Namespace, joint_names: tuple[str, ...]) -> tuple[str, ...] | None:
    """The MJCF's name of each controlled joint that --joint-map gives (None: no --joint-map)."""
    if not getattr(args, 'joint_map', None):
        return None
    if not getattr(args, 'mjcf', None):
        raise EpisodeError('--joint-map names the joints of an MJCF robot: give it with --mjcf')
    mapping = {}
    for ours, theirs in args.joint_map:
        if ours in mapping:
            raise EpisodeError(f'--joint-map maps joint {ours!r} twice')
        mapping[ours] = theirs
    unknown = sorted(set(mapping) - set(joint_names))
    if unknown:
        raise EpisodeError(f'--joint-map names {unknown}, which are not joints the motion controls '
                           f'{list(joint_names)}')
    return tuple(mapping.get(name, name) for name in joint_names)


def add_torque_limit_arguments(parser: argparse.ArgumentParser, urdf_limits_help: str) -> None:
    """ddarm's actuator limit, one of three ways (torque_limit reads them)."""
    limits = parser.add_mutually_exclusive_group()
    limits.add_argument('--limited', action='store_true',
                        help="the paper's torque limits: 2 x max nominal torque per joint")
    limits.add_argument('--urdf-limits', action='store_true', help=urdf_limits_help)
    limits.add_argument('--torque-limit', type=finite, nargs='+', metavar='N',
                        help='torque limits in N m, one per joint')


def torque_limit(args: argparse.Namespace):
    """The spec's torque_limit the options of add_torque_limit_arguments give."""
    if args.torque_limit is not None:
        return args.torque_limit
    return 'paper' if args.limited else 'urdf' if args.urdf_limits else 'none'


def absolute_path(text: str | None) -> str | None:
    return None if text is None else str(Path(text).expanduser().absolute())


def episode_spec(args: argparse.Namespace) -> EpisodeSpec:
    """The episode the options define; gains from --omega (the ω rule) or --kp/--kv; a template (no gains) for the
    commands that choose the gains themselves."""
    spec = EpisodeSpec(
        controller=args.controller, trajectory=args.trajectory or 1, duration=args.duration,
        period=args.period, delay=args.delay, tau=args.tau, torque_limit=torque_limit(args),
        external_torque=args.external_torque, viscous_friction=args.viscous_friction,
        coulomb_friction=args.coulomb_friction, mass_scale=args.mass_scale, substeps=args.substeps,
        urdf=absolute_path(args.urdf), model_urdf=absolute_path(args.model_urdf), motion=absolute_path(args.motion))
    if getattr(args, 'mjcf', None) or getattr(args, 'joint_map', None):
        spec = dataclasses.replace(spec, mjcf=absolute_path(args.mjcf),
                                   mjcf_joints=robot_joints(args, arm_joints(spec)[0]))
    if not hasattr(args, 'omega'):
        return spec
    if args.omega is not None:
        if args.kv is not None:
            raise EpisodeError('--kv goes with --kp; --omega sets both gains from the ω rule')
        kp, kv = gains_from_omega(spec, args.omega)
    else:
        if args.kv is None:
            raise EpisodeError('--kp needs --kv')
        kp, kv = args.kp, args.kv
    return dataclasses.replace(spec, kp=kp, kv=kv)


def output_path(text: str) -> str:
    """An argparse type: a path ddarm writes at (its folder may exist): not empty, which would be the current folder
    or a silent default. Its parts that ddarm creates are checked where it is written (checked_output_path)."""
    if not text:
        raise argparse.ArgumentTypeError('an empty path: give the path to write')
    return text


def new_output_path(text: str) -> str:
    """An argparse type: the path of a new file or folder ddarm makes, whose last part is a name it creates: not
    empty, and a name (ddarm.recording.bags.output_name_problem: no control character)."""
    from ddarm.recording.bags import output_name_problem

    name = Path(output_path(text)).name  # '' for / or .: refused where it is written, as a path that exists
    problem = output_name_problem(name) if name else None
    if problem is not None:
        raise argparse.ArgumentTypeError(problem)
    return text


def new_output_name(text: str) -> str:
    """An argparse type: the name of a file or folder ddarm makes (output_name_problem: not empty, no control
    character)."""
    from ddarm.recording.bags import output_name_problem

    problem = output_name_problem(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(problem)
    return text


def add_run_arguments(parser: argparse.ArgumentParser, command: str = '<command>') -> None:
    """The run folder a command writes (--runs, --run) and its --json."""
    parser.add_argument('--runs', default='runs', type=output_path, help='folder of run folders (runs)')
    parser.add_argument('--run', metavar='NAME', type=new_output_name,
                        help=f'run folder name (default: {command}-<law>-<time>)')
    parser.add_argument('--json', action='store_true', help='print one JSON object')


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser)
    parser.add_argument('--out', metavar='FILE.yaml', type=new_output_path,
                        help='also write the controller YAML here (new file)')
