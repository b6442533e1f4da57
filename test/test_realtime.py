"""Real time: the deadline schedule (absolute, never drifting), the scheduling asked of the node processes, and
its refusals, naming the parameter and what the OS needs. Behaviour and equality only: no timing is asserted."""

import errno
import os
import re
import shutil
import signal
import subprocess
import sys

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from ddarm.episodes.spec import EpisodeSpec
from ddarm.realtime import (PRIORITY_RANGE, STARTED_ON, ProcessScheduling, SchedulingError, checked_affinity,
                            deadline_ns, next_tick, run_ticks, scheduling_of)
from ddarm.ros.driver import GraphEpisodeError
from ddarm.ros.node_parameters import SchedulingOptions, node_parameters
from ddarm.episodes.spec import plan_episode
from ddarm_control.node import ControllerNode
from ddarm_sim.node import ENDED, RUNNING, PlantNode
from graph_helpers import InProcessGraph, overrides
from test_node_faults import Listener, spin_until

SPEC = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, duration=0.2)
NOT_A_CORE = max(STARTED_ON) + 1
MS = 1_000_000  # ns


def refuse_fifo(monkeypatch):
    """os.sched_setscheduler as an OS without CAP_SYS_NICE or an rtprio limit answers a SCHED_FIFO request."""
    def refused(thread, policy, parameters):
        if policy == os.SCHED_FIFO:
            raise PermissionError(errno.EPERM, 'Operation not permitted')
    monkeypatch.setattr(os, 'sched_setscheduler', refused)


def fifo_allowed() -> bool:
    """Whether this OS gives a process SCHED_FIFO (asked in a child: this process stays as it is)."""
    done = subprocess.run([sys.executable, '-c', 'import os; os.sched_setscheduler(0, os.SCHED_FIFO, '
                           'os.sched_param(1))'], capture_output=True)
    return done.returncode == 0


# The deadline schedule -----------------------------------------------------------------------------

def test_deadlines_are_products_of_the_period_and_never_drift():
    start, period = 123_456_789_012, 10 * MS
    for index in (0, 1, 6000, 360_000, 10**9):
        assert deadline_ns(start, period, index) == start + index * period
    assert deadline_ns(start, period, 360_000) == start + 3600 * 10**9  # an hour at 100 Hz, to the ns


