"""Bags record the QoS each topic's publishers offered, as rosbag2 Jazzy writes and reads it (metadata version 9)."""

import sqlite3
import struct
import time

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSCompatibility, QoSProfile,
                       ReliabilityPolicy, qos_check_compatible)
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from ddarm.ros.interface import CLOCK_QOS, DIAGNOSTICS_QOS, REFERENCE_QOS, ROBOT_COMMAND_QOS, SAMPLE_QOS
from ddarm.recording.bags import (DEFAULT_QOS, EPISODE_TOPIC, ROBOT_COMMANDED_TOPIC, ROBOT_COMMANDS_TOPIC,
                                  ROBOT_TOPICS, TOPICS, BagError, EpisodeBagWriter)

DECLARED = {'/joint_states': SAMPLE_QOS, '/effort_command': SAMPLE_QOS, '/reference': REFERENCE_QOS,
            '/clock': CLOCK_QOS, '/diagnostics': DIAGNOSTICS_QOS}
MESSAGE_TYPES = {'/joint_states': JointState, '/effort_command': JointState, '/reference': JointTrajectory,
                 '/clock': Clock, '/diagnostics': DiagnosticArray}
EPISODE = {'spec': {'period': 0.01}, 'joints': ['joint1', 'joint2', 'joint3']}


def topic_qos(profile: QoSProfile) -> dict:
    """An rclpy profile as the bag's TopicQos.

    The driver passes each `node.get_publishers_info_by_topic(topic)[i].qos_profile` through
    this, one entry per publisher; the graph reports history 'unknown' (depth 0), which DDS
    discovery does not carry.
    """
    return {'reliability': profile.reliability.short_key, 'durability': profile.durability.short_key,
            'history': profile.history.short_key, 'depth': profile.depth}


def recorded_profile(entry: dict) -> QoSProfile:
    """A metadata.yaml offered_qos_profiles entry as an rclpy profile: what `ros2 bag play` offers."""
    def duration(value):
        return Duration(seconds=value['sec'], nanoseconds=value['nsec'])

    return QoSProfile(history=HistoryPolicy.get_from_short_key(entry['history']), depth=entry['depth'],
                      reliability=ReliabilityPolicy.get_from_short_key(entry['reliability']),
                      durability=DurabilityPolicy.get_from_short_key(entry['durability']),
                      liveliness=LivelinessPolicy.get_from_short_key(entry['liveliness']),
                      deadline=duration(entry['deadline']), lifespan=duration(entry['lifespan']),
                      liveliness_lease_duration=duration(entry['liveliness_lease_duration']),
                      avoid_ros_namespace_conventions=entry['avoid_ros_namespace_conventions'])


def assert_matches(publisher: QoSProfile, subscription: QoSProfile) -> None:
    """Compatible: ddarm's profiles leave liveliness at system_default, which rmw can only warn about."""
    compatibility, reason = qos_check_compatible(publisher, subscription)
    assert compatibility != QoSCompatibility.ERROR, reason
    assert all('liveliness' in warning for warning in reason.split(';') if warning), reason


def stored_qos_text(storage_file) -> dict:
    """Topic -> offered_qos_profiles as the storage file itself holds it (what rosbag2's storage plugins read)."""
    if storage_file.suffix == '.db3':
        connection = sqlite3.connect(storage_file)
        try:
            return dict(connection.execute('SELECT name, offered_qos_profiles FROM topics'))
        finally:
            connection.close()
    found = {}
    with Reader(storage_file) as reader:
        for channel in reader.storage.channels.values():
            metadata, offset = {}, 0
            while offset < len(channel.metadata):  # an MCAP map<string, string>
                strings = []
                for _ in range(2):
                    (size,) = struct.unpack_from('<I', channel.metadata, offset)
                    strings.append(channel.metadata[offset + 4:offset + 4 + size].decode())
                    offset += 4 + size
                metadata[strings[0]] = strings[1]
            found[channel.topic] = metadata['offered_qos_profiles']
    return found


def connection_qos(path) -> dict:
    """Topic -> rosbags' parsed offered_qos_profiles, from a bag folder (metadata.yaml) or a storage file."""
    with Reader(path) as reader:
        return {connection.topic: connection.ext.offered_qos_profiles for connection in reader.connections}


def graph_qos(context) -> dict:
    """What rclpy's graph reports for publishers that offer ddarm's profiles, as the driver will see it."""
    node = Node('qos_probe', context=context)
    try:
        for topic, profile in DECLARED.items():
            node.create_publisher(MESSAGE_TYPES[topic], topic, profile)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not all(node.get_publishers_info_by_topic(topic) for topic in DECLARED):
            time.sleep(0.01)
        return {topic: [topic_qos(info.qos_profile) for info in node.get_publishers_info_by_topic(topic)]
                for topic in DECLARED}
    finally:
        node.destroy_node()


