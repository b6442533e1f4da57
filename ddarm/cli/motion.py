"""`ddarm motion`: a waypoint motion file written from a recorded bag's JointTrajectory or /joint_states, or an
excitation motion for identification (--excite)."""

from __future__ import annotations

import argparse
import shlex

from ddarm.cli.arguments import finite, seed, whole_number

# The options of each way to make a motion, by their dests: given with the other way, they are refused.
EXCITE_OPTIONS = ('urdf', 'duration', 'harmonics', 'seed', 'locked', 'point_period')
BAG_OPTIONS = ('topic', 'end')
DEFAULT_HARMONICS = 5
DEFAULT_POINT_PERIOD = 0.02


def command_motion(args: argparse.Namespace) -> int:
    """Write the motion file --out (new) from the bag or, with --excite, an excitation motion; print its path, and
    its points and joints."""
    from ddarm.motion.files import parse_motion
    from ddarm.motion.from_bag import motion_file_from_bag
    from ddarm.motion.programmed import MotionError
    from ddarm.recording.bags import BagError, checked_output_path
    from ddarm.recording.runs import write_new_text

    if args.excite:
        if args.bag is not None:
            raise MotionError(f'a BAG ({args.bag}) with --excite: an excitation motion is made from the URDF, not '
                              'from a bag')
        if given := [option_name(dest) for dest in BAG_OPTIONS if getattr(args, dest) is not None]:
            raise MotionError(f'{given[0]} is an option of a motion from a bag, not of --excite')
    else:
        if given := [option_name(dest) for dest in EXCITE_OPTIONS if getattr(args, dest) is not None]:
            raise MotionError(f'{given[0]} is an option of --excite (an excitation motion), not of a motion from a bag')
        if args.bag is None:
            raise MotionError('no BAG: give a bag to write its motion, or --excite for an excitation motion')
        if args.start is not None and len(args.start) != 1:
            raise MotionError(f'--start of a bag is one time in s, got {len(args.start)} values')

    # Checked before the bag is read, so a long read never ends in a refusal it could have started with: as every
    # output, new, with no '..' and through no symlink.
    try:
        out = checked_output_path(args.out)
    except BagError as error:
        raise MotionError(str(error)) from error
    if not out.absolute().parent.is_dir():
        raise MotionError(f'{out}: no folder {out.parent} to write it in')
    if args.excite:
        excitation = _excitation(args, out)
        text, written = excitation.text, excitation.file
    else:
        text = motion_file_from_bag(args.bag, args.topic, args.joints, None if args.start is None else args.start[0],
                                    args.end)
        written = parse_motion(text, str(out))
    write_new_text(out, text)
    print(f'{out}: {len(written.motion.times)} points of {len(written.joint_names)} joints '
          f'({", ".join(written.joint_names)}), {written.motion.duration!r} s')
    if args.excite:
        from ddarm.motion.excitation import SAMPLES

        print(f'condition number of the base regressor: {excitation.condition:.8g} ({excitation.base} base parameters '
              f'of {excitation.parameters}; samples {SAMPLES}); at the seeded random start: '
              f'{excitation.start_condition:.8g}')
    return 0


