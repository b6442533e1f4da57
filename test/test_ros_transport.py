"""What the lockstep path does to be cheap, checked for being right: stamps read from serialized messages, the node
processes' transport, messages built from arrays, and the bare round trip `ddarm bench --ros` compares against."""

import dataclasses
import re
import time

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from ddarm.ros.cdr import read_stamp
from ddarm.ros.interface import joint_state_msg, read_joint_state, time_msg
from ddarm.ros.round_trip import round_trips_in_process
from ddarm.samples import MessageError

JOINTS = ['joint_1', 'joint_2', 'joint_3']


@pytest.mark.parametrize('seconds', [0.0, 0.01, 1.23, 59.99, 3600.5, 2.0 ** 31 - 1.0])
def test_the_stamp_read_in_place_is_the_deserialized_one(seconds):
    state = joint_state_msg(JOINTS, seconds, np.ones(3), np.zeros(3), np.full(3, -2.0))
    clock = Clock(clock=time_msg(seconds))
    for message in (state, clock):
        data = serialize_message(message)
        stamp = read_stamp(data, 'a message')
        expected = deserialize_message(data, type(message))
        expected = expected.header.stamp if isinstance(message, JointState) else expected.clock
        assert (stamp.sec, stamp.nanosec) == (expected.sec, expected.nanosec)


@pytest.mark.parametrize('data, problem', [
    (b'', 'not a stamped message in little-endian CDR (0 bytes, encapsulation none)'),
    (b'\x00\x01\x00\x00\x01\x00', 'not a stamped message in little-endian CDR (6 bytes'),
    (b'\x00\x00\x00\x00' + b'\x00' * 12, 'encapsulation 0000'),  # big-endian: the bag reader refuses it
    (b'\x00\x07\x00\x00' + b'\x00' * 12, 'encapsulation 0007'),  # XCDR2
    (b'\x00\x01\x00\x00' + (1).to_bytes(4, 'little') + (10 ** 9).to_bytes(4, 'little'), 'not below 10^9'),
])
def test_what_is_no_stamped_message_is_refused_naming_it(data, problem):
    with pytest.raises(MessageError, match=re.escape(problem)) as refused:
        read_stamp(data, 'joint state on /joint_states')
    assert 'joint state on /joint_states' in str(refused.value)


def test_arrays_go_into_a_state_and_come_back_exactly():
    q, v, effort = np.array([0.1, -2.5, 1e-300]), np.array([3.0, 0.0, -0.0]), np.array([1e6, -7.25, 2.0])
    msg = deserialize_message(serialize_message(joint_state_msg(JOINTS, 0.37, q, v, effort)), JointState)
    sample = read_joint_state(msg, JOINTS, 0.01, need_effort=True)
    assert sample.n == 37
    np.testing.assert_array_equal(sample.q, q)
    np.testing.assert_array_equal(sample.v, v)
    np.testing.assert_array_equal(sample.effort, effort)
    empty = joint_state_msg(JOINTS, 0.0, effort=effort)
    assert list(empty.position) == list(empty.velocity) == [] and list(empty.effort) == effort.tolist()


def test_a_state_in_our_order_and_a_reordered_one_read_the_same():
    q = np.array([1.0, 2.0, 3.0])
    ours = read_joint_state(joint_state_msg(JOINTS, 0.0, q, -q), JOINTS, 0.01)
    theirs = read_joint_state(joint_state_msg(JOINTS[::-1], 0.0, q[::-1], -q[::-1]), JOINTS, 0.01)
    np.testing.assert_array_equal(ours.q, theirs.q)
    np.testing.assert_array_equal(ours.v, theirs.v)


@pytest.mark.parametrize('serialized', [False, True], ids=['messages', 'serialized'])
def test_the_bare_round_trip_makes_every_round_trip(serialized):
    figures = round_trips_in_process(200, serialized=serialized)
    assert figures['round_trips'] == 200
    assert figures['latency_p50_ms'] <= figures['latency_p99_ms']


def test_a_stopped_node_is_waited_for_until_the_graph_forgets_it_and_named_if_it_never_does():
    import rclpy

    from ddarm.ros.driver import GraphDriver, GraphEpisodeError
    from ddarm.ros.session import session_namespace

    namespace = session_namespace()
    contexts = [rclpy.Context(), rclpy.Context()]
    for context in contexts:
        rclpy.init(context=context)
    driver = GraphDriver(namespace=namespace, context=contexts[0])
    other = rclpy.create_node('pd_gravity', namespace=namespace, context=contexts[1])
    try:
        deadline = time.monotonic() + 20
        while other.get_fully_qualified_name() not in {f'{ns.rstrip("/")}/{name}' for name, ns in
                                                       driver.get_node_names_and_namespaces()}:
            assert time.monotonic() < deadline, 'the driver never saw the node'
            time.sleep(0.05)
        with pytest.raises(GraphEpisodeError, match=f'{namespace}/pd_gravity still on the graph'):
            driver.wait_until_gone(['pd_gravity'], timeout=0.3)
        other.destroy_node()
        rclpy.try_shutdown(context=contexts[1])
        driver.wait_until_gone(['pd_gravity'])
        driver.wait_until_gone(['computed_torque'])  # never there
    finally:
        driver.destroy_node()
        for context in contexts:
            rclpy.try_shutdown(context=context)


