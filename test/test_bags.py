"""Episodes recorded as rosbag2 bags and scored from the bag alone; broken bags refused by name (FAULTS.md 17-19)."""

import json
import os

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, Writer

from ddarm_tuner.bags import (TYPESTORE, BagError, EpisodeBagWriter, checked_output_path, child_path,
                              read_episode_bag, score_bag)
from ddarm_tuner.cli import main
from ddarm_tuner.episodes import EpisodeSpec, run_episode
from ddarm_tuner.ros_episode import episode_record, run_graph_episode
from graph_helpers import InProcessGraph

SPECS = {
    'computed_torque': EpisodeSpec(controller='computed_torque', kp=(900.0,) * 3, kv=(60.0,) * 3, tau=0.1,
                                   torque_limit='paper'),
    'pd_gravity': EpisodeSpec(controller='pd_gravity', kp=(28000.0, 27000.0, 3500.0), kv=(1760.0, 1700.0, 220.0),
                              delay=0, tau=0.1, torque_limit='paper'),
}


def record(context, spec, path, storage='mcap'):
    graph = InProcessGraph(context, spec)
    with EpisodeBagWriter(path, episode_record(spec, graph.plan, 'ros-lockstep', 'test'), storage) as bag:
        graph.bag = bag
        try:
            result = graph.run()
            bag.close(complete=True)
        finally:
            graph.close()
    return result


@pytest.fixture(scope='module')
def good_bag(tmp_path_factory):
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    path = tmp_path_factory.mktemp('bags') / 'good'
    try:
        record(context, SPECS['computed_torque'], path)
    finally:
        rclpy.try_shutdown(context=context)
    return path


@pytest.mark.parametrize('controller', ['computed_torque', 'pd_gravity'])
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_scores_from_the_bag_equal_the_in_process_indices(ros_context, tmp_path, controller, storage):
    spec = SPECS[controller]
    record(ros_context, spec, tmp_path / 'bag', storage)
    scored, reference = score_bag(tmp_path / 'bag'), run_episode(spec)
    assert np.any(np.abs(reference.command) > reference.plan.torque_limit)  # the limits matter here
    for key in ('I1', 'I2', 'I'):
        assert scored[key] == pytest.approx(reference.indices[key], rel=1e-9)
    assert scored['spec'] == spec.to_dict()


def test_ddarm_episode_ros_bag_records_what_it_prints(tmp_path, capsys):
    arguments = ['episode', '--controller', 'pd_gravity', '--omega', '10', '--delay', '0', '--tau', '0.05',
                 '--limited', '--ros', '--bag', str(tmp_path / 'bag'), '--json']
    assert main(arguments) == 0
    printed = json.loads(capsys.readouterr().out)
    assert main(['score', str(tmp_path / 'bag'), '--json']) == 0
    scored = json.loads(capsys.readouterr().out)
    for key in ('I1', 'I2', 'I', 'max_abs_error_deg', 'max_abs_torque', 'spec'):
        assert scored[key] == printed[key]
    episode = read_episode_bag(tmp_path / 'bag').episode
    assert episode['command'].startswith('ddarm episode --controller pd_gravity')


def copy_bag(source, target, keep=lambda topic: True, transform=None):
    """A copy of a bag with some topics dropped or some messages changed."""
    with Reader(source) as reader, Writer(target, version=9) as writer:
        connections = {}
        for connection in reader.connections:
            if keep(connection.topic):
                connections[connection.id] = writer.add_connection(connection.topic, connection.msgtype,
                                                                   typestore=TYPESTORE)
        for connection, timestamp, raw in reader.messages():
            if connection.id not in connections:
                continue
            if transform is not None:
                from ddarm_tuner.bags import deserialize

                message = transform(connection.topic, deserialize(raw, connection.msgtype))
                raw = TYPESTORE.serialize_cdr(message, connection.msgtype)
            writer.write(connections[connection.id], timestamp, raw)
        writer.set_custom_data('ddarm.status', 'complete')
    return target


def test_a_bag_without_the_commands_is_refused(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / 'no_commands', keep=lambda topic: topic != '/effort_command')
    with pytest.raises(BagError, match=r"missing topics \['/effort_command'\]"):
        score_bag(bag)


