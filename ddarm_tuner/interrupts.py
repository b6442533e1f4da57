"""SIGINT and SIGTERM as one exception, so every ddarm command stops the same way: children stopped,
the bag under way closed as incomplete, the run marked interrupted, one line, exit 128 + signal."""

from __future__ import annotations

import contextlib
import signal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(BaseException):
    """A stop asked for by a signal. A BaseException, like KeyboardInterrupt: no `except Exception` eats it."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f'stopped by {signal.Signals(signum).name}')

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # the shell's convention: 130 for SIGINT, 143 for SIGTERM


_critical = 0
_pending: list[int] = []


def _raise(signum, frame) -> None:
    # Further signals must not cut the clean-up this one starts (closing bags, stopping nodes).
    for stop in STOP_SIGNALS:
        signal.signal(stop, signal.SIG_IGN)
    if _critical:
        _pending.append(signum)
        return
    raise Interrupted(signum)


@contextlib.contextmanager
def critical_section():
    """A block that a stop must not cut in two (a bag's metadata being written): the stop waits for its end.

    Masking the signal would not do: Python runs its handlers in the main thread whichever thread
    the signal reached, and DDS has threads of its own.
    """
    global _critical
    _critical += 1
    try:
        yield
    finally:
        _critical -= 1
    if not _critical and _pending:
        raise Interrupted(_pending.pop())


@contextlib.contextmanager
def stop_on_signals():
    """Within the block, SIGINT or SIGTERM raises Interrupted in the main thread; old handlers come back after."""
    previous = {stop: signal.signal(stop, _raise) for stop in STOP_SIGNALS}
    try:
        yield
    finally:
        for stop, handler in previous.items():
            signal.signal(stop, handler)
