"""Progress of a long command (a search, a Pareto front, a reproduction): episodes done, the best so far, time left.

One interface for two kinds of reader. On a terminal it is a tqdm bar redrawn in place; written to a
log file or a CI console, where carriage returns pile up as garbage, it is plain lines at a slow pace.
"""

from __future__ import annotations

import sys
import time
from typing import Callable, TextIO

from tqdm import tqdm

from ddarm.reporting.text import TerminalStream, terminal_text

# A log gains a line at most this often: enough to see a run is alive, few enough to read the log.
PLAIN_INTERVAL_S = 5.0


class Progress:
    """Shows `label`'s episodes done out of `total` (None: unknown), the best index so far and the time left.

    On a TTY `stream`: a tqdm bar, done/total with tqdm's time left and the best as its postfix. On any
    other stream: lines without carriage returns, at most one every PLAIN_INTERVAL_S seconds and always
    a last one at close, e.g. `search: 1200/4000 episodes, best I = 0.3701, about 12 s left` (the last
    says the time taken instead). `quiet` (a command printing --json) shows nothing. `index_name` is the
    name shown before a numeric best; `clock` (seconds, monotonic) paces and times the plain lines; `position`
    is the bar's line on the terminal, one per bar shown at once (tqdm's).
    Used as a context manager, it is closed on leaving the block, however the block ends.
    """

    def __init__(self, total: int | None, label: str, stream: TextIO | None = None, *, quiet: bool = False,
                 index_name: str = 'I', clock: Callable[[], float] = time.monotonic, position: int = 0) -> None:
        self.total, self.label, self.index_name, self.position = total, label, index_name, position
        self.stream = sys.stderr if stream is None else stream
        self.clock = clock
        self.quiet, self.closed = quiet, False
        self.done, self.best = 0, None
        self.started = self.last_line = clock()
        self._bar = None
        if not quiet and self.stream.isatty():
            # A bar below the first is cleared when it ends: tqdm would redraw it, finished, over the first line.
            # tqdm's carriage returns and cursor moves go to the terminal itself, its texts shown as terminal_text.
            terminal = self.stream.target if isinstance(self.stream, TerminalStream) else self.stream
            self._bar = tqdm(total=total, desc=terminal_text(label), unit='episode', file=terminal,
                             dynamic_ncols=True, position=position, leave=position == 0)

    def update(self, done: int, best: float | str | None = None) -> None:
        """`done` episodes finished so far (a count, not an increment); `best` the best index so far, a number
        (shown as `best <index_name> = 0.3701`) or a short text (`best <text>`); None keeps the last one given."""
        if self.quiet or self.closed:
            return
        self.done = done
        if best is not None:
            self.best = best
        if self._bar is not None:
            if best is not None:
                self._bar.set_postfix_str(terminal_text(self._best_text()), refresh=False)
            self._bar.update(done - self._bar.n)
        elif self.clock() - self.last_line >= PLAIN_INTERVAL_S:
            self._write_line(final=False)

    def close(self) -> None:
        """Show the final state (the bar left in place, or the last plain line); later calls do nothing."""
        if self.quiet or self.closed:
            return
        self.closed = True
        if self._bar is not None:
            self._bar.close()
        elif self.done:  # a command refused before its first batch shows no progress line
            self._write_line(final=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exception) -> None:
        self.close()

    def _best_text(self) -> str:
        if isinstance(self.best, str):
            return f'best {self.best}'
        return f'best {self.index_name} = {float(self.best):.4g}'

    def _write_line(self, final: bool) -> None:
        now = self.clock()
        elapsed = now - self.started
        parts = [f'{self.label}: {self.done}/{self.total} episodes' if self.total is not None
                 else f'{self.label}: {self.done} episodes']
        if self.best is not None:
            parts.append(self._best_text())
        if final:
            parts.append(f'{_duration(elapsed)} elapsed')
        elif self.total is not None and 0 < self.done < self.total:
            # The rate so far: searches run episodes in batches of one size, so it changes little.
            parts.append(f'about {_duration(elapsed * (self.total - self.done) / self.done)} left')
        self.stream.write(', '.join(parts) + '\n')
        self.stream.flush()
        self.last_line = now


def _duration(seconds: float) -> str:
    if seconds < 10:
        return f'{seconds:.1f} s'
    if seconds < 100:
        return f'{seconds:.0f} s'
    if seconds < 6000:
        return f'{seconds / 60:.0f} min'
    return f'{seconds / 3600:.1f} h'
