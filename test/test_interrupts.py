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


def test_a_stop_a_library_turned_into_its_own_error_ends_as_the_stop_and_is_not_printed(capsys):
    """SIGTERM while numba compiled: the raise landed in a ctypes callback (printed as "Exception ignored") and numba
    then failed with RuntimeError('no compiled object yet'), a traceback."""
    def library_call():
        try:
            StoppedWhileCollected()  # the stop lands where it cannot be raised
        finally:
            raise RuntimeError('no compiled object yet')  # and the library fails on what it left undone

    with pytest.raises(Interrupted) as stopped:
        with stop_on_signals():
            library_call()
    assert stopped.value.exit_code == 143 and isinstance(stopped.value.__cause__, RuntimeError)
    assert 'Exception ignored' not in capsys.readouterr().err


def test_an_error_without_a_stop_is_left_as_it_is():
    with pytest.raises(RuntimeError, match='a bug'):
        with stop_on_signals():
            raise RuntimeError('a bug')
