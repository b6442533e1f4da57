"""A graph session in a process of its own: it records and scores as the in-process session does, raises the
child's refusals in the caller with the session still usable, and a dead child is named, never waited on."""

import os
import signal

import pytest

from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec
from ddarm.recording.bags import BagError
from ddarm.ros.session_process import SessionProcess, SessionProcessError

SPEC = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, duration=0.3)


def test_an_episode_through_a_session_process_scores_as_in_process(tmp_path):
    with SessionProcess(tmp_path / 'nodes') as session:
        (tmp_path / 'taken').mkdir()
        with pytest.raises(BagError, match='exists already'):
            session.record_and_score(SPEC, tmp_path / 'taken')
        _, scored = session.record_and_score(SPEC, tmp_path / 'bag', command='test')
    expected = run_episode(SPEC)
    assert (scored['I1'], scored['I2'], scored['I']) == (expected.I1[0], expected.I2[0], expected.I[0])
    assert scored['bag'] == str(tmp_path / 'bag')


def test_a_dead_session_process_is_named_at_the_next_call(tmp_path):
    session = SessionProcess(tmp_path / 'nodes')
    try:
        os.kill(session._process.pid, signal.SIGKILL)
        session._process.join()
        with pytest.raises(SessionProcessError, match='exited with code -9'):
            session.prepare(SPEC)
    finally:
        session.close()
