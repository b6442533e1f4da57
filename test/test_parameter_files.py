"""Parameter files that configure no node of the process are refused, naming the file (ddarm/ros/parameter_files.py)."""

import re

import pytest
import rclpy
from rclpy.node import Node

from ddarm.ros.parameter_files import (ParameterFileError, check_parameter_files, configures, given_parameters,
                                       node_keys, parameter_file_paths)

# (key, fully qualified name, whether rcl applies the key's parameters to that node), as rclpy 7.1 on
# Jazzy does: test_rcl_applies_a_key_exactly_where_it_configures checks every row against it.
RCL_MATCHES = [
    ('plant', '/plant', True), ('/plant', '/plant', True), ('plant', '/ns/plant', False),
    ('/plant', '/ns/plant', False), ('ns/plant', '/ns/plant', True), ('/ns/plant', '/ns/plant', True),
    ('/ns/plant', '/plant', False), ('/ns/plant', '/a/ns/plant', False), ('/a/ns/plant', '/a/ns/plant', True),
    ('/plnat', '/plant', False), ('/ns/planter', '/ns/plant', False),
    ('/**', '/plant', True), ('/**', '/a/ns/plant', True), ('**', '/ns/plant', True),
    ('/*', '/plant', True), ('*', '/plant', True), ('/*', '/ns/plant', False),
    ('/**/plant', '/plant', True), ('/**/plant', '/a/ns/plant', True), ('**/plant', '/ns/plant', True),
    ('/**/plant', '/ns/other', False),
    ('/*/plant', '/plant', False), ('/*/plant', '/ns/plant', True), ('*/plant', '/a/ns/plant', False),
    ('/ns/*', '/ns/plant', True), ('/ns/*', '/plant', False), ('/ns/**', '/ns/plant', True),
    ('/ns/**', '/a/ns/plant', False), ('/**/ns/plant', '/ns/plant', True), ('/**/ns/plant', '/a/ns/plant', True),
    ('/*/*/plant', '/a/ns/plant', True), ('/*/*/plant', '/ns/plant', False), ('/**/*', '/plant', True),
    ('/ns/**/plant', '/ns/plant', True), ('/ns/**/plant', '/ns/a/b/plant', True), ('/ns/*/plant', '/ns/plant', False),
]


@pytest.mark.parametrize('key, name, applies', RCL_MATCHES)
def test_a_key_configures_the_nodes_rcl_gives_its_parameters(key, name, applies):
    assert configures(key, name) is applies


@pytest.mark.parametrize('key, name, applies', RCL_MATCHES)
def test_rcl_applies_a_key_exactly_where_it_configures(tmp_path, key, name, applies):
    parameters = tmp_path / 'parameters.yaml'
    parameters.write_text(f"'{key}':\n  ros__parameters:\n    marker: 1\n")
    namespace, _, node_name = name.rpartition('/')
    context = rclpy.Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(parameters)])
    try:
        node = Node(node_name, namespace=namespace or '/', context=context, allow_undeclared_parameters=True,
                    automatically_declare_parameters_from_overrides=True)
        assert node.get_fully_qualified_name() == name
        assert node.has_parameter('marker') is applies
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_the_files_are_those_of_every_ros_args_block():
    arguments = ['prog', 'pd_gravity', '--params-file', 'not_ros.yaml', '--ros-args', '-p', 'kp:=1',
                 '--params-file', 'a.yaml', '-r', '__ns:=/arm', '--', 'other', '--params-file', 'after_end.yaml',
                 '--ros-args', '--log-level', 'info', '--params-file', 'b.yaml', '--params-file', 'c.yaml']
    assert parameter_file_paths(arguments) == ['a.yaml', 'b.yaml', 'c.yaml']
    assert parameter_file_paths(['--ros-args', '-p', '--params-file', '--params-file', 'd.yaml']) == ['d.yaml']
    assert parameter_file_paths(['prog']) == []


def write(tmp_path, text, name='parameters.yaml'):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_nested_keys_are_namespaces(tmp_path):
    path = write(tmp_path, '/arm:\n  plant:\n    ros__parameters: {period: 0.01}\n'
                           '  left:\n    computed_torque:\n      ros__parameters: {kp: [1.0, 1.0, 1.0]}\n'
                           '/:\n  tuner:\n    ros__parameters: {}\n'
                           'pd_gravity:\n  ros__parameters: {omega: 10.0}\n')
    assert node_keys(path) == ['/arm/plant', '/arm/left/computed_torque', '/tuner', 'pd_gravity']
    for name in ('/arm/plant', '/arm/left/computed_torque', '/tuner', '/pd_gravity'):
        check_parameter_files(['--ros-args', '--params-file', path], name)