def test_a_node_name_discovery_keeps_without_any_endpoint_is_no_node_on_the_graph():
    """On a busy machine discovery kept a stopped controller's name for good, with no endpoint: make run failed
    with 'still on the graph 25 s after its process ended'. Such a name is no node, and does not double a live one."""
    import rclpy

    from ddarm.ros.driver import GraphDriver
    from ddarm.ros.session import session_namespace

    namespace = session_namespace()
    contexts = [rclpy.Context(), rclpy.Context(), rclpy.Context()]
    for context in contexts:
        rclpy.init(args=[], context=context)
    driver = GraphDriver(namespace=namespace, context=contexts[0])
    # A name without endpoints, as the graph shows a departed node's: no rosout, parameter services or events.
    ghost = rclpy.create_node('pd_gravity', namespace=namespace, context=contexts[1], enable_rosout=False,
                              start_parameter_services=False)
    ghost.destroy_publisher(ghost._parameter_event_publisher)
    live = None
    try:
        deadline = time.monotonic() + 20
        while ('pd_gravity', namespace) not in driver.get_node_names_and_namespaces():
            assert time.monotonic() < deadline, 'the driver never heard of the name'
            time.sleep(0.05)
        assert driver.graph_nodes()[f'{namespace}/pd_gravity'] == 0
        driver.wait_until_gone(['pd_gravity'], timeout=0.3)
        live = rclpy.create_node('pd_gravity', namespace=namespace, context=contexts[2])
        while driver.graph_nodes()[f'{namespace}/pd_gravity'] == 0:
            assert time.monotonic() < deadline + 20, 'the driver never saw the live node'
            time.sleep(0.05)
        assert [name for name, ns in driver.get_node_names_and_namespaces() if ns == namespace].count('pd_gravity') == 2
        assert driver.graph_nodes()[f'{namespace}/pd_gravity'] == 1
    finally:
        for node in (driver, ghost, live):
            if node is not None:
                node.destroy_node()
        for context in contexts:
            rclpy.try_shutdown(context=context)


def test_a_request_that_may_be_repeated_is_sent_again_until_a_reply_comes(monkeypatch):
    """A service drops its reply if the client's reader has not matched yet: a controller once never answered its
    parameters on a busy machine, and the episode timed out."""
    import rclpy
    from rclpy.task import Future

    import ddarm.ros.driver
    from ddarm.ros.driver import GraphDriver, GraphEpisodeError
    from ddarm.ros.executors import node_executor
    from ddarm.ros.session import session_namespace

    monkeypatch.setattr(ddarm.ros.driver, 'RESEND_AFTER', 0.2)
    context = rclpy.Context()
    rclpy.init(args=[], context=context)
    driver = GraphDriver(namespace=session_namespace(), context=context)
    executor = node_executor(context)
    executor.add_node(driver)
    sent = []

    def send():  # the first reply is lost; the second comes
        sent.append(Future())
        if len(sent) == 2:
            sent[-1].set_result('the reply')
        return sent[-1]

    try:
        assert driver._answer(executor, send, time.monotonic() + 30, 'a reply', lambda: None) == 'the reply'
        assert len(sent) == 2
        sent.clear()
        with pytest.raises(GraphEpisodeError, match='timed out waiting for a reply'):
            driver._answer(executor, send, time.monotonic() + 1, 'a reply', lambda: None, again=False)
        assert len(sent) == 1
    finally:
        executor.shutdown()
        driver.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_killed_node_of_a_session_is_forgotten_within_its_short_lease_and_the_next_law_runs(tmp_path):
    import os
    import signal

    from ddarm.episodes.spec import EpisodeSpec
    from ddarm.ros.session import NODE_LEASE_S, GraphSession

    spec = EpisodeSpec(controller='pd_gravity', kp=(225.0,) * 3, kv=(30.0,) * 3, duration=0.05)
    with GraphSession(tmp_path / 'nodes') as session:
        session.ready(spec)
        killed = session.processes['pd_gravity']
        os.kill(killed.pid, signal.SIGKILL)  # no goodbye: discovery forgets it only when its lease runs out
        killed.wait()
        # Fast DDS's default lease, 20 s, is forgotten 17 to 20 s after the kill; the session's nodes announce 5 s.
        session.driver.wait_until_gone(['pd_gravity'], timeout=3 * NODE_LEASE_S)
        session.processes.pop('pd_gravity')
        episode = session.run(dataclasses.replace(spec, controller='computed_torque'))
        assert not episode.diverged[0] and episode.I1[0] > 0


