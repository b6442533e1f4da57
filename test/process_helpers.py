"""Shared by the tests that run real processes: ddarm commands and hand-started nodes, their children, their end."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

DDARM = Path(sys.executable).with_name('ddarm')


def ddarm(*arguments: str) -> subprocess.Popen:
    """A `ddarm` command as a user runs it, with its output captured."""
    return subprocess.Popen([str(DDARM), *arguments], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finished_json(process: subprocess.Popen, timeout: float = 180.0) -> dict:
    """The JSON a ddarm process printed; one that does not end within `timeout` s is killed (left running, one stuck
    in its shutdown spun a core for the rest of the suite) and the test fails naming it."""
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        _, err = process.communicate()
        raise AssertionError(f'{process.args} did not end within {timeout} s (killed): {err[-2000:]}') from None
    assert process.returncode == 0, err
    return json.loads(out)


def start_node(arguments: list[str], log: Path) -> subprocess.Popen:
    """A node process as `ros2 run` starts it: `arguments` after `python -m`."""
    with open(log, 'w') as output:
        return subprocess.Popen([sys.executable, '-m', *arguments], stdout=output, stderr=subprocess.STDOUT)


def stop(processes) -> None:
    """SIGINT, as Ctrl-C would; a process that ignores it is killed and the test fails."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes:
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            raise


def children(pid: int) -> set[int]:
    """The live child processes of `pid` (Linux /proc)."""
    found = set()
    for task in Path(f'/proc/{pid}/task').glob('*'):
        try:
            found.update(int(child) for child in (task / 'children').read_text().split())
        except OSError:
            continue
    return found


def alive(pid: int) -> bool:
    """Running, not merely a zombie waiting for a reaper (a container's PID 1 may never reap)."""
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
    except OSError:
        return False
    return state != 'Z'


def wait_for(condition, timeout: float, what: str) -> None:
    """Poll another process's state (files, /proc): there is no event to wait on across processes."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f'{what} within {timeout} s'
        time.sleep(0.05)


def interrupt(process: subprocess.Popen, signum: int, timeout: float = 60.0) -> str:
    """Send `signum`; return what the process printed on stderr once it has ended."""
    os.kill(process.pid, signum)
    _, err = process.communicate(timeout=timeout)
    return err