def test_a_bag_from_another_robot_is_refused(good_bag, tmp_path):
    def rename(topic, message):
        if topic == '/joint_states':
            message.name = ['shoulder', 'elbow', 'wrist']
        return message

    bag = copy_bag(good_bag, tmp_path / 'foreign', transform=rename)
    with pytest.raises(BagError, match='another robot'):
        score_bag(bag)


def test_a_bag_missing_samples_is_incomplete(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / 'holes', transform=lambda topic, message: message)
    with Reader(bag) as reader:
        kept = [(c, t, r) for c, t, r in reader.messages() if not (c.topic == '/joint_states' and t > 5e8)]
    truncated = tmp_path / 'half'
    with Reader(bag) as reader, Writer(truncated, version=9) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE)
                       for c in reader.connections}
        for connection, timestamp, raw in kept:
            writer.write(connections[connection.id], timestamp, raw)
        writer.set_custom_data('ddarm.status', 'complete')
    with pytest.raises(BagError, match='missing: the episode is incomplete'):
        score_bag(truncated)


def test_a_recording_that_never_closed_is_reported_incomplete(good_bag, tmp_path):
    killed = tmp_path / 'killed'
    killed.mkdir()
    for item in good_bag.iterdir():
        if item.name != 'metadata.yaml':  # what a SIGKILL leaves: storage without metadata
            (killed / item.name).write_bytes(item.read_bytes())
    with pytest.raises(BagError, match='never closed'):
        score_bag(killed)


def test_a_truncated_storage_file_is_unreadable_not_scored(good_bag, tmp_path):
    broken = tmp_path / 'broken'
    broken.mkdir()
    for item in good_bag.iterdir():
        data = item.read_bytes()
        (broken / item.name).write_bytes(data if item.name == 'metadata.yaml' else data[: len(data) // 2])
    with pytest.raises(BagError, match='unreadable|missing'):
        score_bag(broken)


def test_a_bag_marked_incomplete_is_not_scored(tmp_path):
    spec = SPECS['computed_torque']
    with EpisodeBagWriter(tmp_path / 'bag', {'spec': spec.to_dict(), 'joints': ['joint1', 'joint2', 'joint3']}):
        pass  # left by an exception: closed as incomplete
    with pytest.raises(BagError, match='marked incomplete'):
        score_bag(tmp_path / 'bag')


def test_non_bags_are_refused(tmp_path, capsys):
    (tmp_path / 'folder').mkdir()
    (tmp_path / 'garbage').mkdir()
    (tmp_path / 'garbage' / 'metadata.yaml').write_text('not: [a bag')
    assert main(['score', str(tmp_path / 'folder'), str(tmp_path / 'garbage'), str(tmp_path / 'none')]) == 2
    errors = capsys.readouterr().err
    assert 'no metadata.yaml' in errors and 'unreadable bag' in errors and 'no such bag' in errors


def test_output_paths_that_escape_or_overwrite_are_refused(tmp_path):
    (tmp_path / 'existing').mkdir()
    with pytest.raises(BagError, match='exists already'):
        checked_output_path(tmp_path / 'existing')
    with pytest.raises(BagError, match='".." is not allowed'):
        checked_output_path(tmp_path / 'a' / '..' / 'b')
    os.symlink(tmp_path / 'existing', tmp_path / 'link')
    with pytest.raises(BagError, match='symlink'):
        checked_output_path(tmp_path / 'link' / 'bag')
    for name in ('../x', 'a/b', '..', ''):
        with pytest.raises(BagError, match='plain file name'):
            child_path(tmp_path, name)
    assert child_path(tmp_path, 'episode_001') == tmp_path / 'episode_001'


def test_separate_processes_record_a_scorable_bag(tmp_path):
    spec = SPECS['pd_gravity']
    result = run_graph_episode(spec, bag=tmp_path / 'bag', storage='sqlite3')
    assert score_bag(tmp_path / 'bag')['I'] == pytest.approx(result.indices['I'], rel=1e-12)