def test_a_file_for_another_node_is_refused_naming_the_file_and_its_keys(tmp_path):
    good = write(tmp_path, 'plant:\n  ros__parameters: {period: 0.01}\n', 'good.yaml')
    misspelled = write(tmp_path, 'plnat:\n  ros__parameters: {period: 0.01}\n/arm:\n  plant:\n'
                                 '    ros__parameters: {}\n', 'misspelled.yaml')
    with pytest.raises(ParameterFileError, match=re.escape(
            f'{misspelled} configures no node named /plant (its node keys: plnat, /arm/plant)')):
        check_parameter_files(['--ros-args', '--params-file', good, '--params-file', misspelled], '/plant')
    check_parameter_files(['--ros-args', '--params-file', good], '/plant')


@pytest.mark.parametrize('text, problem', [
    ('plant: [unclosed\n', 'is not valid YAML'),
    ('- plant\n- controller\n', 'is not a mapping of node names to ros__parameters (it holds list)'),
    ('plant\n', 'is not a mapping of node names to ros__parameters (it holds str)'),
    ('', 'is not a mapping of node names to ros__parameters (it holds nothing)'),
    ('plant:\n  period: 0.01\n', 'configures no node: no ros__parameters under a node name (its keys: plant)'),
    ('{}\n', 'configures no node: no ros__parameters under a node name (its keys: none)'),
    ('ros__parameters:\n  period: 0.01\n', 'configures no node: no ros__parameters under a node name '
                                          '(its keys: ros__parameters)'),
])
def test_a_file_that_configures_no_node_at_all_is_refused_naming_it(tmp_path, text, problem):
    path = write(tmp_path, text)
    with pytest.raises(ParameterFileError, match=re.escape(f'parameter file {path} {problem}')):
        check_parameter_files(['--ros-args', '--params-file', path], '/plant')


def test_an_unreadable_file_is_refused_naming_it(tmp_path):
    for path in (tmp_path / 'missing.yaml', tmp_path):
        with pytest.raises(ParameterFileError, match=re.escape(f'parameter file {path} cannot be read: ')):
            check_parameter_files(['--ros-args', '--params-file', str(path)], '/plant')
    binary = tmp_path / 'binary.yaml'
    binary.write_bytes(b'\xff\xfe\x00plant')
    with pytest.raises(ParameterFileError, match=re.escape(f'parameter file {binary} ')):
        check_parameter_files(['--ros-args', '--params-file', str(binary)], '/plant')


GIVEN_FILES = {
    'a.yaml': '/arm:\n  plant:\n    ros__parameters: {deep: {x: [1, 2], y: {z: a}}, period: 0.01}\n'
              '  "*":\n    ros__parameters: {star: 1}\n"/**/plant":\n  ros__parameters: {anyplant: 1}\n'
              'plant:\n  ros__parameters: {rootplant: 1}\n',
    'b.yaml': '/**:\n  ros__parameters: {everywhere: true}\nother:\n  ros__parameters: {not_me: 1}\n',
}


@pytest.mark.parametrize('rules', [
    ['--params-file', 'a.yaml', '--params-file', 'b.yaml'],
    ['--params-file', 'a.yaml', '-r', '__ns:=/arm', '-p', 'kpp:=3', '--param', 'plant:only:=1', '--', 'not_ros',
     '--ros-args', '-p', 'later:=[1, 2]', '-p', 'text:=a:b'],
    ['-r', '__node:=other', '--params-file', 'b.yaml', '-p', 'qos_overrides./x.publisher.depth:=3', '-p', 'a.b:=1'],
])
@pytest.mark.parametrize('namespace', ['/', '/arm'])
def test_the_parameters_given_a_node_are_those_rcl_gives_it(tmp_path, rules, namespace):
    for name, text in GIVEN_FILES.items():
        (tmp_path / name).write_text(text)
    arguments = ['prog', '--ros-args', *(str(tmp_path / rule) if rule.endswith('.yaml') else rule for rule in rules)]
    context = rclpy.Context()
    rclpy.init(context=context, args=arguments)
    try:
        # A node that declares every override it is given shows what rcl gives it.
        node = Node('plant', namespace=namespace, context=context, enable_rosout=False,
                    automatically_declare_parameters_from_overrides=True)
        given = set(node.get_parameters_by_prefix('')) - {'use_sim_time', 'start_type_description_service'}
        assert sorted(given_parameters(arguments, node.get_fully_qualified_name())) == sorted(given)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
