"""The `ddarm` command: the parser, the dispatch to each command's module, and how a command ends.

Every command module turns its arguments into calls of the core and prints; here, a refusal
(DdarmError) or a path the system refuses (OSError) is one line and exit 2, a stop by SIGINT or
SIGTERM exits 128 + the signal, and anything else is a bug whose traceback shows.
"""

from __future__ import annotations

import argparse
import re
import sys

from ddarm.cli.arguments import (add_episode_arguments, add_output_arguments, add_robot_arguments, finite, new_output_path,
                                 seed, whole_number)
from ddarm.cli.episode import command_episode
from ddarm.cli.nodes import command_controller, command_plant, command_robot, command_tuner
from ddarm.cli.omega import command_omega
from ddarm.cli.output import terminal_streams
from ddarm.cli.reproduce import command_reproduce, job_count
from ddarm.cli.score import command_score
from ddarm.cli.tune import add_robust_arguments, command_tune, index_name
from ddarm.cli.validate import add_validate_arguments, command_validate
from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.control.laws import CONTROLLERS
from ddarm.deprecation import one_line_deprecations
from ddarm.errors import DdarmError
from ddarm.realtime import PRIORITY_RANGE, SPIN_MARGIN_RANGE
from ddarm.cli.bench import add_bench_parser
from ddarm.cli.campaign import add_campaign_parser
from ddarm.cli.pareto import add_pareto_parser
from ddarm.cli.stability import add_stability_parser
from ddarm.cli.identify import add_identify_parser
from ddarm.cli.transfer import add_transfer_parser
from ddarm.cli.motion import add_motion_parser
from ddarm.interrupts import Interrupted, skip_cycle_search_at_exit, stop_on_signals
from ddarm.tuning.methods import DEFAULT_METHOD, DEFAULT_TUNE_BUDGET, METHODS


# What a user means as a negative number: a minus before a digit (no ddarm option starts so), -inf or -nan. The
# argument's own type then reads it or refuses it by name (`-1_0` is -10 to float(), `-0x1p3` no number).
_NEGATIVE_NUMBER = re.compile(r'^-(?:\.?\d|inf$|infinity$|nan$)', re.IGNORECASE)


