"""A node's life as an executable: its parameter files checked before rcl reads them, every refusal
named in one line (exit 2), rclpy set up, the node run, and everything shut down whatever happens.

The plant and controller nodes (`run_node`: spin until Ctrl-C, SIGTERM or shutdown, exit 0) and
the tuner node (a sweep with exit codes of its own) share this flow through `run_executable`.
"""

from __future__ import annotations

import os
import re
import sys
import weakref
from collections.abc import Callable, Sequence

from ddarm.interrupts import skip_cycle_search_at_exit
from ddarm.reporting.text import shortened
from ddarm.ros.parameter_files import ParameterFileError, read_parameter_files, refuse_unconfigured

REFUSED = 2  # the exit code of a node that refused to start
SIGNAL_CHECK_PERIOD_S = 0.2  # the longest a spinning node waits in rcl before its signal handlers run
# The arguments each context was initialised with by `run_executable` (rclpy keeps no public copy).
_ARGUMENTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def context_arguments(context) -> list[str]:
    """The command line an rclpy context was initialised with, as far as ddarm knows it.

    The arguments `run_executable` gave rclpy.init; for the default context otherwise the
    process's own (what rclpy.init reads when given none); for another context, none.
    """
    import rclpy

    if context in _ARGUMENTS:
        return _ARGUMENTS[context]
    return list(sys.argv) if context is rclpy.get_default_context() else []


def non_utf8_argument(arguments: Sequence[str]) -> str | None:
    """Why ROS cannot take these arguments, if it cannot: the first that is not UTF-8 text, named.

    Python keeps a file name's non-UTF-8 bytes as lone surrogates; rclpy.init, node parameters, parameter files
    and rosbag2's metadata hold UTF-8 only, and fail on them with a UnicodeEncodeError, after any work before.
    """
    for argument in arguments:
        try:
            argument.encode('utf-8')
        except UnicodeEncodeError:
            return (f'the argument {_shown(argument)} is not UTF-8 text, and ROS 2 (node parameters, parameter '
                    'files, bags) takes only UTF-8: rename the file or folder')
    return None


def _shown(text: str) -> str:
    """`text` as a message shows it: a non-UTF-8 byte as \\xff, and cut after its first 200 characters."""
    shown = text.encode('utf-8', 'surrogateescape').decode('utf-8', 'backslashreplace')
    return shown[:200] + '…' if len(shown) > 200 else shown


# The ROS domain IDs Fast DDS (the one RMW ddarm ships with) takes with its default ports, as ROS 2 documents:
# on this machine 232 started a node and 233 failed with Fast DDS's "Calculated port number is too high".
DOMAIN_ID_RANGE = (0, 232)
# In decimal digits only: rcl reads it as C's strtoul with base 0 does, and refuses only no number at all; on this
# machine '010' went to domain 8, '0x10' to 16, '-1' to 0, '1_0' to 1, ' 5' to 5, and 4294967296 was taken.
_DOMAIN_ID = re.compile(r'0|[1-9][0-9]*')


def _log_files_disabled(arguments: Sequence[str]) -> bool:
    """Whether ROS arguments turn rcl's log files off (--disable-external-lib-logs, the last of it and --enable-)."""
    within, disabled = False, False
    for argument in arguments:
        if argument == '--ros-args':
            within = True
        elif argument == '--':
            within = False
        elif within and argument in ('--disable-external-lib-logs', '--enable-external-lib-logs'):
            disabled = argument == '--disable-external-lib-logs'
    return disabled


def _log_folder(environment) -> tuple[str, str, str | None]:
    """The folder rcl's log files go to, as rcutils_get_logging_directory finds it: (variable, its value, the
    folder, None if it cannot be found). ROS_LOG_DIR, else ROS_HOME/log, else HOME/.ros/log, the first set and
    not empty; a leading ~ is HOME, and only HOME (rcutils reads no password database)."""
    home = environment.get('HOME', '')
    for variable, below in (('ROS_LOG_DIR', ''), ('ROS_HOME', 'log'), ('HOME', os.path.join('.ros', 'log'))):
        value = environment.get(variable, '')
        if value:
            folder = value
            if folder.startswith('~'):
                if not home:
                    return variable, value, None
                folder = home + folder[1:]
            return variable, value, os.path.join(os.path.abspath(folder), below) if below else os.path.abspath(folder)
    return 'HOME', '', None


