"""Gains keyed by joint name (ros2_controllers' `gains: {<joint>: {p, d}}`): the controller YAML that
`controller_yaml` writes, and the controller node that loads it, refuses it, or converts it at run time."""

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
import yaml
from rclpy.exceptions import InvalidParameterValueException, ParameterNotDeclaredException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from ddarm.control.laws import GainError
from ddarm.recording.runs import controller_yaml
from ddarm.ros.interface import flat_parameters, given_gains
from ddarm_control.node import ControllerNode
from graph_helpers import overrides, parameter_client

ROOT = Path(__file__).resolve().parent.parent
DDARM_JOINTS = ['joint1', 'joint2', 'joint3']
UR5 = ROOT / 'config' / 'arms' / 'ur5'
UR5_JOINTS = ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint', 'wrist_2_joint',
              'wrist_3_joint']
needs_ur5 = pytest.mark.skipif(not (UR5 / 'ur5.urdf').is_file(), reason='config/arms/ur5 is not in the tree')


def keyed(joints, kp, kv) -> dict:
    return {f'gains.{joint}.{key}': float(value) for joint, p, d in zip(joints, kp, kv)
            for key, value in (('p', p), ('d', d))}


def node_from_file(path, law):
    """A controller node started as `--ros-args --params-file path` starts it (in this process)."""
    context = rclpy.Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(path)])
    try:
        return ControllerNode(law, context=context), context
    except BaseException:
        rclpy.try_shutdown(context=context)
        raise


def close(node, context):
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def test_controller_yaml_writes_the_gains_keyed_by_joint_with_the_arm():
    text = controller_yaml('computed_torque', [100.0, 200.0, 300.0], [10.0, 20.0, 30.0], 2, 0.005,
                           'tuned by a test\nsecond line', joint_names=DDARM_JOINTS, urdf='config/ddarm.urdf',
                           motion='config/arms/ur5/ur5-motion.yaml')
    assert text.startswith('# tuned by a test\n# second line\n')
    parameters = yaml.safe_load(text)['computed_torque']['ros__parameters']
    assert parameters['gains'] == {'joint1': {'p': 100.0, 'd': 10.0}, 'joint2': {'p': 200.0, 'd': 20.0},
                                   'joint3': {'p': 300.0, 'd': 30.0}}
    assert 'kp' not in parameters and 'kv' not in parameters
    assert parameters['urdf'] == str((Path.cwd() / 'config/ddarm.urdf').resolve())
    assert parameters['motion'] == str((Path.cwd() / 'config/arms/ur5/ur5-motion.yaml').resolve())
    assert (parameters['delay'], parameters['period'], parameters['omega']) == (2, 0.005, 0.0)
    # Without urdf and motion, neither is written (the node's defaults).
    plain = yaml.safe_load(controller_yaml('pd_gravity', [1, 2, 3], [4, 5, 6], 1, 0.01, 'x',
                                           joint_names=DDARM_JOINTS))['pd_gravity']['ros__parameters']
    assert 'urdf' not in plain and 'motion' not in plain
    # What the tuner reads back from such a file: the same gains, by the node's own rule.
    assert given_gains(flat_parameters(parameters), DDARM_JOINTS) == ([100.0, 200.0, 300.0], [10.0, 20.0, 30.0])


@pytest.mark.parametrize('joint_names, problem', [
    (['joint1', 'joint2'], '2 joint_names'),
    (['joint1', 'joint1', 'joint3'], 'distinct'),
    (['joint1', '', 'joint3'], 'distinct non-empty'),
])
def test_controller_yaml_refuses_joint_names_that_do_not_fit_the_gains(joint_names, problem):
    with pytest.raises(ValueError, match=problem):
        controller_yaml('computed_torque', [1.0] * 3, [1.0] * 3, 1, 0.01, 'x', joint_names=joint_names)