class _OneLineParser(argparse.ArgumentParser):
    """argparse's parser whose refusal is one line, as every other refusal of ddarm's (its usage is in --help),
    and which takes `-1e-3`, `-1_0` and `-inf` as the negative numbers they are: Python 3.11's argparse reads only -1 and
    -0.5 so, and any other as an option (the private attribute is argparse's one hook for it)."""

    def __init__(self, *arguments, **options) -> None:
        super().__init__(*arguments, **options)
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message: str):
        self.exit(2, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog='ddarm', description='Feedback-gain selection for the direct-drive arm (Kowalska).')
    commands = parser.add_subparsers(dest='command', required=True)
    episode = commands.add_parser('episode', help='run one closed-loop episode and print its indices')
    add_episode_arguments(episode)
    episode.add_argument('--json', action='store_true', help='print one JSON object')
    episode.add_argument('--ros', action='store_true',
                         help='run through the ROS 2 graph: plant and controller processes, lockstep over DDS')
    episode.add_argument('--realtime', action='store_true',
                         help='run through the ROS 2 graph on the wall clock (implies --ros)')
    episode.add_argument('--realtime-priority', type=whole_number(1, PRIORITY_RANGE[1]), metavar='N',
                         help='run the plant and controller processes at SCHED_FIFO priority N (needs CAP_SYS_NICE '
                              'or an rtprio limit; refused otherwise)')
    episode.add_argument('--cpu-affinity', type=whole_number(0, 4095), nargs='+', metavar='C',
                         help='pin the plant and controller processes to these cores (ones this process may use)')
    episode.add_argument('--spin-margin', type=finite, metavar='S',
                         help='the plant wakes S seconds before each real-time deadline and spins to it '
                              f'(default 0.001; 0: no spin; less than the period, at most {SPIN_MARGIN_RANGE[1]:g})')
    episode.add_argument('--bag', type=new_output_path, metavar='DIR', help='record the ROS episode as a rosbag2 bag in DIR (new)')
    episode.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap', help='bag storage (mcap)')
    add_robot_arguments(episode)
    episode.set_defaults(handler=command_episode)
    validate = commands.add_parser('validate', help="run a controller YAML on a robot (MJCF) beside ddarm's prediction")
    add_validate_arguments(validate)
    validate.set_defaults(handler=command_validate)
    omega = commands.add_parser('omega', help="section 2's procedure: the ω rule's ω from permitted errors "
                                             'and torques')
    add_episode_arguments(omega, gains=False)
    omega.add_argument('--max-error', type=finite, nargs='+', required=True, metavar='DEG',
                       help='permitted steady-state error in degrees, mm for a prismatic joint (one, or one per '
                            'joint)')
    omega.add_argument('--disturbance', type=finite, nargs='+', metavar='PZ',
                       help='constant external joint torques P^z in N m (same as --external-torque)')
    omega.add_argument('--mass-error', type=finite, nargs='+', metavar='E',
                       help='relative link mass error of the plant: plant mass = model mass x (1 + E)')
    omega.add_argument('--torque-factor', type=finite, default=1.5, metavar='F',
                       help='largest torque allowed, as a multiple of the largest nominal torque (1.5)')
    omega.add_argument('--omega-step', type=finite, default=0.5, help='ω increment when raising (0.5)')
    omega.add_argument('--omega-max', type=finite, default=100.0, help='largest ω tried (100)')
    add_output_arguments(omega)
    omega.set_defaults(handler=command_omega)
    tune = commands.add_parser('tune', help='optimise the gains for index (2.5) or (3.2), then check them '
                                           'through the ROS graph')
    add_episode_arguments(tune, gains=False)
    tune.add_argument('--index', type=index_name, required=True, metavar='{I1,I2,I}',
                      help='the index minimised: I1 (2.5), I2, or I = I1 + I2 (3.2); 2.5 and 3.2 also name them')
    tune.add_argument('--method', choices=METHODS, default=DEFAULT_METHOD,
                      help='global: Nelder-Mead from the ω-rule starts of both laws, then differential evolutions '
                           'and wide CMA-ES runs until enough independent runs agree (default); nelder-mead: '
                           'multi-start Nelder-Mead from the ω-rule gains (the paper-style local search); cma: '
                           'one CMA-ES run from the best ω-rule start')
    tune.add_argument('--budget', type=int, default=DEFAULT_TUNE_BUDGET,
                      help=f'most episodes evaluated ({DEFAULT_TUNE_BUDGET}); a ceiling: the global search stops '
                           'earlier once its certificate holds')
    tune.add_argument('--omegas', type=finite, nargs='+', default=list(SEARCH_START_OMEGAS),
                      metavar='W', help='ω of the ω-rule start gains (8 12 15 20 30)')
    tune.add_argument('--seed', type=seed, default=0, help='random seed of DE and CMA-ES (0)')
    tune.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    add_robust_arguments(tune)
    add_output_arguments(tune)
    tune.set_defaults(handler=command_tune, starts_ros=True)
    reproduce = commands.add_parser('reproduce', help="reproduce the paper's Tables 2-4 and section 2 through "
                                                     'the ROS graph, with a report')
    reproduce.add_argument('--out', default='runs/paper', help='output folder, new (runs/paper)')
    reproduce.add_argument('--quick', action='store_true',
                           help='small search budgets and three τ values: a first look in well under a minute')
    reproduce.add_argument('--jobs', type=job_count, metavar='N',
                           help='searches run at once, each a process with its share of the cores, and graph '
                                'sessions recording episodes at once; the results do not depend on it (default: '
                                'the cores this process may use)')
    reproduce.set_defaults(handler=command_reproduce, starts_ros=True)
    score = commands.add_parser('score', help='score recorded episodes from their bags alone')
    score.add_argument('bags', nargs='+', metavar='BAG', help='rosbag2 folders written by ddarm')
    score.add_argument('--json', action='store_true', help='one JSON object per bag, one per line')
    score.set_defaults(handler=command_score)
    plant = commands.add_parser('plant', help='start the plant node (then --ros-args ...)')
    plant.set_defaults(handler=command_plant, takes_ros_arguments=True)
    robot = commands.add_parser('robot', help='start a MuJoCo robot behind ros2_control\'s topics, a lifecycle node '
                                             '(then --ros-args -p mjcf:=FILE ...)')
    robot.add_argument('--mjcf', metavar='FILE', help='the MuJoCo robot (the node\'s mjcf parameter): an MJCF, or a '
                                                     'URDF MuJoCo compiles')
    robot.set_defaults(handler=command_robot, takes_ros_arguments=True)
    controller = commands.add_parser('controller', help='start a controller node (then --ros-args ...)')
    controller.add_argument('law', choices=CONTROLLERS)
    controller.set_defaults(handler=command_controller, takes_ros_arguments=True)
    tuner = commands.add_parser('tuner', help='start the tuner node: a recorded sweep on running nodes '
                                             '(then --ros-args ...)')
    tuner.set_defaults(handler=command_tuner, takes_ros_arguments=True)
    add_bench_parser(commands)
    add_pareto_parser(commands)
    add_stability_parser(commands)
    add_motion_parser(commands)
    add_identify_parser(commands)
    add_transfer_parser(commands)
    add_campaign_parser(commands)
    return parser