def ros_environment_problem(arguments: Sequence[str] = (), environment=None) -> str | None:
    """Why ROS 2 cannot start in this environment (os.environ by default), if it cannot, in words naming the variable.

    rcl's own words for these are a traceback (RCLError) or Fast DDS's coloured log line, after any work before:
    ROS_DOMAIN_ID must be unset, empty or a whole number in DOMAIN_ID_RANGE, and rcl must find, or be able to make,
    a folder it can write its log files in (`_log_folder`) unless `arguments` turn the log files off. Nothing is made.
    """
    environment = os.environ if environment is None else environment
    domain_id = environment.get('ROS_DOMAIN_ID', '')
    low, high = DOMAIN_ID_RANGE
    if domain_id and not (_DOMAIN_ID.fullmatch(domain_id) and low <= int(domain_id) <= high):
        return (f"ROS_DOMAIN_ID is '{_shown(domain_id)}', and ROS 2 takes a whole number from {low} to {high} in "
                'decimal digits, or none (unset or empty: domain 0): set it so or unset it')
    if _log_files_disabled(arguments):
        return None
    variable, value, folder = _log_folder(environment)
    if folder is None:
        if value:
            return (f"{variable} is '{_shown(value)}', and ROS 2 reads its ~ from HOME, which is unset or empty: "
                    f'give {variable} without ~ or set HOME')
        return ('ROS 2 finds no folder for its log files: ROS_LOG_DIR, ROS_HOME and HOME are all unset or empty; '
                'set one of them (ROS_LOG_DIR: the folder itself, ROS_HOME: its log folder, HOME: its .ros/log)')
    where = f"{variable} is '{_shown(value)}'" + (f', so ROS 2 writes its log files in {_shown(folder)}'
                                                   if folder != os.path.abspath(value) else '')
    existing = folder
    while not os.path.lexists(existing):  # the folder rcl would make, and each missing one above it
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        shown = '' if existing == folder else f' ({_shown(existing)})'
        return (f'{where}, and that{shown} is not a folder: give {variable} a folder, or where one can be made')
    if not os.access(existing, os.W_OK | os.X_OK):
        shown = '' if existing == folder else f' ({_shown(existing)}, where it would be made)'
        return f'{where}, and that folder{shown} cannot be written: give {variable} a folder you may write in'
    return None


def parameter_file_refusal(parameter_files: dict, name: str) -> ParameterFileError | None:
    """Why a node named `name` got none of its parameter files' values, if it did not."""
    import rclpy

    # A bare node under the same remapping rules tells the name the refused one would have had.
    stand_in = rclpy.create_node(name, enable_rosout=False)
    try:
        refuse_unconfigured(parameter_files, stand_in.get_fully_qualified_name())
    except ParameterFileError as error:
        return error
    finally:
        stand_in.destroy_node()
    return None