@pytest.mark.parametrize('law', ['computed_torque', 'pd_gravity'])
def test_the_node_started_with_the_written_yaml_has_its_gains(tmp_path, law):
    path = tmp_path / f'{law}.yaml'
    path.write_text(controller_yaml(law, [100.0, 200.0, 300.0], [10.0, 20.0, 30.0], 2, 0.02, 'test',
                                    joint_names=DDARM_JOINTS))
    node, context = node_from_file(path, law)
    try:
        assert node.controller.law.kp.tolist() == [100.0, 200.0, 300.0]
        assert node.controller.law.kv.tolist() == [10.0, 20.0, 30.0]
        assert node.controller.delay == 2 and node.period == 0.02
        assert node.get_parameter('gains.joint2.d').value == 20.0
    finally:
        close(node, context)


@needs_ur5
def test_the_written_yaml_of_a_six_joint_arm_names_its_model_and_joints(tmp_path):
    kp, kv = [float(100 + i) for i in range(6)], [float(10 + i) for i in range(6)]
    path = tmp_path / 'tuned.yaml'
    path.write_text(controller_yaml('computed_torque', kp, kv, 1, 0.01, 'ur5', joint_names=UR5_JOINTS,
                                    urdf=UR5 / 'ur5.urdf', motion=UR5 / 'ur5-motion.yaml'))
    node, context = node_from_file(path, 'computed_torque')
    try:
        assert node.joints == UR5_JOINTS and node.model.joint_names == UR5_JOINTS
        assert node.controller.law.kp.tolist() == kp and node.controller.law.kv.tolist() == kv
    finally:
        close(node, context)


def test_the_written_yaml_loads_as_it_is_in_a_node_process(tmp_path, ros_context):
    """`ros2 run ddarm_control computed_torque --ros-args --params-file FILE`, through the same main()."""
    path = tmp_path / 'tuned.yaml'
    path.write_text(controller_yaml('computed_torque', [150.0, 160.0, 170.0], [15.0, 16.0, 17.0], 1, 0.01, 'test',
                                    joint_names=DDARM_JOINTS))
    process = subprocess.Popen([sys.executable, '-m', 'ddarm_control.node', 'computed_torque', '--ros-args',
                                '--params-file', str(path)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)
    node = rclpy.create_node('gains_probe', context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        client = node.create_client(Trigger, '/computed_torque/status')
        assert client.wait_for_service(timeout_sec=60), 'the controller never came up'
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=30)
        status = json.loads(future.result().message)
        assert status['kp'] == [150.0, 160.0, 170.0] and status['kv'] == [15.0, 16.0, 17.0]
        assert status['parameters']['gains.joint3.p'] == 170.0
    finally:
        executor.shutdown()
        node.destroy_node()
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=30)
    assert process.returncode == 0, output


def test_the_positional_gains_still_work_read_as_the_gains_by_joint(ros_context):
    node = ControllerNode('computed_torque', context=ros_context,
                          parameter_overrides=overrides({'kp': [1.0, 2.0, 3.0], 'kv': [4.0, 5.0, 6.0]}))
    try:
        assert node.controller.law.kp.tolist() == [1.0, 2.0, 3.0] and node.controller.law.kv.tolist() == [4, 5, 6]
        # Read as the gains by joint, which the node holds from then on (the deprecated form left empty).
        assert [node.get_parameter(f'gains.{joint}.d').value for joint in DDARM_JOINTS] == [4.0, 5.0, 6.0]
        assert len(node.get_parameter('kp').value) == 0
    finally:
        node.destroy_node()


def test_gains_given_both_ways_are_refused_naming_both(ros_context):
    values = {'kp': [1.0] * 3, 'kv': [1.0] * 3, **keyed(DDARM_JOINTS, [2.0] * 3, [2.0] * 3)}
    with pytest.raises(GainError, match=r'gains given twice: by kp and kv and by gains\.joint1\.p'):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(values))


def test_keyed_gains_for_some_joints_only_are_refused_naming_the_unset(ros_context):
    values = keyed(DDARM_JOINTS[:2], [2.0] * 2, [2.0] * 2)
    with pytest.raises(GainError, match=r'gains\.joint3\.p, gains\.joint3\.d unset'):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(values))


def test_no_gains_at_all_are_refused_saying_how_to_give_them(ros_context):
    with pytest.raises(GainError, match=re.escape("set the gains: gains.<joint>.p and .d for each joint of "
                                                  "['joint1', 'joint2', 'joint3'], or kp and kv")):
        ControllerNode('computed_torque', context=ros_context)


