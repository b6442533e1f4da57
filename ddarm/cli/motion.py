"""`ddarm motion`: a waypoint motion file written from a recorded bag's JointTrajectory or /joint_states."""

from __future__ import annotations

import argparse

from ddarm.cli.arguments import finite


def command_motion(args: argparse.Namespace) -> int:
    """Write the motion file --out (new) from the bag; print its path, and its points and joints."""
    from ddarm.motion.files import parse_motion
    from ddarm.motion.from_bag import motion_file_from_bag
    from ddarm.motion.programmed import MotionError
    from ddarm.recording.bags import BagError, checked_output_path
    from ddarm.recording.runs import write_new_text

    # Checked before the bag is read, so a long read never ends in a refusal it could have started with: as every
    # output, new, with no '..' and through no symlink.
    try:
        out = checked_output_path(args.out)
    except BagError as error:
        raise MotionError(str(error)) from error
    if not out.absolute().parent.is_dir():
        raise MotionError(f'{out}: no folder {out.parent} to write it in')
    text = motion_file_from_bag(args.bag, args.topic, args.joints, args.start, args.end)
    written = parse_motion(text, str(out))
    write_new_text(out, text)
    print(f'{out}: {len(written.motion.times)} points of {len(written.joint_names)} joints '
          f'({", ".join(written.joint_names)}), {written.motion.duration!r} s')
    return 0


def add_motion_parser(commands) -> None:
    """Register `ddarm motion` on the `ddarm` command's subparsers."""
    motion = commands.add_parser('motion', help="write a motion file from a recorded bag's JointTrajectory or "
                                                '/joint_states')
    motion.add_argument('bag', metavar='BAG', help='a rosbag2 folder (mcap or sqlite3)')
    motion.add_argument('--topic', help='a JointTrajectory or JointState topic (default: /joint_states if the bag '
                                        'has it, else its only JointTrajectory topic)')
    motion.add_argument('--joints', nargs='+', metavar='NAME',
                        help="of JointState messages, the joints taken, in this order (default: the first message's)")
    motion.add_argument('--start', type=finite, metavar='S',
                        help="of JointState messages, the first used: s after the topic's first, by header stamp")
    motion.add_argument('--end', type=finite, metavar='S', help='of JointState messages, the last used (likewise)')
    motion.add_argument('--out', required=True, metavar='FILE.yaml', help='the motion file written (new)')
    motion.set_defaults(handler=command_motion)