def test_the_next_tick_skips_only_the_deadlines_an_overrun_passed():
    start, period = 1_000, 10 * MS
    assert next_tick(start, period, 3, start + 3 * period + 1) == 4  # on time
    assert next_tick(start, period, 3, start + 4 * period) == 4  # just at the next deadline: run it, late by 0
    assert next_tick(start, period, 3, start + 5 * period + period // 2) == 5  # 4 skipped, 5 run at once


class FakeTime:
    """A clock that moves 1 µs per reading and a stop event whose wait moves it, waking `latency` late."""

    def __init__(self, start, latency):
        self.now, self.latency, self.waits = start, latency, []

    def clock(self):
        self.now += 1_000
        return self.now

    def is_set(self):
        return False

    def wait(self, seconds):
        self.waits.append(round(seconds * 1e9))
        self.now += round(seconds * 1e9) + self.latency
        return False


def test_a_tick_wakes_a_margin_early_and_starts_on_its_deadline_over_an_hour_of_ticks():
    start, period, margin = 5 * 10**12, 10 * MS, 1 * MS
    fake = FakeTime(start, latency=995_000)  # each wake 0.995 ms late: within the margin
    ticks = []

    def tick(index, deadline):
        ticks.append((index, deadline, fake.now))
        return index < 360_000
    run_ticks(start, period, margin, tick, fake, clock=fake.clock)
    assert [index for index, _, _ in ticks] == list(range(1, 360_001))
    assert all(deadline == start + index * period for index, deadline, _ in ticks)
    assert all(deadline <= began <= deadline + 2_000 for _, deadline, began in ticks)
    assert all(wait <= period - margin for wait in fake.waits)


def test_a_tick_that_overruns_is_followed_by_one_late_tick_then_the_grid():
    start, period = 0, 10 * MS
    fake = FakeTime(start, latency=0)
    ticks = []

    def tick(index, deadline):
        ticks.append(index)
        if index == 3:
            fake.now += 2 * period + period // 2  # tick 3 takes 2.5 periods
        return index < 8
    run_ticks(start, period, 0, tick, fake, clock=fake.clock)
    assert ticks == [1, 2, 3, 5, 6, 7, 8]


# The scheduling and its refusals -------------------------------------------------------------------

def test_a_core_this_process_may_not_use_is_refused_naming_it():
    with pytest.raises(SchedulingError, match=re.escape(f'cpu_affinity = [{NOT_A_CORE}]: core {NOT_A_CORE} is not one '
                                                        f'this process may use (it may use {sorted(STARTED_ON)}')):
        checked_affinity([NOT_A_CORE])
    assert checked_affinity([min(STARTED_ON)]) == (min(STARTED_ON),)
    with pytest.raises(SchedulingError, match='named twice'):
        checked_affinity([min(STARTED_ON)] * 2)


def test_a_refused_priority_names_the_parameter_and_what_it_needs_and_changes_nothing(monkeypatch):
    before = scheduling_of(0)
    refuse_fifo(monkeypatch)
    with pytest.raises(SchedulingError) as refused:
        ProcessScheduling().apply(80, [min(STARTED_ON)])
    message = str(refused.value)
    assert message.startswith('realtime_priority = 80: the OS refused SCHED_FIFO priority 80 (EPERM: Operation not '
                              'permitted); it needs CAP_SYS_NICE')
    assert 'rtprio limit of at least 80' in message and 'ulimit -r' in message
    assert scheduling_of(0) == before  # the affinity applied first is given back


def test_the_parameters_are_declared_with_their_ranges(ros_context):
    plant = PlantNode(context=ros_context, parameter_overrides=overrides({'autostart': False}))
    controller = ControllerNode('computed_torque', context=ros_context,
                                parameter_overrides=overrides({'kp': [225.0] * 3, 'kv': [30.0] * 3}))
    try:
        for node in (plant, controller):
            priority = node.describe_parameter('realtime_priority')
            assert (priority.integer_range[0].from_value, priority.integer_range[0].to_value) == PRIORITY_RANGE
            assert node.get_parameter('realtime_priority').value == 0
            assert node.describe_parameter('cpu_affinity').type == Parameter.Type.INTEGER_ARRAY.value
            assert not node.set_parameters([Parameter('realtime_priority', value=99)])[0].successful
        margin = plant.describe_parameter('spin_margin').floating_point_range[0]
        assert (margin.from_value, margin.to_value) == (0.0, 1.0) and plant.settings.spin_margin == 0.001
        result = plant.set_parameters([Parameter('spin_margin', value=0.01)])[0]
        assert not result.successful and result.reason == 'spin_margin = 0.01 s must be less than the period, 0.01 s'
    finally:
        plant.destroy_node()
        controller.destroy_node()


@pytest.mark.parametrize('make', [
    lambda context, values: PlantNode(context=context, parameter_overrides=overrides({'autostart': False, **values})),
    lambda context, values: ControllerNode('computed_torque', context=context, parameter_overrides=overrides(
        {'kp': [225.0] * 3, 'kv': [30.0] * 3, **values})),
], ids=['plant', 'computed_torque'])
def test_a_node_refuses_a_scheduling_the_os_refuses_at_start_and_at_run_time(ros_context, monkeypatch, make):
    refuse_fifo(monkeypatch)
    with pytest.raises(SchedulingError, match='realtime_priority = 80: the OS refused SCHED_FIFO'):
        make(ros_context, {'realtime_priority': 80})
    node = make(ros_context, {})
    try:
        result = node.set_parameters([Parameter('realtime_priority', value=80)])[0]
        assert not result.successful and result.reason.startswith('realtime_priority = 80: the OS refused SCHED_FIFO')
        result = node.set_parameters([Parameter('cpu_affinity', value=[NOT_A_CORE])])[0]
        assert not result.successful and f'core {NOT_A_CORE} is not one this process may use' in result.reason
        assert node.get_parameter('realtime_priority').value == 0
        assert node.get_parameters_by_prefix('')['cpu_affinity'].value is None
    finally:
        node.destroy_node()


def test_an_episode_whose_scheduling_the_os_refuses_does_not_start_and_says_why(ros_context, monkeypatch):
    refuse_fifo(monkeypatch)
    graph = InProcessGraph(ros_context, SPEC)
    try:
        with pytest.raises(GraphEpisodeError, match=r"/plant refused the episode's parameters: "
                                                    r'realtime_priority = 80: the OS refused SCHED_FIFO'):
            graph.driver.run_episode(graph.executor, SPEC, graph.plan, mode='realtime',
                                     scheduling=SchedulingOptions(80))
        assert graph.plant.phase != RUNNING
    finally:
        graph.close()


def test_the_scheduling_goes_to_both_nodes_and_only_when_asked_for():
    plan = plan_episode(SPEC)
    plain = node_parameters(SPEC, plan, 'realtime')
    assert not {'realtime_priority', 'cpu_affinity', 'spin_margin'} & set(plain['plant']['ros__parameters'])
    asked = node_parameters(SPEC, plan, 'realtime', SchedulingOptions(50, (1,), 0.0005))
    assert {key: asked['plant']['ros__parameters'][key] for key in ('realtime_priority', 'cpu_affinity',
                                                                     'spin_margin')} == {
        'realtime_priority': 50, 'cpu_affinity': [1], 'spin_margin': 0.0005}
    controller = asked['computed_torque']['ros__parameters']
    assert (controller['realtime_priority'], controller['cpu_affinity']) == (50, [1])
    assert 'spin_margin' not in controller


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which('setpriv') is None,
                    reason='needs root and setpriv to take CAP_SYS_NICE away from a child')
