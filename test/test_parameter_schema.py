"""The parameter schema is where every node parameter is defined: the nodes declare exactly its rows, a
describe_parameters call (what `ros2 param describe` shows) returns them, and rclpy refuses what its ranges refuse."""

import subprocess
import sys
from pathlib import Path

import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from ddarm.ros.interface import flat_parameters
from ddarm.ros.parameter_schema import NODES, SCHEMA, TYPES, joint_gains, parameters_of
from ddarm_control.node import ControllerNode
from ddarm_sim.node import PlantNode
from ddarm_sim.robot_node import RobotNode
from ddarm_tuner.node import TunerNode
from graph_helpers import overrides, parameter_client

TYPE_NUMBERS = {'bool': ParameterType.PARAMETER_BOOL, 'integer': ParameterType.PARAMETER_INTEGER,
                'double': ParameterType.PARAMETER_DOUBLE, 'string': ParameterType.PARAMETER_STRING,
                'integer[]': ParameterType.PARAMETER_INTEGER_ARRAY,
                'double[]': ParameterType.PARAMETER_DOUBLE_ARRAY, 'string[]': ParameterType.PARAMETER_STRING_ARRAY}
GAINS = {'kp': [100.0, 200.0, 300.0], 'kv': [10.0, 20.0, 30.0]}
ROBOT = {'mjcf': str(Path(__file__).parent.parent / 'config' / 'robots' / 'panda' / 'panda.xml')}
RCLPY_OWN = {'use_sim_time', 'start_type_description_service'}  # every rclpy node's


def test_the_schema_loads_without_rclpy():
    code = 'import sys, ddarm.ros.parameter_schema; print(any(m.startswith("rclpy") for m in sys.modules))'
    assert subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True).stdout.strip() == 'False'


def test_every_row_is_well_formed_and_its_default_within_its_range():
    for parameter in SCHEMA:
        assert parameter.type in TYPES and parameter.nodes and set(parameter.nodes) <= set(NODES), parameter
        assert parameter.description, parameter
        if parameter.range is not None:
            assert parameter.type in ('integer', 'double') and parameter.range[0] <= parameter.range[1]
            assert parameter.range[0] <= parameter.default <= parameter.range[1], parameter
        if parameter.default is None:
            assert parameter.type.endswith('[]'), parameter
    for node in NODES:
        names = [parameter.name for parameter in parameters_of(node)]
        assert len(names) == len(set(names)), node
    with pytest.raises(ValueError, match='no node'):
        parameters_of('planner')


def _described(context, node, name, probe):
    """What a client on the graph reads back from `node` through the parameter services: {name: descriptor}, and the
    result of setting `probe` (name, value)."""
    with parameter_client(context, node, name) as (client, wait):
        names = wait(client.list_parameters()).result.names
        descriptors = wait(client.describe_parameters(names)).descriptors
        refused = wait(client.set_parameters([Parameter(probe[0], value=probe[1])])).results[0]
    return dict(zip(names, descriptors)), refused


@pytest.mark.parametrize('kind, name, make, probe', [
    ('plant', 'plant', lambda context: PlantNode(context=context, parameter_overrides=overrides({'autostart': False})),
     ('period', 2.0)),
    ('robot', 'robot', lambda context: RobotNode(context=context,
                                                 parameter_overrides=overrides({**ROBOT, 'autostart': False})),
     ('position_noise', 11.0)),
    ('controller', 'computed_torque', lambda context: ControllerNode('computed_torque', context=context,
                                                                     parameter_overrides=overrides(GAINS)),
     ('delay', 101)),
    ('tuner', 'tuner', lambda context: TunerNode(context=context, parameter_overrides=overrides(GAINS)),
     ('episode_timeout', 0.5)),
])
def test_a_client_describing_each_node_reads_the_schema(ros_context, kind, name, make, probe):
    node = make(ros_context)
    try:
        described, refused = _described(ros_context, node, name, probe)
    finally:
        node.destroy_node()
    expected = {parameter.name: parameter for parameter in parameters_of(kind)}
    if kind in ('controller', 'tuner'):  # the ddarm arm's joints, declared at configure (at start: the tuner)
        expected.update({parameter.name: parameter for joint in ('joint1', 'joint2', 'joint3')
                         for parameter in joint_gains(joint)})
    assert set(described) - RCLPY_OWN == set(expected)
    for parameter_name, parameter in expected.items():
        descriptor = described[parameter_name]
        assert descriptor.type == TYPE_NUMBERS[parameter.type], parameter_name
        assert descriptor.description == parameter.description and descriptor.read_only == parameter.read_only
        ranges = descriptor.floating_point_range or descriptor.integer_range
        if parameter.range is None:
            assert not ranges, parameter_name
        else:
            assert (ranges[0].from_value, ranges[0].to_value) == parameter.range, parameter_name
    # rclpy itself refuses a value out of the schema's range.
    low, high = expected[probe[0]].range
    assert not low <= probe[1] <= high and not refused.successful


CONFIG = Path(__file__).parent.parent / 'config'
CONFIG_NODES = {'plant.yaml': ('plant', 'plant'), 'robot.yaml': ('robot', 'robot'),
                'pd_gravity.yaml': ('pd_gravity', 'controller'),
                'computed_torque.yaml': ('computed_torque', 'controller'), 'tuner.yaml': ('tuner', 'tuner')}