def test_the_defaults_are_what_ddarm_publishers_offer():
    assert {topic: DEFAULT_QOS[topic] for topic in DECLARED} == {topic: topic_qos(profile)
                                                                 for topic, profile in DECLARED.items()}
    assert DEFAULT_QOS[EPISODE_TOPIC] == {'reliability': 'reliable', 'durability': 'transient_local',
                                          'history': 'keep_last', 'depth': 1}
    assert set(DEFAULT_QOS) == set(TOPICS) | set(ROBOT_TOPICS)
    # A robot's episode: its record of the commands in force as its states go, the efforts as a robot takes them.
    assert DEFAULT_QOS[ROBOT_COMMANDED_TOPIC] == topic_qos(SAMPLE_QOS)
    assert DEFAULT_QOS[ROBOT_COMMANDS_TOPIC] == topic_qos(ROBOT_COMMAND_QOS)


@pytest.mark.parametrize('source', ['defaults', 'graph'])
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_bag_records_the_offered_qos_as_rosbag2_jazzy_reads_it(ros_context, tmp_path, storage, source):
    offered = None if source == 'defaults' else graph_qos(ros_context)
    with EpisodeBagWriter(tmp_path / 'bag', EPISODE, storage, offered_qos=offered) as bag:
        bag.close(complete=True)
    metadata = yaml.safe_load((tmp_path / 'bag' / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert metadata['version'] == 9
    recorded = {entry['topic_metadata']['name']: entry['topic_metadata']['offered_qos_profiles']
                for entry in metadata['topics_with_message_count']}
    assert set(recorded) == set(TOPICS)
    for topic, profiles in recorded.items():
        assert isinstance(profiles, list) and len(profiles) == 1 and isinstance(profiles[0], dict), topic
    for topic, profile in DECLARED.items():  # what `ros2 bag play` offers still reaches ddarm's subscribers
        assert_matches(recorded_profile(recorded[topic][0]), profile)
    reference = recorded_profile(recorded['/reference'][0])
    assert reference.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert reference.reliability == ReliabilityPolicy.RELIABLE
    assert recorded_profile(recorded[EPISODE_TOPIC][0]).durability == DurabilityPolicy.TRANSIENT_LOCAL
    with pytest.raises(AssertionError):  # the check can fail: a volatile recording misses the latched reference
        assert_matches(recorded_profile(recorded['/joint_states'][0]), REFERENCE_QOS)
    if source == 'defaults':
        assert recorded['/joint_states'][0]['depth'] == 1000 and recorded['/clock'][0]['depth'] == 1000
    else:
        assert recorded['/reference'][0]['history'] == 'unknown' and recorded['/reference'][0]['depth'] == 0

    # The storage file says the same on its own (rosbag2's MCAP channels, its sqlite3 topics table).
    (storage_file,) = (tmp_path / 'bag').glob('*.mcap' if storage == 'mcap' else '*.db3')
    assert {topic: yaml.safe_load(text) for topic, text in stored_qos_text(storage_file).items()} == recorded
    from_metadata = connection_qos(tmp_path / 'bag')
    assert connection_qos(storage_file) == from_metadata
    assert from_metadata['/reference'][0].durability == QosDurability.TRANSIENT_LOCAL


def test_one_profile_per_publisher_heard(tmp_path):
    two = [DEFAULT_QOS['/diagnostics'], {**DEFAULT_QOS['/diagnostics'], 'reliability': 'best_effort'}]
    with EpisodeBagWriter(tmp_path / 'bag', EPISODE, offered_qos={'/diagnostics': two, '/clock': []}) as bag:
        bag.close(complete=True)
    metadata = yaml.safe_load((tmp_path / 'bag' / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    recorded = {entry['topic_metadata']['name']: entry['topic_metadata']['offered_qos_profiles']
                for entry in metadata['topics_with_message_count']}
    assert [profile['reliability'] for profile in recorded['/diagnostics']] == ['reliable', 'best_effort']
    assert recorded['/clock'] == []  # no publisher heard
    assert recorded['/reference'][0]['durability'] == 'transient_local'  # left out: the default


@pytest.mark.parametrize('offered, problem', [
    ({'/joint_state': [DEFAULT_QOS['/joint_states']]}, r"\['/joint_state'\], which are not topics"),
    ({'/reference': DEFAULT_QOS['/reference']}, '/reference must be a list of profiles'),
    ({'/reference': [{**DEFAULT_QOS['/reference'], 'durability': 'transient'}]},
     "/reference: durability must be one of .*'transient_local'.*got 'transient'"),
    ({'/clock': [{**DEFAULT_QOS['/clock'], 'depth': -1}]}, '/clock: depth must be an int >= 0, got -1'),
    ({'/clock': [{**DEFAULT_QOS['/clock'], 'depth': True}]}, '/clock: depth must be an int >= 0, got True'),
    ({'/clock': [{'reliability': 'reliable'}]}, '/clock must be a mapping with exactly the keys'),
])
def test_bad_offered_qos_is_refused_before_anything_is_written(tmp_path, offered, problem):
    with pytest.raises(BagError, match=problem):
        EpisodeBagWriter(tmp_path / 'bag', EPISODE, offered_qos=offered)
    assert not (tmp_path / 'bag').exists()