def run_executable(name: str, make_node: Callable, refusals: tuple, args: Sequence[str] | None,
                   run: Callable[..., int], *, out=None, signal_handler_options=None, follow: bool = True) -> int:
    """Start the node `make_node` builds (named `name`), hand it to `run`, and return `run`'s exit code.

    Refused with exit 2, in one line on `out` (stdout by default): a parameter file that cannot
    be read or configures no node (checked before rcl reads it, so the words name the file),
    arguments rcl refuses, and an exception in `refusals` (or a parameter exception) while the
    node is built; a node refused on its defaults names the file meant for another node as the
    cause. `follow`: end with the ddarm process that started this one (`ddarm.ros.lifetime`).
    `signal_handler_options` goes to rclpy.init (None: rclpy's own handlers).
    """
    import rclpy
    from rclpy.exceptions import ParameterException

    skip_cycle_search_at_exit()

    def refuse(error) -> int:
        print(f'{name}: refused to start: {shortened(error)}', file=out, flush=True)
        return REFUSED

    arguments = list(sys.argv if args is None else args)
    if (problem := ros_environment_problem(arguments)) is not None:  # before anything starts
        return refuse(problem)
    if follow:
        from ddarm.ros.lifetime import follow_parent

        follow_parent()
    try:
        # Read before rcl does, so that a file it cannot parse is refused in our words, naming it.
        parameter_files = read_parameter_files(sys.argv if args is None else args)
    except ParameterFileError as error:
        return refuse(error)
    if (problem := non_utf8_argument(arguments)) is not None:
        return refuse(problem)
    try:
        rclpy.init(args=arguments, signal_handler_options=signal_handler_options)
    except RuntimeError as error:  # rclpy's errors of rcl (unknown arguments, a file it cannot parse)
        return refuse(f'rcl refused the arguments: {error}')
    context = rclpy.get_default_context()
    _ARGUMENTS[context] = arguments
    node = None
    try:
        try:
            node = make_node()
            refuse_unconfigured(parameter_files, node.get_fully_qualified_name())
        except (*refusals, ParameterException, ParameterFileError) as error:
            if node is None and parameter_files:
                # Refused on defaults (a controller without gains, say): a file for another node is the cause.
                error = parameter_file_refusal(parameter_files, name) or error
            return refuse(error)
        return run(node)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        _ARGUMENTS.pop(context, None)


def run_node(make_node: Callable, name: str, refusals: tuple, args=None) -> int:
    """A node's whole life as an executable: 0 after a normal end (Ctrl-C, SIGTERM, shutdown), 2 if refused.

    `make_node` builds the node named `name` after rclpy.init; an exception in `refusals` while it
    does (a bad parameter file, say) is printed as the reason the node refused to start, as is a
    parameter file that rcl cannot parse or that configures no node of this name.
    """
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    from ddarm.interrupts import Interrupted, critical_section, stop_on_signals
    from ddarm.ros.executors import node_executor

    executors = []

    def make_executor_and_node():
        # The executor before the node: once the node's services are on the graph, a Ctrl-C may come at once
        # (a test, a launch file), and by then rclpy's handler has shut the context down that a new executor needs.
        executors.append(node_executor())
        return make_node()

    def spin(node) -> int:
        executor = executors[0]
        executor.add_node(node)
        try:
            # Bounded waits, not rclpy.spin's endless one: between them the process is back in Python, where
            # its own SIGINT and SIGTERM handlers run (a node with no timer slept through rclpy's in rcl_wait).
            while node.context.ok():
                # A stop that comes while a callback runs is raised once spin_once returns, here: raised in the
                # callback, rclpy's EventsExecutor logs it as FATAL with a stack before passing it on.
                with critical_section():
                    executor.spin_once(timeout_sec=SIGNAL_CHECK_PERIOD_S)
        except (*refusals, ParameterException, ParameterFileError) as error:
            print(f'{name}: refused to start: {shortened(error)}', flush=True)
            return REFUSED
        finally:
            executor.shutdown()  # before the node is destroyed and the context shut down
        return 0

    try:
        # Python's handlers, not rclpy's: a node with no timer sometimes never heard rclpy's SIGINT (its guard
        # condition did not wake the wait, and no KeyboardInterrupt followed) and outlived Ctrl-C.
        with stop_on_signals():
            return run_executable(name, make_executor_and_node, refusals, args, spin,
                                  signal_handler_options=SignalHandlerOptions.NO)
    except (Interrupted, KeyboardInterrupt, ExternalShutdownException):  # Ctrl-C, SIGTERM, or a shutdown
        return 0
    finally:
        for executor in executors:  # a node refused before it spun (shutting down twice does nothing)
            executor.shutdown()
