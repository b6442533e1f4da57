"""A run on disk: runs/<name>/ holds its bags, a JSON summary of every episode, the tuned YAML and a log."""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path
from typing import BinaryIO, Callable

import yaml

from ddarm.episodes.indices import INDICES
from ddarm.errors import DdarmError
from ddarm.recording import DEFAULT_ROOT
from ddarm.datafiles import is_missing, unreachable
from ddarm.recording.bags import BagError, checked_output_location, checked_output_path, child_path
from ddarm.interrupts import Interrupted, critical_section
from ddarm.strict_json import json_text

SUMMARY_NAME = 'summary.json'


def write_new_file(path: Path | str, write: Callable[[BinaryIO], None]) -> Path:
    """Make the new file `path` (checked_output_path: no '..', no symlink, not there yet) and `write` into it.

    A file that cannot be written whole (a full disk, a quota) is removed, so no part of it passes for the
    output, and the BagError names it: an OSError raised while writing would not (only opening names its file).
    """
    path = checked_output_path(path)
    try:
        file = path.open('xb')  # 'x': a file made there meanwhile is not overwritten either
    except OSError as error:
        raise BagError(f'{path}: cannot write it: {error.strerror or error}') from error
    try:
        with file:
            write(file)
    except OSError as error:
        path.unlink(missing_ok=True)
        raise BagError(f'{path}: cannot write it: {error.strerror or error}') from error
    return path


def write_new_text(path: Path | str, text: str) -> Path:
    """write_new_file of `text` as UTF-8."""
    return write_new_file(path, lambda file: file.write(text.encode('utf-8')))


def controller_yaml(controller: str, kp, kv, delay: int, period: float, provenance: str, *,
                    joint_names, urdf: str | Path | None = None, motion: str | Path | None = None,
                    duration: float | None = None) -> str:
    """A parameter file that `ros2 run ddarm_control <controller> --ros-args --params-file` loads as it is.

    The gains are keyed by joint name, as ros2_controllers write them (`gains: {<joint>: {p: K_p, d: K_v}}`,
    which ROS 2 reads as the parameters gains.<joint>.p and .d); `joint_names` are the controller's joints
    in the order of kp and kv. `urdf` (the controller's model) and `motion` (its joints and, with
    sampling:=timer, its reference) are written when given, as absolute paths, so the file is all the
    robot's controller node needs; with a motion, `duration` is the T the gains were tuned for (timer mode
    runs the motion over it).
    """
    names = list(joint_names)
    if not names or not all(isinstance(name, str) and name for name in names) or len(set(names)) != len(names):
        raise ValueError(f'joint_names must be distinct non-empty names, got {names!r}')
    if not len(kp) == len(kv) == len(names):
        raise ValueError(f'{len(names)} joint_names {names} for {len(kp)} kp and {len(kv)} kv values')
    parameters = {}
    for name, value in (('urdf', urdf), ('motion', motion)):
        if value:
            parameters[name] = str(Path(value).resolve())
    if motion and duration is not None:
        parameters['duration'] = float(duration)
    parameters.update({
        'gains': {name: {'p': float(p), 'd': float(d)} for name, p, d in zip(names, kp, kv)}, 'omega': 0.0,
        'delay': int(delay), 'period': float(period)})
    header = ''.join(f'# {line}\n' for line in provenance.splitlines())
    # Flow style for the innermost mappings: one line per joint, `<joint>: {p: …, d: …}`.
    return header + yaml.safe_dump({controller: {'ros__parameters': parameters}}, sort_keys=False,
                                   default_flow_style=None)


