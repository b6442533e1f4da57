"""Real time for a node process: its SCHED_FIFO priority and CPU affinity, asked for, checked and refused by name,
and the absolute deadline schedule of a wake-then-spin tick. Only os, resource, threading and time: no rclpy.

What the OS needs (Linux): SCHED_FIFO needs CAP_SYS_NICE (root, `setcap cap_sys_nice+ep` on the interpreter,
a container started with `--cap-add SYS_NICE`) or an rtprio limit of at least the priority (`ulimit -r`,
`<user> - rtprio 98` in /etc/security/limits.conf), and real-time runtime in its cgroup. A CPU must be one
the process may use (its cgroup cpuset, the `taskset` it was started with). Without them a request is
refused, never run without: the caller says which parameter asked for what.
"""

from __future__ import annotations

import errno
import os
import resource
import threading
import time
from dataclasses import dataclass
from typing import Callable

from ddarm.errors import DdarmError

# 0: off (the scheduling the process started with); 99 is left to the kernel's own threads (watchdog, migration).
PRIORITY_RANGE = (0, 98)
# A wake-then-spin tick wakes this long before each deadline and spins the rest on the clock (s).
SPIN_MARGIN_RANGE = (0.0, 1.0)
POLICY_NAMES = {getattr(os, name): name for name in ('SCHED_OTHER', 'SCHED_FIFO', 'SCHED_RR', 'SCHED_BATCH',
                                                     'SCHED_IDLE') if hasattr(os, name)}
# The cores this process was started with (cgroup cpuset, taskset, the container's), before anything here pins it.
STARTED_ON = frozenset(os.sched_getaffinity(0))


class SchedulingError(DdarmError, ValueError):
    """A real-time priority or CPU affinity the OS refused, or that cannot be asked for, naming the parameter."""


@dataclass(frozen=True)
class Scheduling:
    """How a thread is scheduled: its policy (SCHED_OTHER, SCHED_FIFO, …), priority (0 for SCHED_OTHER), cores."""

    policy: str
    priority: int
    affinity: tuple[int, ...]

    def report(self) -> dict:
        """The scheduling as a report's entries: what every jitter figure must be shown with."""
        return {'sched_policy': self.policy, 'sched_priority': self.priority, 'cpu_affinity': list(self.affinity)}


def scheduling_of(thread: int = 0) -> Scheduling:
    """The scheduling of one thread (0: the calling one), as the kernel reports it."""
    policy = os.sched_getscheduler(thread)
    return Scheduling(POLICY_NAMES.get(policy, str(policy)), os.sched_getparam(thread).sched_priority,
                      tuple(sorted(os.sched_getaffinity(thread))))


def process_threads() -> list[int]:
    """The thread ids of this process (DDS's, the executor's, Python's); only the calling thread where /proc is not."""
    try:
        return sorted(int(name) for name in os.listdir('/proc/self/task'))
    except OSError:
        return [0]


def checked_affinity(cores, allowed=STARTED_ON, parameter: str = 'cpu_affinity') -> tuple[int, ...]:
    """The cores asked for, sorted, each one a core this process may use; SchedulingError names the first other."""
    given = [int(core) for core in cores]
    for core in given:
        if core not in allowed:
            raise SchedulingError(f'{parameter} = {given}: core {core} is not one this process may use (it may use '
                                  f'{sorted(allowed)}: the cores of its cgroup cpuset, its taskset, its machine)')
    if len(set(given)) != len(given):
        raise SchedulingError(f'{parameter} = {given}: a core is named twice')
    return tuple(sorted(set(given)))


def checked_priority(priority: int, parameter: str = 'realtime_priority') -> int:
    low, high = PRIORITY_RANGE
    if not low <= priority <= high:
        raise SchedulingError(f'{parameter} = {priority}: not in [{low}, {high}] (0: off, 1-{high}: SCHED_FIFO)')
    return int(priority)


def priority_refusal(priority: int, error: OSError, parameter: str = 'realtime_priority') -> SchedulingError:
    """Why SCHED_FIFO at `priority` was refused, and what it needs."""
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    limit = 'unlimited' if soft == resource.RLIM_INFINITY else soft
    code = errno.errorcode.get(error.errno, str(error.errno))
    return SchedulingError(
        f'{parameter} = {priority}: the OS refused SCHED_FIFO priority {priority} ({code}: {error.strerror}); it '
        f'needs CAP_SYS_NICE (root, setcap cap_sys_nice+ep on the interpreter, a container with --cap-add SYS_NICE) '
        f'or an rtprio limit of at least {priority} (this process has {limit}: ulimit -r; /etc/security/limits.conf: '
        f'"<user> - rtprio 98"), and real-time runtime in its cgroup; {parameter} = 0 runs without it')


