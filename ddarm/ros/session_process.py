"""A graph session in a process of its own, so that several record episodes on every core at once.

Sessions driven from threads of one process share its interpreter lock: a driver's per-episode Python
work (configuring the nodes, checking the graph, writing and scoring the bag) is most of an episode, and
two sessions in threads ran the reproduction's episodes only 1.0 to 1.3 times as fast as one. A
`SessionProcess` runs a `GraphSession` in a child process and takes its calls over a pipe.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
from pathlib import Path

from ddarm.errors import DdarmError
from ddarm.interrupts import check_stop

# How long a caller waits on the child's answer before it checks for a stop and for the child's life again, s.
POLL_S = 0.2


class SessionProcessError(DdarmError, RuntimeError):
    """The session's process died, or answered with what cannot be sent back."""


class SessionProcess:
    """`GraphSession(folder, timeout)` in a child process: `prepare`, `record_and_score` and `close` as the session's.

    The child ends with this process, even a killed one (`ddarm.ros.lifetime`), and its nodes with it; a
    stop by signal reaches it as it reaches the nodes (the terminal's process group), and an exception in
    the child is raised here. Start it from the thread that lives longest (the main thread): the child's
    end is tied to it.
    """

    def __init__(self, folder: Path | str, timeout: float = 120.0) -> None:
        context = multiprocessing.get_context('spawn')  # a fresh interpreter: no copy of this one's threads or DDS
        self._connection, child = context.Pipe()
        self.folder = Path(folder)
        self._process = context.Process(target=_serve, args=(child, str(folder), timeout, os.getpid()),
                                        name=f'ddarm-session-{self.folder.name}', daemon=True)
        self._process.start()
        child.close()
        self.namespace = self._answer()  # the session is up (or why not)

    def _gone(self) -> SessionProcessError:
        self._process.join(timeout=1)
        return SessionProcessError(f'the graph session process {self._process.name} exited with code '
                                   f'{self._process.exitcode} (its nodes\' logs: {self.folder})')

    def _answer(self):
        while not self._connection.poll(POLL_S):
            check_stop()
            if not self._process.is_alive():
                raise self._gone()
        try:
            kind, value = self._connection.recv()
        except EOFError:
            raise self._gone() from None
        if kind == 'error':
            raise value
        return value

    def _call(self, method: str, *arguments):
        try:
            self._connection.send((method, arguments))
        except OSError:  # a broken pipe: the child is gone
            raise self._gone() from None
        return self._answer()

    def prepare(self, spec) -> None:
        self._call('prepare', spec)

    def record_and_score(self, spec, bag: Path, command: str | None = None, storage: str = 'mcap'):
        return self._call('record_and_score', spec, Path(bag), command, storage)

    def close(self) -> None:
        if self._process.is_alive():
            try:
                self._connection.send(('close', ()))
                self._answer()
            except (OSError, EOFError, SessionProcessError):
                pass  # it is gone already; what it left is ended below
        self._process.join(timeout=15)
        if self._process.is_alive():
            self._process.terminate()  # its nodes end with it (SIGTERM, then the kernel's notice)
            self._process.join()
        self._connection.close()

    def __enter__(self) -> SessionProcess:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        try:
            self.close()
        except Exception as cleanup:
            if error is None:
                raise
            error.add_note(f'while closing the graph session process: {type(cleanup).__name__}: {cleanup}')


def _sendable(error: BaseException) -> BaseException:
    """`error` if it pickles (with its notes), else its words as a SessionProcessError."""
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:
        return SessionProcessError(f'{type(error).__name__}: {error}')


def _serve(connection, folder: str, timeout: float, parent: int) -> None:
    """The child: a GraphSession answering its parent's calls until `close`, a stop, or the parent's end."""
    from ddarm.interrupts import Interrupted, stop_on_signals
    from ddarm.ros.lifetime import PARENT_PID_VARIABLE, follow_parent
    from ddarm.ros.session import GraphSession

    os.environ[PARENT_PID_VARIABLE] = str(parent)
    follow_parent()
    try:
        with stop_on_signals(), GraphSession(folder, timeout=timeout) as session:
            connection.send(('ok', session.namespace))
            while True:
                method, arguments = connection.recv()
                if method == 'close':
                    break
                try:
                    answer = ('ok', getattr(session, method)(*arguments))
                    pickle.dumps(answer)
                except Exception as error:  # the caller's to raise; the session stays up for the next call
                    answer = ('error', _sendable(error))
                connection.send(answer)
        connection.send(('ok', None))
    except Interrupted:
        pass  # the stop reached the parent too (the terminal's process group, or the parent sent it)
    except Exception as error:
        connection.send(('error', _sendable(error)))
    finally:
        connection.close()
