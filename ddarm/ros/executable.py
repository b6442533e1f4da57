"""A node's life as an executable: its parameter files checked before rcl reads them, every refusal
named in one line (exit 2), rclpy set up, the node run, and everything shut down whatever happens.

The plant and controller nodes (`run_node`: spin until Ctrl-C, SIGTERM or shutdown, exit 0) and
the tuner node (a sweep with exit codes of its own) share this flow through `run_executable`.
"""

from __future__ import annotations

import sys
import weakref
from collections.abc import Callable, Sequence

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
            shown = argument.encode('utf-8', 'surrogateescape').decode('utf-8', 'backslashreplace')
            if len(shown) > 200:
                shown = shown[:200] + '…'
            return (f'the argument {shown} is not UTF-8 text, and ROS 2 (node parameters, parameter files, '
                    'bags) takes only UTF-8: rename the file or folder')
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

    def refuse(error) -> int:
        print(f'{name}: refused to start: {shortened(error)}', file=out, flush=True)
        return REFUSED

    if follow:
        from ddarm.ros.lifetime import follow_parent

        follow_parent()
    try:
        # Read before rcl does, so that a file it cannot parse is refused in our words, naming it.
        parameter_files = read_parameter_files(sys.argv if args is None else args)
    except ParameterFileError as error:
        return refuse(error)
    arguments = list(sys.argv if args is None else args)
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
