"""Independent searches on several processes at once, each with its share of the cores, the same results as in turn.

A search's batches keep both cores busy only while its compiled loop runs: its own Python work between
batches (differential evolution's and CMA-ES's bookkeeping, scoring, the next batch's set-up) leaves them
idle, and a batch of 90 members splits into chunks that two threads cannot finish together. Two searches
side by side, each on one core, fill those gaps. Every search is a pure function of its arguments (the
engine's members do not depend on how they are shared out), so the results do not depend on `workers`.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import queue
import signal
from collections.abc import Callable, Hashable
from dataclasses import dataclass

from ddarm.errors import DdarmError
from ddarm.interrupts import check_stop

# How long the parent waits for a word from its workers before it checks for a stop again, s.
POLL_S = 0.2


class JobError(DdarmError, RuntimeError):
    """A job list that cannot run: a job needing one that is not in the list, a cycle, a worker that died."""


@dataclass(frozen=True)
class Job:
    """One search: `function(*arguments, *results of needs, progress=callback)`, a module-level function.

    `label` names it in progress lines, `total` is its budget in episodes and `index_name` the index
    its progress reports. Among the jobs ready to start, the one of highest `priority` starts first.
    """

    key: Hashable
    label: str
    function: Callable
    arguments: tuple = ()
    needs: tuple = ()
    total: int | None = None
    index_name: str = 'I'
    priority: float = 0.0


def default_workers() -> int:
    """One worker per core this process may use."""
    return len(os.sched_getaffinity(0))


def _check(jobs: list[Job]) -> None:
    keys = [job.key for job in jobs]
    if len(set(keys)) != len(keys):
        raise JobError(f'two jobs share a key: {sorted(map(str, keys))}')
    known = set(keys)
    for job in jobs:
        missing = [need for need in job.needs if need not in known]
        if missing:
            raise JobError(f'job {job.label!r} needs {missing}, which no job makes')


def _next(pending: list[Job], results: dict) -> Job | None:
    ready = [job for job in pending if all(need in results for need in job.needs)]
    return max(ready, key=lambda job: job.priority) if ready else None


def run_jobs(jobs: list[Job], workers: int, *, on_start=None, on_progress=None, on_done=None) -> dict:
    """Every job's result by key, `workers` at a time (1: in this process, in turn).

    `on_start(job)`, `on_progress(job, episodes, best)` and `on_done(job, result)` are called in this
    process, as the jobs start, report and end. A job's exception is raised here (the others stopped);
    so is a stop by signal (ddarm.interrupts), after the workers are ended.
    """
    if not (isinstance(workers, int) and workers >= 1):
        raise JobError(f'workers must be a whole number >= 1, got {workers!r}')
    _check(jobs)
    on_start = on_start or (lambda job: None)
    on_progress = on_progress or (lambda job, episodes, best: None)
    on_done = on_done or (lambda job, result: None)
    pending, results = list(jobs), {}
    if workers == 1:
        while pending:
            job = _next(pending, results)
            if job is None:
                raise JobError(f'jobs {[job.label for job in pending]} need each other')
            pending.remove(job)
            on_start(job)
            result = job.function(*job.arguments, *(results[need] for need in job.needs),
                                  progress=lambda episodes, best, job=job: on_progress(job, episodes, best))
            results[job.key] = result
            on_done(job, result)
        return results
    # forkserver, not fork: this process may have threads (tqdm's monitor, the engine's pool) that a fork copies
    # mid-step; the server is a fresh process that forks each worker.
    context = multiprocessing.get_context('forkserver')
    messages = context.Queue()
    threads = max(1, default_workers() // workers)
    by_key = {job.key: job for job in jobs}
    pool = [_Worker(context, number, messages, threads) for number in range(workers)]
    try:
        running: dict[int, Job] = {}  # worker number -> its job
        while pending or running:
            for worker in pool:
                if worker.number in running or not pending:
                    continue
                job = _next(pending, results)
                if job is None:
                    if not running:
                        raise JobError(f'jobs {[job.label for job in pending]} need each other')
                    break
                pending.remove(job)
                on_start(job)
                running[worker.number] = job
                worker.tasks.put((job.key, job.function, (*job.arguments, *(results[need] for need in job.needs))))
            check_stop()
            try:
                kind, number, key, *payload = messages.get(timeout=POLL_S)
            except queue.Empty:
                # Nothing in flight: a worker that is gone now died in its job.
                for number, job in running.items():
                    if not pool[number].process.is_alive():
                        raise JobError(f'{job.label}: its worker process ended (exit code '
                                       f'{pool[number].process.exitcode}) before the job did')
                continue
            job = by_key[key]
            if kind == 'progress':
                on_progress(job, *payload)
            elif kind == 'done':
                del running[number]
                results[key] = payload[0]
                on_done(job, results[key])
            else:
                error, text = payload
                raise error if error is not None else JobError(f'{job.label} failed: {text}')
        for worker in pool:
            worker.tasks.put(None)
        return results
    finally:
        for worker in pool:
            worker.end()
        messages.close()


class _Worker:
    """A process that runs one job after another, sent on its own queue, and reports on the shared one."""

    def __init__(self, context, number: int, messages, threads: int) -> None:
        self.number = number
        self.tasks = context.SimpleQueue()
        self.process = context.Process(target=_work, args=(number, self.tasks, messages, threads), daemon=True,
                                       name=f'ddarm-job-{number}')
        self.process.start()

    def end(self) -> None:
        """Ended by now: after its last job it is told to stop; otherwise (a failure, a stop) it is terminated."""
        self.process.join(timeout=1.0)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join()


def _work(number: int, tasks, messages, threads: int) -> None:
    """A worker's life: the parent alone takes Ctrl-C (and ends its workers), and the worker ends with the parent."""
    from ddarm.episodes.engine import set_default_threads
    from ddarm.ros.lifetime import PARENT_PID_VARIABLE, follow_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ[PARENT_PID_VARIABLE] = str(os.getppid())  # the forkserver, which ends when this process's parent does
    follow_parent()
    set_default_threads(threads)
    while (task := tasks.get()) is not None:
        key, function, arguments = task
        try:
            result = function(*arguments, progress=lambda episodes, best: messages.put(
                ('progress', number, key, episodes, best)))
        except Exception as error:
            text = f'{type(error).__name__}: {error}'
            try:
                pickle.dumps(error)
            except Exception:
                error = None  # the parent gets its text
            messages.put(('failed', number, key, error, text))
            continue
        messages.put(('done', number, key, result))
