"""ddarm.tuning.jobs: searches on several processes give what they give in turn; a job's failure, a worker's
death and a bad job list are named; no worker outlives the call."""

import os

import numpy as np
import pytest

import job_helpers
from ddarm.episodes.spec import EpisodeSpec
from ddarm.tuning.jobs import Job, JobError, run_jobs


def _searches():
    jobs = []
    for controller in ('pd_gravity', 'computed_torque'):
        template = EpisodeSpec(controller=controller, kp=(1.0,) * 3, kv=(1.0,) * 3, duration=0.5,
                               delay=0 if controller == 'pd_gravity' else 1)
        for index in ('I1', 'I'):
            jobs.append(Job((controller, index), f'{controller} {index}', job_helpers.search, (template, index, 300),
                            total=300, priority=len(jobs)))
    return jobs



def test_searches_on_two_workers_equal_the_searches_in_turn():
    heard = []
    parallel = run_jobs(_searches(), 2, on_progress=lambda job, episodes, best: heard.append((job.key, episodes)))
    serial = run_jobs(_searches(), 1)
    assert parallel.keys() == serial.keys()
    for key in serial:
        for got, expected in zip(parallel[key], serial[key]):
            np.testing.assert_array_equal(got, expected)  # bit for bit
    assert {key for key, _ in heard} == set(serial)  # every job reported its progress through the queue
    assert all(0 < episodes <= 300 for _, episodes in heard)


def test_a_job_gets_the_results_it_needs_and_waits_for_them():
    jobs = [Job('sum', 'sum', job_helpers.add, needs=('a', 'b')),
            Job('a', 'a', job_helpers.square, (3,)), Job('b', 'b', job_helpers.square, (4,))]
    started = []
    for workers in (1, 2):
        started.clear()
        results = run_jobs(jobs, workers, on_start=lambda job: started.append(job.key))
        assert results == {'a': 9, 'b': 16, 'sum': 25}
        assert started[-1] == 'sum'


def test_jobs_start_by_priority_among_those_ready():
    jobs = [Job(name, name, job_helpers.square, (1,), priority=priority)
            for name, priority in (('low', 0.0), ('high', 2.0), ('middle', 1.0))]
    started = []
    run_jobs(jobs, 1, on_start=lambda job: started.append(job.key))
    assert started == ['high', 'middle', 'low']


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_failing_job_raises_its_own_error_and_ends_the_workers():
    pids = run_jobs([Job(number, str(number), job_helpers.worker_pid) for number in range(2)], 2)
    assert not any(_alive(pid) for pid in pids.values())
    with pytest.raises(ValueError, match='no such gain: kq'):
        run_jobs([Job('bad', 'bad', job_helpers.refuses), Job('ok', 'ok', job_helpers.square, (2,))], 2)


def test_a_worker_that_dies_in_its_job_is_named_not_waited_for():
    with pytest.raises(JobError, match=r'the doomed job: its worker process ended \(exit code -9\)'):
        run_jobs([Job('doomed', 'the doomed job', job_helpers.dies), Job('ok', 'ok', job_helpers.square, (2,))], 2)


@pytest.mark.parametrize('jobs, message', [
    ([Job('a', 'a', job_helpers.add, needs=('b',))], "job 'a' needs \\['b'\\], which no job makes"),
    ([Job('a', 'a', job_helpers.add, needs=('b',)), Job('b', 'b', job_helpers.add, needs=('a',))],
     'need each other'),
    ([Job('a', 'a', job_helpers.square, (1,)), Job('a', 'again', job_helpers.square, (2,))], 'two jobs share a key'),
])
@pytest.mark.parametrize('workers', [1, 2])
def test_a_job_list_that_cannot_run_is_refused(jobs, message, workers):
    with pytest.raises(JobError, match=message):
        run_jobs(jobs, workers)


@pytest.mark.parametrize('workers', [0, -1, 1.5, None])
def test_workers_must_be_a_whole_number_of_at_least_one(workers):
    with pytest.raises(JobError, match='workers must be a whole number'):
        run_jobs([], workers)


def test_background_jobs_hand_over_every_result_even_the_last_as_they_end():
    from ddarm.tuning.jobs import BackgroundJobs

    jobs = [Job(name, name, job_helpers.square, (value,)) for name, value in (('a', 2), ('b', 3))]
    for workers in (1, 2):
        with BackgroundJobs(jobs, workers) as searches:
            while not searches.ready(['a', 'b']):  # the last result and the end of the jobs come together
                searches.wait_for_change()
            assert searches.wait() == {'a': 4, 'b': 9}
            searches.wait_for_change()  # all over: returns at once


def test_background_jobs_raise_a_jobs_failure_in_the_waiting_thread():
    from ddarm.tuning.jobs import BackgroundJobs

    with BackgroundJobs([Job('bad', 'bad', job_helpers.refuses)], 2) as searches:
        with pytest.raises(ValueError, match='no such gain: kq') as raised:
            searches.wait(['bad'])
    assert any("in the job 'bad'" in note for note in raised.value.__notes__)
