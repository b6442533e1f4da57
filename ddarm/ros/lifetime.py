"""Node processes that ddarm starts end with the process that started them, even if it is killed outright.

The parent names itself in DDARM_PARENT_PID; the child asks the Linux kernel to send it SIGTERM
when that parent dies (prctl PR_SET_PDEATHSIG), so a SIGKILL of a driver leaves no node
running on (docs/faults.md 23). SIGTERM rather than SIGKILL: the node leaves the DDS graph cleanly.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys

PARENT_PID_VARIABLE = 'DDARM_PARENT_PID'
_PR_SET_PDEATHSIG = 1


def child_environment(environment: dict | None = None) -> dict:
    """The environment for a node process that must not outlive this process."""
    environment = dict(os.environ if environment is None else environment)
    environment[PARENT_PID_VARIABLE] = str(os.getpid())
    return environment


def follow_parent() -> None:
    """In a node process started by ddarm: end when the parent ends; a no-op for hand-started nodes.

    The kernel's notice goes to the thread that forked us, so the parent starts nodes from its
    main thread. A parent that died before the request took effect is caught by the check after it.
    """
    parent = os.environ.get(PARENT_PID_VARIABLE)
    if not parent:
        return
    if sys.platform.startswith('linux'):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), 'prctl(PR_SET_PDEATHSIG) failed')
    if os.getppid() != int(parent):
        raise SystemExit(f'the process that started this node ({parent}) is gone; not starting')


def tell_to_stop(processes, stop: int = signal.SIGINT) -> None:
    """`stop` (SIGINT: a node leaves the graph as after a Ctrl-C) to each of `processes` still running, at once."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(stop)


def stop_processes(processes, stop: int = signal.SIGINT, timeout: float = 10.0, signalled=()) -> None:
    """Stop node processes started by this one: `stop` to all at once (tell_to_stop) but the `signalled` ones (told
    before), then, for each still running after `timeout` s, SIGKILL; each one waited for (no zombie left)."""
    processes = list(processes)
    tell_to_stop(processes, stop)
    for process in [*processes, *signalled]:
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
