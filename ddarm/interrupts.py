"""SIGINT and SIGTERM as one exception, so every ddarm command stops the same way: children stopped,
the bag under way closed as incomplete, the run marked interrupted, one line, exit 128 + signal; and a process's
end without the interpreter's search for cycles (skip_cycle_search_at_exit)."""

from __future__ import annotations

import atexit
import contextlib
import gc
import signal
import sys
import threading

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def skip_cycle_search_at_exit() -> None:
    """For a process's entry point (a command, a node), which closes its files, bags and ROS contexts itself: at exit,
    gc.freeze, so that the interpreter's end no longer searches every object left for cycles (a command that had
    loaded the search, the plots and rclpy spent 0.5 s of its exit in that search, a stopped node 0.35 s before it
    left the graph). Registered once per process, whichever entry points it passed."""
    atexit.unregister(gc.freeze)
    atexit.register(gc.freeze)


class Interrupted(BaseException):
    """A stop asked for by a signal. A BaseException, like KeyboardInterrupt: no `except Exception` eats it."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f'stopped by {signal.Signals(signum).name}')

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # the shell's convention: 130 for SIGINT, 143 for SIGTERM


# The stop asked for, kept after it is raised: a raise that lands in a finaliser or in a C
# extension that turns it into an error of its own is lost, and `check_stop` raises it again.
_requested: int | None = None
_critical = 0
_deferred: int | None = None  # a stop that came during a critical section
_critical_lock = threading.Lock()


def _raise(signum, frame) -> None:
    global _requested, _deferred
    _requested = signum
    if _critical:
        _deferred = signum
        return
    raise Interrupted(signum)


def check_stop() -> None:
    """At a point where work can stop (between episodes, batches, waits): raise a stop asked for and not yet taken."""
    if _requested is not None and not _critical:
        raise Interrupted(_requested)


@contextlib.contextmanager
def critical_section():
    """A block that a stop must not cut in two (a bag's metadata being written): the stop waits for its end.

    Masking the signal would not do: Python runs its handlers in the main thread whichever thread
    the signal reached, and DDS has threads of its own.
    """
    global _critical, _deferred
    with _critical_lock:  # threads of one command (its graph sessions') each write their bags
        _critical += 1
    try:
        yield
    finally:
        with _critical_lock:
            _critical -= 1
            signum = _deferred if not _critical else None
            if signum is not None:
                _deferred = None
    if signum is not None:
        raise Interrupted(signum)


@contextlib.contextmanager
def stop_on_signals():
    """Within the block, SIGINT or SIGTERM raises Interrupted in the main thread; old handlers come back after."""
    global _requested, _deferred
    _requested = _deferred = None
    previous = {stop: signal.signal(stop, _raise) for stop in STOP_SIGNALS}
    previous_hook = sys.unraisablehook

    def unraisable(hook_arguments) -> None:
        # A stop raised inside a callback from C (numba's compiler calls back into Python) cannot leave it and is
        # printed as "Exception ignored"; it is kept in _requested and raised again below or at check_stop.
        if not isinstance(hook_arguments.exc_value, Interrupted):
            previous_hook(hook_arguments)

    sys.unraisablehook = unraisable
    try:
        yield
    except Exception as error:
        # An error after a stop was asked for is the stop's doing: a raise that a library turned into its own
        # error (numba's "no compiled object yet" once its compiler's callback was cut short).
        if _requested is None:
            raise
        raise Interrupted(_requested) from error
    finally:
        for stop, handler in previous.items():
            signal.signal(stop, handler)
        sys.unraisablehook = previous_hook
        _requested = _deferred = None