def test_a_session_started_before_its_run_folder_keeps_its_nodes_files_there_however_it_ends(tmp_path):
    """`ddarm tune`'s session: nodes started while the search runs (in a folder of the session's own), told to stop
    before the report, their logs copied into the run folder once they stopped; also when the session fails."""
    from ddarm.episodes.spec import EpisodeSpec
    from ddarm.ros.session import GraphSession

    spec = EpisodeSpec(controller='pd_gravity', kp=(225.0,) * 3, kv=(30.0,) * 3, duration=0.05)
    with GraphSession() as session:
        session.prepare(spec)
        own = session.folder
        session.keep_files_in(tmp_path / 'run' / 'nodes')
        episode = session.run(spec)
        processes = list(session.processes.values())
        session.stop_nodes()
        assert not session.processes
        session.close()
    assert not episode.diverged[0] and all(process.returncode is not None for process in processes)
    assert not own.exists(), "the session's own folder is removed"
    kept = tmp_path / 'run' / 'nodes'
    assert {'plant.log', 'pd_gravity.log', 'plant.parameters.yaml', 'fastdds_profile.xml'} <= {
        path.name for path in kept.iterdir()}
    assert 'episode complete' in (kept / 'plant.log').read_text()
    with pytest.raises(RuntimeError, match='the search failed'), GraphSession() as session:
        session.prepare(spec)
        session.keep_files_in(tmp_path / 'failed' / 'nodes')
        raise RuntimeError('the search failed')
    assert (tmp_path / 'failed' / 'nodes' / 'plant.parameters.yaml').is_file()


def test_a_users_own_fast_dds_profile_is_kept_for_a_sessions_nodes(tmp_path, monkeypatch):
    from ddarm.ros.session import node_environment

    assert node_environment(tmp_path)['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(tmp_path / 'fastdds_profile.xml')
    for variable in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
        with monkeypatch.context() as patch:
            patch.setenv(variable, '/etc/mine.xml')
            environment = node_environment(tmp_path / 'other')
            assert environment[variable] == '/etc/mine.xml'
            assert all(environment.get(name) in (None, '/etc/mine.xml') for name in
                       ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'))


def _recording():
    """A complete recording of a short episode, serialized as the driver hears it (states of the in-process run)."""
    from ddarm.episodes.engine import run_episode
    from ddarm.episodes.spec import EpisodeSpec, check_episode
    from ddarm.ros.driver import Recording

    spec = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, duration=0.05)
    plan = check_episode(spec)
    ran = run_episode(spec, plan)
    joints = list(plan.joint_names)
    recording = Recording(plan.k_max, spec.controller, plant_report={'event': 'complete'})
    for n in range(plan.k_max + 2):
        state = min(n, plan.k_max)
        torque = None if n == 0 else ran.torque[0, n - 1]
        recording.states[n] = serialize_message(joint_state_msg(joints, n * spec.period, ran.q[0, state],
                                                                ran.v[0, state], torque))
    for n in range(plan.k_max + 1):
        recording.commands[n] = serialize_message(joint_state_msg(joints, n * spec.period,
                                                                  effort=ran.command[0, n]))
    return spec, plan, recording, joints


def test_recorded_bytes_score_as_the_episode_and_garbage_is_refused_naming_the_sample():
    from ddarm.ros.driver import GraphEpisodeError, result_from_recording

    spec, plan, recording, joints = _recording()
    topics = {'states': '/s/joint_states', 'commands': '/s/effort_command'}
    assert result_from_recording(spec, plan, recording, joints, topics).I1[0] > 0
    for field, problem in (('commands', 'unusable command on /s/effort_command: sample 2'),
                           ('states', 'unusable joint state on /s/joint_states: sample 2')):
        for broken in (getattr(recording, field)[2][:16], b'\x00\x01\x00\x00' + b'\xff' * 40):
            damaged = dict(getattr(recording, field))
            damaged[2] = broken
            copy = type(recording)(recording.k_max, recording.controller, plant_report=recording.plant_report,
                                   **{'states': recording.states, 'commands': recording.commands, field: damaged})
            with pytest.raises(GraphEpisodeError, match=re.escape(problem)):
                result_from_recording(spec, plan, copy, joints, topics)