class ProcessScheduling:
    """The scheduling of every thread of this process: as it started, and as asked for since.

    A priority or an affinity applies to every thread there is (DDS's receive threads answer the
    samples as much as the executor's), and threads started later inherit it from the one that
    starts them. Asking for 0 (or no cores) gives back what the process started with.
    """

    def __init__(self) -> None:
        self.started_with = scheduling_of(0)

    def current(self) -> Scheduling:
        return scheduling_of(0)

    def apply(self, priority: int, cores) -> Scheduling:
        """SCHED_FIFO at `priority` (0: the starting policy) on `cores` (empty: the starting ones), for every thread.

        Refused (SchedulingError naming realtime_priority or cpu_affinity, and what it needs), nothing
        is changed: each thread gets back the scheduling it had.
        """
        priority = checked_priority(priority)
        affinity = checked_affinity(cores) or self.started_with.affinity
        if priority:
            policy = os.SCHED_FIFO
        else:
            policy = next(number for number, name in POLICY_NAMES.items() if name == self.started_with.policy)
            priority = self.started_with.priority
        threads = process_threads()
        before = {}
        for thread in threads:
            try:
                before[thread] = (os.sched_getscheduler(thread), os.sched_getparam(thread),
                                  os.sched_getaffinity(thread))
            except ProcessLookupError:  # a thread that ended since it was listed
                continue
        try:
            for thread in before:
                _for_thread(os.sched_setaffinity, thread, affinity)
            if set(os.sched_getaffinity(0)) != set(affinity):  # a cpuset keeps only its own cores, silently
                raise SchedulingError(f'cpu_affinity = {list(affinity)}: the OS gave this process cores '
                                      f'{sorted(os.sched_getaffinity(0))} instead (its cgroup cpuset)')
        except OSError as error:
            _restore(before)
            raise SchedulingError(f'cpu_affinity = {list(affinity)}: the OS refused it ({error.strerror})') from error
        except SchedulingError:
            _restore(before)
            raise
        try:
            for thread in before:
                _for_thread(os.sched_setscheduler, thread, policy, os.sched_param(priority))
        except OSError as error:
            _restore(before)
            raise priority_refusal(priority, error) from error
        return self.current()


def _for_thread(call: Callable, thread: int, *args) -> None:
    try:
        call(thread, *args)
    except ProcessLookupError:
        pass


def _restore(before: dict) -> None:
    for thread, (policy, parameters, cores) in before.items():
        for call, args in ((os.sched_setscheduler, (policy, parameters)), (os.sched_setaffinity, (cores,))):
            try:
                call(thread, *args)
            except OSError:
                pass  # a thread gone, or a scheduling it can no longer get back: nothing better to do


# The deadline schedule ---------------------------------------------------------------------------

def deadline_ns(start_ns: int, period_ns: int, index: int) -> int:
    """Tick `index`'s deadline t0 + index·Δ in integer ns: a product, never a running sum, so it never drifts."""
    return start_ns + index * period_ns


def next_tick(start_ns: int, period_ns: int, index: int, now_ns: int) -> int:
    """The tick after tick `index`: the next one, or, once `now_ns` is past its deadline and later ones, the
    latest deadline passed (run at once, late); the ones between are skipped, as rcl's timers skip them."""
    return max(index + 1, (now_ns - start_ns) // period_ns)


def period_ns(period: float) -> int:
    return round(period * 1e9)


def run_ticks(start_ns: int, period: int, margin: int, tick: Callable[[int, int], bool], stop: threading.Event,
              clock: Callable[[], int] = time.monotonic_ns) -> None:
    """Call tick(index, deadline) at each deadline t0 + index·Δ (index 1, 2, …) until it returns False or `stop`
    is set: sleep until `margin` ns before the deadline, then spin on the clock to it, so that the tick starts on
    the deadline instead of a wake-up latency after it. All times in ns of `clock` (CLOCK_MONOTONIC)."""
    index = 1
    while not stop.is_set():
        deadline = deadline_ns(start_ns, period, index)
        sleep = deadline - margin - clock()
        if sleep > 0 and stop.wait(sleep * 1e-9):
            return
        while clock() < deadline:
            pass
        if not tick(index, deadline):
            return
        index = next_tick(start_ns, period, index, clock())


class TickThread:
    """The real-time ticks of a node on a thread of their own: `run_ticks` from `start`, until the tick returns False
    or `end` is called. A thread, not an rclpy timer: the executor's timer wakes its spinning thread through a
    queue, a second wake-up's latency; this one sleeps to `margin` before each deadline and spins the rest.
    `failed(error)` says an exception that stopped the ticks: no executor reports for this thread."""

    def __init__(self, name: str, tick: Callable[[int, int], bool], failed: Callable[[Exception], None]) -> None:
        self.name = name
        self._tick = tick
        self._failed = failed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def thread(self) -> threading.Thread | None:
        """The ticking thread (None before the first start and after a stop)."""
        return self._thread

    def start(self, start_ns: int, period: int, margin: int = 0) -> None:
        """Tick at start_ns + kΔ (ns of CLOCK_MONOTONIC; `period` and `margin` in ns)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True,
                                        args=(start_ns, period, margin, self._stop))
        self._thread.start()

    def _run(self, start_ns: int, period: int, margin: int, stop: threading.Event) -> None:
        try:
            run_ticks(start_ns, period, margin, self._tick, stop)
        except Exception as error:
            self._failed(error)

    def end(self) -> None:
        """No tick after the one under way (if this is it, the thread ends when it returns); not waited for."""
        self._stop.set()

    def stop(self) -> None:
        """End the ticks and wait for the thread (at most one tick's work), unless called from a tick."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
            self._thread = None
