"""Progress of a long command: a tqdm bar on a terminal, paced plain lines in a log, nothing when quiet."""

import io

from ddarm.reporting.progress import PLAIN_INTERVAL_S, Progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class Clock:
    """Seconds that pass only when the test says so."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_terminal_gets_a_bar_with_the_count_and_the_best_so_far():
    stream = Terminal()
    with Progress(4000, 'search', stream) as progress:
        progress.update(1200, 0.37012)
        progress.update(4000)
    text = stream.getvalue()
    assert '\r' in text and text.endswith('\n')
    last = text.split('\r')[-1]
    assert last.startswith('search: 100%') and '4000/4000' in last and 'best I = 0.3701' in last


def test_a_bar_of_unknown_length_counts_episodes_and_shows_a_best_given_as_text():
    stream = Terminal()
    with Progress(None, 'pareto', stream) as progress:
        progress.update(300, 'front of 12')
    last = stream.getvalue().split('\r')[-1]
    assert last.startswith('pareto: 300') and 'best front of 12' in last


def test_a_log_gets_a_line_at_most_every_interval_and_always_a_last_one():
    stream, clock = io.StringIO(), Clock()
    progress = Progress(4000, 'search', stream, clock=clock)
    progress.update(100, 0.9)
    assert stream.getvalue() == ''  # too soon for a line
    clock.now += PLAIN_INTERVAL_S
    progress.update(1000, 0.5)
    clock.now += 1.0
    progress.update(1100)  # within the interval of the last line: none
    clock.now += PLAIN_INTERVAL_S
    progress.update(2000, 0.37012)
    progress.close()
    progress.close()  # a second close adds nothing
    assert stream.getvalue().splitlines() == [
        'search: 1000/4000 episodes, best I = 0.5, about 15 s left',
        'search: 2000/4000 episodes, best I = 0.3701, about 11 s left',
        'search: 2000/4000 episodes, best I = 0.3701, 11 s elapsed',
    ]
    assert '\r' not in stream.getvalue()


def test_lines_of_unknown_length_name_the_index_and_give_no_time_left():
    stream, clock = io.StringIO(), Clock()
    with Progress(None, 'omega', stream, index_name='I1', clock=clock) as progress:
        clock.now += PLAIN_INTERVAL_S
        progress.update(50, 2.5)
        clock.now += 0.5
    assert stream.getvalue().splitlines() == ['omega: 50 episodes, best I1 = 2.5',
                                              'omega: 50 episodes, best I1 = 2.5, 5.5 s elapsed']


def test_a_block_left_by_an_exception_still_gets_its_last_line():
    stream, clock = io.StringIO(), Clock()
    try:
        with Progress(4000, 'reproduce', stream, clock=clock) as progress:
            progress.update(10)
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        pass
    assert stream.getvalue() == 'reproduce: 10/4000 episodes, 0.0 s elapsed\n'


def test_quiet_shows_nothing_on_a_terminal_or_a_log():
    for stream in (Terminal(), io.StringIO()):
        clock = Clock()
        with Progress(4000, 'search', stream, quiet=True, clock=clock) as progress:
            clock.now += 10 * PLAIN_INTERVAL_S
            progress.update(2000, 0.5)
        assert stream.getvalue() == ''
