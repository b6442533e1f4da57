"""Job functions for test_jobs: module-level, so that a worker process can import them."""

import os
import signal

from ddarm.tuning.search import omega_starts, search_gains


def square(value, progress=None):
    progress(1, value * value)
    return value * value


def add(first, second, progress=None):
    return first + second


def dies(progress=None):
    os.kill(os.getpid(), signal.SIGKILL)


def refuses(progress=None):
    raise ValueError('no such gain: kq')


def worker_pid(progress=None):
    return os.getpid()


def search(template, index, budget, progress=None):
    """A small global search: its optimum and its whole history."""
    start_kp, start_kv = omega_starts(template, (5.0, 10.0))
    result = search_gains(template, index=index, start_kp=start_kp, start_kv=start_kv, budget=budget,
                          method='global', popsize=4, progress=progress)
    return result.kp, result.kv, result.index, result.history_index