def test_a_node_started_without_cap_sys_nice_refuses_to_start_naming_the_priority():
    done = subprocess.run(['setpriv', '--bounding-set', '-sys_nice', '--inh-caps', '-sys_nice', sys.executable,
                           '-m', 'ddarm_sim.node', '--ros-args', '-p', 'realtime_priority:=80'],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stdout + done.stderr
    assert 'plant: refused to start: realtime_priority = 80: the OS refused SCHED_FIFO priority 80 (EPERM' in done.stdout


# Real-time episodes ---------------------------------------------------------------------------------

def test_a_reset_during_a_real_time_episode_stops_its_ticks_and_the_end_of_one_ends_them(ros_context):
    plant = PlantNode(context=ros_context, parameter_overrides=overrides(
        {'mode': 'realtime', 'period': 0.01, 'max_samples': 20, 'autostart': False}))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(plant)
    listener = Listener(ros_context, executor, command_publisher=True)
    try:
        plant.start_episode()
        spin_until(executor, lambda: plant.phase == RUNNING)
        first = plant.ticks.thread
        plant.start_episode()  # mid-episode: the old ticks end before the new episode's state is set
        assert not first.is_alive() and plant.ticks.thread is None
        spin_until(executor, lambda: listener.ends() == ['complete'])
        assert plant.phase == ENDED
        plant.ticks.thread.join(timeout=10)
        assert not plant.ticks.thread.is_alive()
        report = listener.values()[-1]
        assert report['sample'] == '20' and report['sched_policy'] == scheduling_of(0).policy
    finally:
        executor.shutdown()
        listener.node.destroy_node()
        plant.destroy_node()


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_a_plant_ticking_in_real_time_stops_cleanly_on_a_signal(ros_context, signum):
    process = subprocess.Popen([sys.executable, '-m', 'ddarm_sim.node', '--ros-args', '-p', 'mode:=realtime'],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    executor = SingleThreadedExecutor(context=ros_context)
    listener = Listener(ros_context, executor, command_publisher=True)
    try:
        spin_until(executor, lambda: 'started' in [values['event'] for values in listener.values()], timeout=60)
    finally:
        process.send_signal(signum)
        output, _ = process.communicate(timeout=20)
        executor.shutdown()
        listener.node.destroy_node()
    assert process.returncode == 0 and 'Traceback' not in output, output


@pytest.mark.skipif(not fifo_allowed(), reason='this OS refuses SCHED_FIFO (no CAP_SYS_NICE, no rtprio limit)')
def test_a_real_time_episode_with_priority_and_affinity_runs_and_its_report_names_the_scheduling():
    from ddarm.ros.driver import realtime_warnings
    from ddarm.ros.session import run_graph_episode

    core = max(STARTED_ON)
    result = run_graph_episode(SPEC, realtime=True, scheduling=SchedulingOptions(10, (core,), 0.0005))
    report = result.plant_report
    assert report['event'] == 'complete' and report['mode'] == 'realtime'
    assert (report['sched_policy'], report['sched_priority'], report['cpu_affinity'], report['spin_margin_s']) == (
        'SCHED_FIFO', '10', f'[{core}]', '0.0005')
    assert {'period_jitter_p99_ms', 'tick_lateness_max_ms', 'deadline_misses'} <= set(report)
    assert len(result.scored('errors')) == 21
    report = {**report, 'deadline_misses': '2'}  # as a loaded machine might: the warning names the scheduling
    assert realtime_warnings(report)[-1].endswith(f'the plant ran SCHED_FIFO priority 10 on cores [{core}])')


@pytest.mark.parametrize('arguments, problem', [
    (['--cpu-affinity', '0'], '--cpu-affinity sets the node processes of an episode through ROS: add --realtime'),
    (['--realtime', '--cpu-affinity', str(NOT_A_CORE)],
     f'--cpu-affinity = [{NOT_A_CORE}]: core {NOT_A_CORE} is not one this process may use'),
    (['--realtime', '--spin-margin', '0.01'], '--spin-margin 0.01: not in [0, the period 0.01)'),
])
def test_ddarm_episode_refuses_a_scheduling_it_cannot_give_before_any_node_starts(capsys, arguments, problem):
    from ddarm.cli.main import main

    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', *arguments]) == 2
    assert problem in capsys.readouterr().err


def test_ddarm_episode_takes_priorities_from_1_to_98(capsys):
    from ddarm.cli.main import build_parser

    parser = build_parser()
    arguments = ['episode', '--controller', 'computed_torque', '--omega', '15', '--realtime']
    assert parser.parse_args([*arguments, '--realtime-priority', '98']).realtime_priority == 98
    for refused in ('0', '99'):
        with pytest.raises(SystemExit):
            parser.parse_args([*arguments, '--realtime-priority', refused])
        assert f'{refused} is not in [1, 98]' in capsys.readouterr().err