def test_gains_for_a_joint_not_controlled_are_refused_naming_it(ros_context):
    values = {**keyed(DDARM_JOINTS, [2.0] * 3, [2.0] * 3), 'gains.wrist.p': 1.0}
    with pytest.raises(GainError, match=r"gains for joint 'wrist', which the computed_torque controller does not "
                                        r"control: its joints are \['joint1', 'joint2', 'joint3'\]"):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(values))


def test_a_file_with_gains_for_a_joint_not_controlled_is_refused_at_start_naming_it(tmp_path):
    path = tmp_path / 'tuned.yaml'
    path.write_text(controller_yaml('computed_torque', [1.0] * 3, [1.0] * 3, 1, 0.01, 'x',
                                    joint_names=['joint1', 'joint2', 'wrist']))
    done = subprocess.run([sys.executable, '-m', 'ddarm_control.node', 'computed_torque', '--ros-args',
                           '--params-file', str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "refused to start: unknown parameters ['gains.wrist.d', 'gains.wrist.p'] (gains for joint 'wrist'" \
        in done.stdout


@pytest.mark.parametrize('value', [-1.0, float('nan'), float('inf'), 2e9])
def test_a_bad_gain_value_is_refused_naming_the_parameter(ros_context, value):
    values = {**keyed(DDARM_JOINTS, [2.0] * 3, [2.0] * 3), 'gains.joint2.d': value}
    with pytest.raises(InvalidParameterValueException, match=re.escape('gains.joint2.d')):
        ControllerNode('computed_torque', context=ros_context, parameter_overrides=overrides(values))


@pytest.fixture
def keyed_node(ros_context):
    node = ControllerNode('computed_torque', context=ros_context,
                          parameter_overrides=overrides(keyed(DDARM_JOINTS, [100.0, 200.0, 300.0], [10.0, 20.0, 30.0])))
    yield node
    node.destroy_node()


def test_keyed_gains_set_at_run_time_through_the_service_atomically_and_validated(ros_context, keyed_node):
    node = keyed_node
    with parameter_client(ros_context, node, 'computed_torque') as (client, wait):
        result = wait(client.set_parameters_atomically(
            [Parameter('gains.joint1.p', value=110.0), Parameter('gains.joint3.d', value=33.0)])).result
        assert result.successful, result.reason
        assert node.controller.law.kp.tolist() == [110.0, 200.0, 300.0]
        assert node.controller.law.kv.tolist() == [10.0, 20.0, 33.0]
        # One bad value in the change: nothing of it is taken, the reason names the parameter.
        result = wait(client.set_parameters_atomically(
            [Parameter('gains.joint1.p', value=1.0), Parameter('gains.joint2.p', value=-1.0)])).result
        assert not result.successful and 'gains.joint2.p' in result.reason
        # Unsetting one joint's gain: refused, naming it.
        result = wait(client.set_parameters([Parameter('gains.joint2.d', value=0.0)])).results[0]
        assert not result.successful and 'gains.joint2.d unset' in result.reason
        result = wait(client.set_parameters([Parameter('gains.elbow.p', value=1.0)])).results[0]
        assert not result.successful and "gains for joint 'elbow'" in result.reason
        assert node.controller.law.kp.tolist() == [110.0, 200.0, 300.0]
        assert node.controller.law.kv.tolist() == [10.0, 20.0, 33.0]


def test_a_positional_change_is_read_as_the_gains_by_joint(keyed_node):
    """The node holds its gains by joint: kp (or kv), deprecated, set at run time is read as gains.<joint>.p (.d)."""
    node = keyed_node
    assert node.set_parameters([Parameter('kp', value=[1.0, 2.0, 3.0])])[0].successful
    assert node.controller.law.kp.tolist() == [1.0, 2.0, 3.0]
    assert node.controller.law.kv.tolist() == [10.0, 20.0, 30.0]
    assert [node.get_parameter(f'gains.{joint}.p').value for joint in DDARM_JOINTS] == [1.0, 2.0, 3.0]
    assert len(node.get_parameter('kp').value) == 0 and node.get_parameter('gains.joint1.d').value == 10.0
    assert node.set_parameters([Parameter('kv', value=[4.0, 5.0, 6.0])])[0].successful
    assert node.controller.law.kv.tolist() == [4.0, 5.0, 6.0] and node.get_parameter('gains.joint3.d').value == 6.0
    assert node.set_parameters([Parameter('gains.joint2.p', value=22.0)])[0].successful
    assert node.controller.law.kp.tolist() == [1.0, 22.0, 3.0] and node.controller.law.kv.tolist() == [4, 5, 6]
    # A positional diagonal that is not one gain > 0 per joint is refused naming it; nothing changes.
    result = node.set_parameters([Parameter('kp', value=[1.0, 2.0])])[0]
    assert not result.successful and 'kp needs 3' in result.reason
    # Both forms in one change: refused, nothing changes.
    result = node.set_parameters_atomically([Parameter('kp', value=[9.0] * 3), Parameter('gains.joint1.p', value=9.0)])
    assert not result.successful and 'gains given twice' in result.reason
    assert node.controller.law.kp.tolist() == [1.0, 22.0, 3.0]
    with pytest.raises(ParameterNotDeclaredException, match="gains for joint 'wrist'"):
        node.set_parameters([Parameter('gains.wrist.p', value=1.0)])


def test_a_yaml_tuned_over_another_T_runs_its_motion_over_that_T_in_timer_mode():
    """`ddarm tune --duration 0.5` on a 1 s bang-bang file: the YAML says T, and the timer-mode reference is the
    motion stretched to it, as the episodes the gains were tuned on."""
    import numpy as np

    from ddarm.motion.files import load_motion
    from ddarm.physics.arm import load_arm
    from ddarm_control.node import motion_reference

    root = Path(__file__).resolve().parents[1] / 'config' / 'arms' / 'z1'
    text = controller_yaml('computed_torque', [225.0] * 6, [30.0] * 6, 1, 0.01, 'test',
                           joint_names=[f'joint{i}' for i in range(1, 7)], urdf=root / 'z1.urdf',
                           motion=root / 'z1-motion.yaml', duration=0.5)
    assert yaml.safe_load(text)['computed_torque']['ros__parameters']['duration'] == 0.5
    file = load_motion(root / 'z1-motion.yaml')
    model = load_arm(str(root / 'z1.urdf'), None, file.joint_names, file.locked)
    reference = motion_reference(model, file, 0.01, 0.5)
    assert len(reference.times) == 51
    np.testing.assert_allclose(reference.q[25], (file.motion.q0 + file.motion.qf) / 2, rtol=1e-12)
    np.testing.assert_array_equal(reference.q[-1], file.motion.qf)
    assert len(motion_reference(model, file, 0.01).times) == 101  # 0: the file's own T


def test_a_file_with_the_old_name_of_the_delay_is_read_with_a_notice_and_both_names_must_agree(tmp_path):
    from ddarm.deprecation import DeprecatedName
    from ddarm.recording.gains_file import GainsFileError, read_gains_file

    text = controller_yaml('pd_gravity', [100.0, 200.0, 300.0], [10.0, 20.0, 30.0], 2, 0.01, 'x',
                           joint_names=DDARM_JOINTS)
    path = tmp_path / 'old.yaml'
    path.write_text(text.replace('delay: 2', 'compute_delay_steps: 0'))
    with pytest.warns(DeprecatedName, match="'compute_delay_steps' is deprecated, read as 'delay'"):
        assert read_gains_file(path).delay == 0
    path.write_text(text.replace('delay: 2', 'delay: 2\n    compute_delay_steps: 0'))
    with pytest.raises(GainsFileError, match=r'delay given twice, as delay \(2\) and by its deprecated name'):
        read_gains_file(path)
    # The node reads such a file as the same delay (its log says the name is deprecated).
    path.write_text(text.replace('delay: 2', 'compute_delay_steps: 0'))
    node, context = node_from_file(path, 'pd_gravity')
    try:
        assert node.controller.delay == 0 == node.get_parameter('delay').value
    finally:
        close(node, context)