def starts_ros(args: argparse.Namespace) -> bool:
    """Whether the command starts ROS 2: a node, or a graph session (which `tune`, `reproduce` and `campaign`
    record their episodes through)."""
    return any(getattr(args, flag, False) for flag in ('starts_ros', 'takes_ros_arguments', 'ros', 'realtime'))


def main(argv: list[str] | None = None) -> int:
    skip_cycle_search_at_exit()
    with terminal_streams():  # argparse's refusals quote the arguments, and every command prints names from files
        return _main(sys.argv[1:] if argv is None else argv)


def _main(argv: list[str]) -> int:
    one_line_deprecations()
    parser = build_parser()
    args, ros_arguments = parser.parse_known_args(argv)
    if ros_arguments and not getattr(args, 'takes_ros_arguments', False):
        parser.error(f'unrecognized arguments: {" ".join(ros_arguments)}')
    args.ros_arguments, args.argv = ros_arguments, argv
    if starts_ros(args):
        from ddarm.ros.executable import non_utf8_argument, ros_environment_problem

        # Before any work, not when ROS starts after it: arguments ROS cannot take, an environment it cannot start in.
        if (problem := non_utf8_argument(argv) or ros_environment_problem(argv)) is not None:
            print(f'ddarm {args.command}: {problem}', file=sys.stderr)
            return 2
    if getattr(args, 'takes_ros_arguments', False):
        return args.handler(args)  # a node: it handles SIGINT and SIGTERM as ROS nodes do
    try:
        with stop_on_signals():
            return args.handler(args)
    except Interrupted as stop:
        print(f'ddarm {args.command}: {stop}; stopped cleanly (bags under way marked incomplete)',
              file=sys.stderr, flush=True)
        return stop.exit_code
    except DdarmError as error:  # refused input or an untrustworthy run; anything else is a bug: its traceback shows
        print(f'ddarm {args.command}: {error}', file=sys.stderr)
        return 2
    except OSError as error:  # a path the user gave that the system refuses (permissions, a full disk)
        where = f'{error.filename}: ' if error.filename else ''
        print(f'ddarm {args.command}: {where}{error.strerror or error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