class RunFolder:
    """runs/<name>/: created new (never reused), with summary.json, run.log and bags/ when episodes are recorded.

    The summary is rewritten after every episode, so a run stopped part way leaves a true
    account of what finished. Its status is `running` from the start (with the process ID, so a
    run killed outright shows as a `running` whose process is gone), then `complete`, `failed`
    or `interrupted`. Used as a context manager, a run left by an exception is marked for it.
    """

    def __init__(self, name: str, root: Path | str = DEFAULT_ROOT, command: str = '') -> None:
        root = Path(root)
        self.path = self.checked_path(name, root)
        try:
            root.mkdir(exist_ok=True)  # its own folder exists (checked_root): a mistyped path grows no tree
            self.path.mkdir()
        except OSError as error:
            raise BagError(f'cannot create the run folder {self.path}: {error.strerror}') from error
        self.summary = {'name': name, 'command': command, 'started': time.strftime('%Y-%m-%dT%H:%M:%S%z'),
                        'status': 'running', 'pid': os.getpid(), 'episodes': []}
        self.finished = False
        self.log = logging.getLogger(f'ddarm.run.{name}')
        self.log.setLevel(logging.INFO)
        self._handler = _RunLog(self.path / 'run.log')
        self._handler.setFormatter(logging.Formatter('%(asctime)s %(levelname)s %(message)s'))
        self.log.addHandler(self._handler)
        self.log.info('run %s: %s', name, command)
        try:
            self._write_summary(self.summary)
        except BaseException:
            self._close_log()
            raise

    @staticmethod
    def checked_root(root: Path | str = DEFAULT_ROOT) -> Path:
        """A folder that can hold run folders: one that exists, or a new one in a folder that exists (as `runs`
        in a fresh checkout); refused before any work otherwise."""
        root = Path(root)
        if root.is_symlink():
            raise BagError(f'{root} is a symlink; refusing to write through it')
        failure = unreachable(root)
        if is_missing(failure) or isinstance(failure, NotADirectoryError):  # a new folder, checked as every output
            return checked_output_location(root)
        if failure is not None:  # a symlink loop on the way, a folder it may not search: the OS's reason
            raise BagError(f'{root}: {failure.strerror or failure}')
        if not root.is_dir():
            raise BagError(f'{root} is not a folder: it cannot hold run folders')
        return root

    @classmethod
    def checked_path(cls, name: str, root: Path | str = DEFAULT_ROOT) -> Path:
        """root/name if a new run folder can be made there; refused before any work otherwise."""
        return child_path(cls.checked_root(root), name)

    def bag_path(self, episode_name: str) -> Path:
        (self.path / 'bags').mkdir(exist_ok=True)
        return child_path(self.path / 'bags', episode_name)

    def add_episode(self, record: dict) -> None:
        self._write_summary({**self.summary, 'episodes': [*self.summary['episodes'], record]})
        self.log.info('episode %s: %s', record.get('name'), json.dumps(
            {key: record.get(key) for key in (*INDICES, 'diverged', 'bag')}))

    def record(self, key: str, value) -> None:
        """`value` in the summary as `key`, written at once (a part of the run that is not one episode's record)."""
        self._write_summary({**self.summary, key: value})

    def write_text(self, name: str, text: str) -> Path:
        path = write_new_text(self.path / name, text)
        self.log.info('wrote %s', path)
        return path

    def discard_bag(self, path: Path) -> None:
        """Remove this run's bag at `path`, left unfinished by a failing file system: no scorer accepts it, and the
        space it holds is what lets the summary still say how the run ended."""
        if not path.resolve().is_relative_to((self.path / 'bags').resolve()):
            raise BagError(f'{path} is not a bag of the run folder {self.path}')
        shutil.rmtree(path, ignore_errors=True)
        self.log.info('removed the unfinished bag %s', path)

    def finish(self, status: str, **extra) -> None:
        if self.finished:
            return
        with critical_section():  # the summary's last word is written whole, whatever signal comes
            summary = {**self.summary, 'status': status, 'finished': time.strftime('%Y-%m-%dT%H:%M:%S%z'), **extra}
            if self._handler.failure:
                summary['log_failure'] = self._handler.failure
            self._write_summary(summary)
            self.log.info('run %s', status)
            self._close_log()
            self.finished = True

    def _close_log(self) -> None:
        self.log.removeHandler(self._handler)
        self._handler.close()

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if kind is None:
            return
        try:  # a summary that cannot be written must not hide why the run ended
            if issubclass(kind, (Interrupted, KeyboardInterrupt)):
                self.log.info('%s', error or 'interrupted')
                self.finish('interrupted')
            else:
                self.log.error('%s: %s', kind.__name__, error)
                self.finish('failed', error=f'{kind.__name__}: {error}')
        except Exception as cleanup:
            if isinstance(error, (DdarmError, OSError)) and isinstance(cleanup, DdarmError):
                # Said on the same line as the failure: the summary left behind still claims the run is running.
                reason = (f'{error.filename}: {error.strerror}' if isinstance(error, OSError) and error.filename
                          else str(error))
                raise BagError(f'{reason}; and the run could not be marked failed: {cleanup}') from error
            error.add_note(f'while marking the run folder {self.path}: {type(cleanup).__name__}: {cleanup}')

    def _write_summary(self, summary: dict) -> None:
        """Write `summary` and make it the run's: one that JSON cannot hold or the disk cannot take is refused, and
        the summary written before stays the run's."""
        path, partial = self.path / SUMMARY_NAME, self.path / f'{SUMMARY_NAME}.partial'
        text = json_text(summary, indent=2)
        try:
            partial.write_text(text)
            partial.replace(path)  # atomic: a reader never sees half a summary
        except OSError as error:
            partial.unlink(missing_ok=True)
            raise BagError(f'{path}: cannot write the summary: {error.strerror or error}') from error
        self.summary = summary


class _RunLog(logging.FileHandler):
    """run.log, whose failure to take a line (a full disk) goes into the summary as `log_failure`, not onto the
    terminal as logging's traceback over the command's own message."""

    failure: str | None = None

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 (logging's name)
        if self.failure is None:
            error = sys.exc_info()[1]
            self.failure = f'{self.baseFilename}: cannot write the log: {getattr(error, "strerror", None) or error}'

    def close(self) -> None:
        try:  # closing flushes, and a flush that fails is one more line lost, not a reason to stop
            super().close()
        except OSError:
            self.handleError(None)
