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
import select
import signal
import threading
import time
import traceback
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


def run_jobs(jobs: list[Job], workers: int, *, on_start=None, on_progress=None, on_done=None,
             check=check_stop) -> dict:
    """Every job's result by key, `workers` at a time (1: in this process, in turn).

    `on_start(job)`, `on_progress(job, episodes, best)` and `on_done(job, result)` are called in this
    process, as the jobs start, report and end. A job's exception is raised here (the others stopped);
    so is what `check` raises (called between jobs and at least every POLL_S s; by default a stop by
    signal, ddarm.interrupts), after the workers are ended.
    """
    if not (isinstance(workers, int) and workers >= 1):
        raise JobError(f'workers must be a whole number >= 1, got {workers!r}')
    _check(jobs)
    on_start = on_start or (lambda job: None)
    on_progress = on_progress or (lambda job, episodes, best: None)
    on_done = on_done or (lambda job, result: None)
    pending, results = list(jobs), {}
    if not jobs:
        return {}
    if workers == 1:
        while pending:
            job = _next(pending, results)
            if job is None:
                raise JobError(f'jobs {[job.label for job in pending]} need each other')
            check()
            pending.remove(job)
            on_start(job)
            result = job.function(*job.arguments, *(results[need] for need in job.needs),
                                  progress=lambda episodes, best, job=job: (check(), on_progress(job, episodes, best)))
            results[job.key] = result
            on_done(job, result)
        return {job.key: results[job.key] for job in jobs}
    workers = min(workers, len(jobs))  # more would never get a job
    # forkserver, not fork: this process may have threads (tqdm's monitor, the engine's pool) that a fork copies
    # mid-step; the server is a fresh process that forks each worker.
    context = multiprocessing.get_context('forkserver')
    # Imported once by the server, so that each worker forks with them (they take seconds to import).
    context.set_forkserver_preload(sorted({job.function.__module__ for job in jobs}))
    threads = max(1, default_workers() // workers)
    by_key = {job.key: job for job in jobs}
    messages, pool, finished = context.Queue(), [], False
    try:
        for number in range(workers):
            pool.append(_Worker(context, number, messages, threads))
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
            check()
            dead = [number for number in running if not pool[number].process.is_alive()]
            try:
                # A dead worker's last words may still be in the queue: read them before calling it dead.
                message = messages.get(timeout=0.0 if dead else POLL_S)
            except queue.Empty:
                for number in dead:
                    raise JobError(f'{running[number].label}: its worker process ended (exit code '
                                   f'{pool[number].process.exitcode}) before the job did')
                continue
            kind, number, key, payload = message
            job = by_key[key]
            if kind == 'progress':
                on_progress(job, *payload)
            elif kind == 'done':
                del running[number]
                results[key] = pickle.loads(payload)
                on_done(job, results[key])
            else:
                error, text, remote = payload
                error = error if error is not None else JobError(f'{job.label} failed: {text}')
                error.add_note(f'in the job {job.label!r}, on worker process {pool[number].process.pid}:\n{remote}')
                raise error
        finished = True
        return {job.key: results[job.key] for job in jobs}
    finally:
        _end(pool, finished)
        messages.close()


def _end(pool: list[_Worker], finished: bool) -> None:
    """Every worker ended: told to stop after its last job, or terminated at once (a failure, a stop)."""
    for worker in pool:
        if finished:
            worker.tasks.put(None)
        else:
            worker.process.terminate()
    deadline = time.monotonic() + 5.0
    for worker in pool:
        worker.process.join(timeout=max(0.0, deadline - time.monotonic()))
        if worker.process.is_alive():
            worker.process.kill()
            worker.process.join()


class Cancelled(BaseException):
    """Raised in a BackgroundJobs' thread when its owner closes it before the jobs are done; a BaseException,
    like ddarm.interrupts.Interrupted, so that no `except Exception` in a job running in that thread eats it."""


class BackgroundJobs:
    """run_jobs in a thread of this process, so that this thread can use each result as it comes (`wait`).

    The callbacks run in that thread. Used as a context manager: leaving the block, however, cancels
    the jobs not done and ends the workers before it returns.
    """

    def __init__(self, jobs: list[Job], workers: int, *, on_start=None, on_progress=None, on_done=None,
                 on_end=None) -> None:
        """`on_end()` is called in the thread once the jobs are over, however they end."""
        _check(jobs)
        self.labels = {job.key: job.label for job in jobs}
        self.results: dict = {}
        self._changed = threading.Condition()
        self._cancelled = threading.Event()
        self._error: BaseException | None = None
        self._finished = False
        user_done = on_done or (lambda job, result: None)

        def done(job: Job, result) -> None:
            user_done(job, result)
            with self._changed:
                self.results[job.key] = result
                self._changed.notify_all()

        def check() -> None:
            if self._cancelled.is_set():
                raise Cancelled('the jobs were closed before they were done')

        def run() -> None:
            try:
                run_jobs(jobs, workers, on_start=on_start, on_progress=on_progress, on_done=done, check=check)
            except BaseException as error:  # handed to the waiting thread, which raises it
                self._error = error
            finally:
                if on_end is not None:
                    on_end()
                with self._changed:
                    self._finished = True
                    self._changed.notify_all()

        self._thread = threading.Thread(target=run, name='ddarm-jobs', daemon=True)
        self._thread.start()

    def ready(self, keys) -> bool:
        with self._changed:
            return all(key in self.results for key in keys)

    def wait(self, keys=None) -> dict:
        """The results of `keys` (default: every job), once all are done; a job's failure is raised here, as is a
        stop by signal (checked every POLL_S s)."""
        with self._changed:
            while True:
                if self._error is not None and not isinstance(self._error, Cancelled):
                    raise self._error
                wanted = self.labels if keys is None else keys
                if all(key in self.results for key in wanted):
                    return {key: self.results[key] for key in wanted}
                if self._finished:
                    missing = [self.labels.get(key, key) for key in wanted if key not in self.results]
                    raise JobError(f'the jobs ended without the results of {missing}')
                self._changed.wait(POLL_S)
                check_stop()

    def wait_for_change(self) -> None:
        """Until a job is done or fails, or POLL_S s have passed (at once if all are over); a job's failure and a stop
        by signal are raised here. A caller waiting for results no job makes would wait forever: `labels` says
        which there are."""
        with self._changed:
            if self._error is None and not self._finished:
                self._changed.wait(POLL_S)
        if self._error is not None and not isinstance(self._error, Cancelled):
            raise self._error
        check_stop()

    def close(self) -> None:
        """Cancel what is not done, end the workers, and return once the thread has."""
        self._cancelled.set()
        self._thread.join()

    def __enter__(self) -> BackgroundJobs:
        return self

    def __exit__(self, *exception) -> None:
        self.close()


class _Worker:
    """A process that runs one job after another, sent on its own queue, and reports on the shared one."""

    def __init__(self, context, number: int, messages, threads: int) -> None:
        self.number = number
        self.tasks = context.SimpleQueue()
        self.process = context.Process(target=_work, args=(number, self.tasks, messages, threads, os.getpid()),
                                       daemon=True, name=f'ddarm-job-{number}')
        self.process.start()


def _end_with(pid: int) -> None:
    """End this process as soon as process `pid` ends, however it ends (SIGKILL included).

    A worker's parent is multiprocessing's fork server, not the command that asked for it, and the
    server outlives a killed command for as long as its workers do: so the worker watches the command.
    """
    try:
        watched = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(1)  # gone before the watch began
    except OSError:  # a kernel before 5.3, or a container that refuses the call: look twice a second instead
        watched = None

    def watch() -> None:
        if watched is not None:
            select.select([watched], [], [])
        else:
            while os.path.exists(f'/proc/{pid}'):
                time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name='ddarm-job-watch', daemon=True).start()


def _work(number: int, tasks, messages, threads: int, command: int) -> None:
    """A worker's life: the command alone takes Ctrl-C (and ends its workers), and the worker ends with it."""
    from ddarm.episodes.engine import set_default_threads

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _end_with(command)
    set_default_threads(threads)
    while (task := tasks.get()) is not None:
        key, function, arguments = task
        try:
            result = function(*arguments, progress=lambda episodes, best: messages.put(
                ('progress', number, key, (episodes, best))))
            # Pickled here, not in the queue's feeder thread, which would drop a result it cannot pickle unseen.
            messages.put(('done', number, key, pickle.dumps(result)))
        except Exception as error:
            text, remote = f'{type(error).__name__}: {error}', traceback.format_exc()
            try:
                pickle.loads(pickle.dumps(error))
            except Exception:
                error = None  # the parent gets its text
            messages.put(('failed', number, key, (error, text, remote)))