def _excitation(args: argparse.Namespace, out):
    """The excitation motion the --excite options describe, checked (ddarm.motion.excitation)."""
    from ddarm.motion.excitation import excitation_motion
    from ddarm.motion.programmed import MotionError
    from ddarm.physics.arm import load_arm, urdf_joints

    for dest in ('urdf', 'joints', 'duration'):
        if getattr(args, dest) is None:
            raise MotionError(f'--excite needs {option_name(dest)}')
    harmonics = DEFAULT_HARMONICS if args.harmonics is None else args.harmonics
    random_seed = 0 if args.seed is None else args.seed
    point_period = DEFAULT_POINT_PERIOD if args.point_period is None else args.point_period
    given = dict(args.locked or ())
    if len(given) != len(args.locked or ()):
        raise MotionError('--locked names a joint more than once')
    arm = load_arm(args.urdf, None, tuple(args.joints), tuple(given.items()))
    # The motion file locks the URDF's other movable joints, each but a mimic one (which follows its joint).
    described = urdf_joints(arm.urdf_path)
    locked = {name: value for name, value in arm.locked if described[name].mimic is None}
    # The command that makes this motion again, every default spelled out; --out left out, so that the same
    # options make the same file wherever it is written.
    command = ['ddarm', 'motion', '--excite', '--urdf', args.urdf, '--joints', *args.joints,
               '--duration', repr(args.duration), '--harmonics', str(harmonics), '--seed', str(random_seed),
               '--point-period', repr(point_period)]
    if args.start is not None:
        command += ['--start', *map(repr, args.start)]
    if given:
        command += ['--locked', *(f'{name}={value!r}' for name, value in given.items())]
    return excitation_motion(arm, args.duration, harmonics, random_seed, args.start, point_period, locked,
                             shlex.join(command), str(out))


def option_name(dest: str) -> str:
    return '--' + dest.replace('_', '-')


def joint_position(text: str) -> tuple[str, float]:
    """An argparse type: NAME=VALUE, a joint and its position (rad or m)."""
    name, equals, value = text.rpartition('=')
    if not (equals and name):
        raise argparse.ArgumentTypeError(f'{text!r} is not NAME=VALUE')
    return name, finite(value)


def add_motion_parser(commands) -> None:
    """Register `ddarm motion` on the `ddarm` command's subparsers."""
    motion = commands.add_parser('motion', help="write a motion file from a recorded bag's JointTrajectory or "
                                                '/joint_states, or an excitation motion for identification (--excite)')
    motion.add_argument('bag', metavar='BAG', nargs='?', help='a rosbag2 folder (mcap or sqlite3)')
    motion.add_argument('--excite', action='store_true',
                        help='an excitation motion for identification instead: a finite Fourier series per joint '
                             "that minimises the base regressor's condition number within the URDF's limits")
    motion.add_argument('--topic', help='a JointTrajectory or JointState topic (default: /joint_states if the bag '
                                        'has it, else its only JointTrajectory topic)')
    motion.add_argument('--joints', nargs='+', metavar='NAME',
                        help="of JointState messages, the joints taken, in this order (default: the first message's); "
                             "with --excite, the joints moved, in the URDF's order (required)")
    motion.add_argument('--start', type=finite, nargs='+', metavar='S',
                        help="of JointState messages, the first used: s after the topic's first, by header stamp; "
                             'with --excite, q0 per joint, where the motion starts and ends at rest (default: the '
                             "middle of each joint's limits)")
    motion.add_argument('--end', type=finite, metavar='S', help='of JointState messages, the last used (likewise)')
    motion.add_argument('--urdf', metavar='FILE', help='with --excite: the arm (required)')
    motion.add_argument('--duration', type=finite, metavar='S', help='with --excite: T, s (required)')
    motion.add_argument('--harmonics', type=whole_number(2, 20, 'harmonics'), metavar='L',
                        help=f'with --excite: harmonics of the series ({DEFAULT_HARMONICS})')
    motion.add_argument('--seed', type=seed, metavar='N', help='with --excite: the random start (0)')
    motion.add_argument('--locked', type=joint_position, nargs='+', metavar='NAME=VALUE',
                        help="with --excite: positions of the URDF's movable joints not moved (default 0)")
    motion.add_argument('--point-period', type=finite, metavar='S',
                        help=f'with --excite: the time between waypoints ({DEFAULT_POINT_PERIOD:g} s, or a little '
                             'less so that the last is at T)')
    motion.add_argument('--out', required=True, metavar='FILE.yaml', help='the motion file written (new)')
    motion.set_defaults(handler=command_motion)
