"""The executor every ddarm process spins its nodes with."""

from __future__ import annotations

import contextlib
import io
import sys


def node_executor(context=None):
    """rclpy's EventsExecutor (its C++ one, experimental in Jazzy) for `context` (default: rclpy's default).

    SingleThreadedExecutor rebuilds its wait set in Python at every wake, about 0.35 ms for a
    node with parameter services and clients: that, three processes a sample, was most of a
    lockstep episode. Measured side by side, 100 lockstep samples took 132 ms instead of 298 ms.
    """
    from rclpy.experimental import EventsExecutor

    # EventsExecutor() enables faulthandler on sys.stderr, which needs a file descriptor: a caller that replaced
    # sys.stderr (pytest's capture, a notebook) gets the process's own for that call.
    try:
        sys.stderr.fileno()
        stream = contextlib.nullcontext()
    except (AttributeError, OSError, io.UnsupportedOperation):
        stream = contextlib.redirect_stderr(sys.__stderr__)
    with stream:
        return EventsExecutor(context=context)