PYTHON_TYPES = {'bool': (bool,), 'integer': (int,), 'double': (int, float), 'string': (str,)}


def _fits(parameter, value) -> bool:
    """Whether a YAML value is one the node takes for `parameter`: its type (an int for a double too), its range."""
    if parameter.type.endswith('[]'):
        kind = PYTHON_TYPES[parameter.type[:-2]]
        return isinstance(value, list) and all(isinstance(item, kind) and not isinstance(item, bool) or
                                               kind == (bool,) and isinstance(item, bool) for item in value)
    kind = PYTHON_TYPES[parameter.type]
    if isinstance(value, bool) != (kind == (bool,)) or not isinstance(value, kind):
        return False
    return parameter.range is None or parameter.range[0] <= value <= parameter.range[1]


@pytest.mark.parametrize('file', sorted(CONFIG_NODES))
def test_every_parameter_a_config_file_sets_is_the_schemas_and_fits_it(file):
    import yaml

    node_name, kind = CONFIG_NODES[file]
    rows = {parameter.name: parameter for parameter in parameters_of(kind)}
    given = flat_parameters(yaml.safe_load((CONFIG / file).read_text())[node_name]['ros__parameters'])
    for name, value in given.items():
        joint = name.split('.')[1] if name.startswith('gains.') else None
        parameter = rows.get(name) or (next((row for row in joint_gains(joint) if row.name == name), None)
                                       if joint else None)
        assert parameter is not None, f'{file} sets {name}, which the schema has not for the {kind} node'
        assert _fits(parameter, value), f'{file}: {name}: {value!r} is not a {parameter.type} within {parameter.range}'


def test_the_config_files_are_the_schema_as_it_is():
    """config/*.yaml are generated from the schema (`make docs`): a default, range or description changes in one place."""
    from ddarm.ros.config_files import FILES, render

    assert sorted(config.name for config in FILES) == sorted(CONFIG_NODES)
    for config in FILES:
        assert (CONFIG / config.name).read_text() == render(config), f'config/{config.name} drifted: run make docs'
        text = render(config)
        assert max(len(line) for line in text.splitlines()) <= 120
        # Every parameter of the node is in its file, set or shown commented out, but the deprecated names.
        for parameter in parameters_of(config.kind):
            written = f' {parameter.name}: ' in text or f'# {parameter.name}: ' in text
            assert written != bool(parameter.alias_of), (config.name, parameter.name)


def test_the_driver_sets_through_the_services_every_parameter_of_an_episode_but_the_schemas_read_only_ones():
    from ddarm.episodes.spec import EpisodeSpec, check_episode
    from ddarm.ros.node_parameters import node_parameters, service_parameters
    from ddarm.ros.parameter_schema import read_only

    arm = Path(__file__).parent.parent / 'config' / 'arms' / 'ur5'
    spec = EpisodeSpec(controller='pd_gravity', kp=(100.0,) * 6, kv=(10.0,) * 6, urdf=str(arm / 'ur5.urdf'),
                       motion=str(arm / 'ur5-motion.yaml'), viscous_friction=(0.1,) * 6)
    parameters = node_parameters(spec, check_episode(spec))
    for node, kind in (('plant', 'plant'), ('pd_gravity', 'controller')):
        given = parameters[node]['ros__parameters']
        assert {'urdf', 'motion'} <= set(given) and {'urdf', 'motion'} <= read_only(kind)
        sent = {parameter.name for parameter in service_parameters(given, (), kind)}
        assert sent == set(flat_parameters(given)) - read_only(kind)


def test_a_deprecated_name_sets_the_parameter_it_names_at_start_and_at_run_time_and_mirrors_it(ros_context):
    from ddarm.recording.gains_file import CONTROLLER_RENAMED
    from ddarm.ros.parameter_schema import aliases

    assert aliases('controller') == CONTROLLER_RENAMED == {'compute_delay_steps': 'delay'}  # files read them alike
    node = ControllerNode('pd_gravity', context=ros_context,
                          parameter_overrides=overrides({**GAINS, 'compute_delay_steps': 0}))
    try:
        assert node.get_parameter('delay').value == 0 == node.controller.delay
        assert node.set_parameters([Parameter('compute_delay_steps', value=2)])[0].successful
        assert node.get_parameter('delay').value == 2 == node.controller.delay
        assert node.set_parameters([Parameter('delay', value=1)])[0].successful
        assert node.get_parameter('compute_delay_steps').value == 1 == node.controller.delay
        refused = node.set_parameters([Parameter('compute_delay_steps', value=101)])[0]
        assert not refused.successful and node.controller.delay == 1
    finally:
        node.destroy_node()
    node = ControllerNode('pd_gravity', context=ros_context, parameter_overrides=overrides({**GAINS, 'delay': 2}))
    try:
        assert node.get_parameter('compute_delay_steps').value == 2 == node.controller.delay  # mirrored from start
    finally:
        node.destroy_node()
    with pytest.raises(Exception, match='delay given twice'):
        ControllerNode('pd_gravity', context=ros_context,
                       parameter_overrides=overrides({**GAINS, 'compute_delay_steps': 0, 'delay': 2}))
