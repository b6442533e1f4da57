"""A stop is never lost: one that lands where Python cannot raise it (a finaliser) is raised at the next
point where work can stop, and one that lands in a critical section waits for its end."""

import signal

import pytest

from ddarm.interrupts import Interrupted, check_stop, critical_section, stop_on_signals


class StoppedWhileCollected:
    def __del__(self):
        signal.raise_signal(signal.SIGTERM)  # the handler's raise ends here, "ignored" by Python


@pytest.mark.filterwarnings('ignore::pytest.PytestUnraisableExceptionWarning')  # the swallowed raise, on purpose
def test_a_stop_swallowed_by_a_finaliser_is_raised_at_the_next_check():
    with stop_on_signals():
        StoppedWhileCollected()
        with pytest.raises(Interrupted) as stopped:
            check_stop()
    assert stopped.value.exit_code == 143


def test_a_stop_in_a_critical_section_waits_for_its_end():
    finished = []
    with stop_on_signals():
        with pytest.raises(Interrupted) as stopped:
            with critical_section():
                signal.raise_signal(signal.SIGINT)
                finished.append(True)
    assert finished and stopped.value.exit_code == 130


def test_outside_the_block_the_old_handlers_are_back():
    before = signal.getsignal(signal.SIGINT)
    with stop_on_signals():
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before
    check_stop()  # no stop pending once the block is left
