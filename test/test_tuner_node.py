"""The tuner node over ROS: episodes driven on separate plant and controller processes, recorded as bags,
scored from the bags; stopped by SIGTERM it leaves every finished bag readable (docs/faults.md 15-17)."""

import json
import signal
import subprocess
import sys
import time

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from ddarm.recording.bags import BagError, bag_status, score_bag
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeError, EpisodeSpec
from ddarm_tuner.node import TunerNode
from ddarm.recording.runs import RunFolder
from process_helpers import stop
from test_hostile_inputs import alias_bomb

GAINS = {'computed_torque': ([900.0] * 3, [60.0] * 3, 1),
         'pd_gravity': ([28000.0, 27000.0, 3500.0], [1760.0, 1700.0, 220.0], 0)}


def start_nodes(law, folder):
    """The plant and one controller as processes, as `ros2 run` would start them."""
    kp, kv, _ = GAINS[law]
    with open(folder / 'plant.log', 'w') as plant_log, open(folder / 'controller.log', 'w') as controller_log:
        plant = subprocess.Popen([sys.executable, '-m', 'ddarm_sim.node', '--ros-args', '-p', 'autostart:=false'],
                                 stdout=plant_log, stderr=subprocess.STDOUT)
        controller = subprocess.Popen([sys.executable, '-m', 'ddarm_control.node', law, '--ros-args',
                                       '-p', f'kp:={kp}', '-p', f'kv:={kv}'],
                                      stdout=controller_log, stderr=subprocess.STDOUT)
    return [plant, controller]


@pytest.mark.parametrize('law', ['computed_torque', 'pd_gravity'])
def test_tuner_episodes_scored_from_their_bags_equal_the_in_process_indices(ros_context, tmp_path, law):
    kp, kv, delay = GAINS[law]
    nodes = start_nodes(law, tmp_path)
    tuner = TunerNode(context=ros_context, parameter_overrides=[
        Parameter('controller', value=law), Parameter('kp', value=kp), Parameter('kv', value=kv),
        Parameter('delay', value=delay), Parameter('taus', value=[0.0, 0.1]),
        Parameter('torque_limits', value=['none', 'paper'])])
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(tuner)
    run = RunFolder('sweep', tmp_path / 'runs', command='test')
    try:
        tuner.run_sweep(executor, run)
        run.finish('complete')
    finally:
        executor.shutdown()
        tuner.destroy_node()
        stop(nodes)
    summary = json.loads((tmp_path / 'runs' / 'sweep' / 'summary.json').read_text())
    assert summary['status'] == 'complete' and len(summary['episodes']) == 4
    for episode in summary['episodes']:
        spec = EpisodeSpec(**episode['spec'])
        expected = run_episode(spec).indices()
        scored = score_bag(episode['bag'])
        for key in ('I1', 'I2', 'I'):
            assert scored[key] == pytest.approx(expected[key], rel=1e-9)
            assert episode[key] == scored[key]
    assert {episode['spec']['torque_limit'] for episode in summary['episodes']} == {'none', 'paper'}


def test_sigterm_stops_the_tuner_and_every_finished_bag_reads_back(tmp_path):
    nodes = start_nodes('computed_torque', tmp_path)
    taus = ','.join(f'{0.01 * i:.2f}' for i in range(11))
    tuner = subprocess.Popen(
        [sys.executable, '-m', 'ddarm_tuner.node', '--ros-args', '-p', 'kp:=[900.0,900.0,900.0]',
         '-p', 'kv:=[60.0,60.0,60.0]', '-p', f'taus:=[{taus}]', '-p', "torque_limits:=['none','paper']",
         '-p', f'output_root:={tmp_path / "runs"}', '-p', 'run_name:=stopped'],
        stdout=open(tmp_path / 'tuner.log', 'w'), stderr=subprocess.STDOUT)
    summary_path = tmp_path / 'runs' / 'stopped' / 'summary.json'
    try:
        deadline = time.monotonic() + 120
        while not (summary_path.exists() and len(json.loads(summary_path.read_text())['episodes']) >= 2):
            assert time.monotonic() < deadline and tuner.poll() is None, (tmp_path / 'tuner.log').read_text()
            time.sleep(0.1)  # polling another process's files: there is no event to wait on
        tuner.send_signal(signal.SIGTERM)
        assert tuner.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        stop(nodes)
    summary = json.loads(summary_path.read_text())
    assert summary['status'] == 'interrupted'
    assert len(summary['episodes']) < 22, 'the tuner should not have finished before SIGTERM'
    finished = {episode['bag'] for episode in summary['episodes']}
    bags = sorted((tmp_path / 'runs' / 'stopped' / 'bags').iterdir())
    assert {str(bag) for bag in bags[:len(finished)]} == finished
    for bag in bags[:len(finished)]:
        assert bag_status(bag) == 'complete' and score_bag(bag)['I'] > 0
    # At most one episode was under way: closed and marked incomplete, or (if the signal came
    # after its bag closed, before the summary) complete and scorable all the same.
    assert len(bags) - len(finished) <= 1
    for bag in bags[len(finished):]:
        if bag_status(bag) == 'complete':
            assert score_bag(bag)['I'] > 0
        else:
            with pytest.raises(BagError, match='marked incomplete'):
                score_bag(bag)


def test_tuner_parameter_typos_are_refused(ros_context, tmp_path):
    with pytest.raises(EpisodeError, match='kp needs 3'):
        TunerNode(context=ros_context, parameter_overrides=[Parameter('kp', value=[1.0, 2.0]),
                                                            Parameter('kv', value=[1.0, 2.0, 3.0])])
    with pytest.raises(EpisodeError, match="unknown parameters \\['tau'\\]"):
        TunerNode(context=ros_context, parameter_overrides=[Parameter('tau', value=0.1)])
    with pytest.raises(EpisodeError, match='gains_file'):
        TunerNode(context=ros_context, parameter_overrides=[Parameter('gains_file', value='/nonexistent.yaml')])
    bomb = tmp_path / 'gains.yaml'
    bomb.write_text('computed_torque:\n  ros__parameters:\n    kp: ' + alias_bomb(9) + '\n')
    with pytest.raises(EpisodeError, match=f'gains_file {bomb}: .*anchor or alias'):
        TunerNode(context=ros_context, parameter_overrides=[Parameter('gains_file', value=str(bomb))])


def test_a_node_that_dies_during_a_sweep_is_named(tmp_path):
    nodes = start_nodes('computed_torque', tmp_path)
    tuner = subprocess.Popen(
        [sys.executable, '-m', 'ddarm_tuner.node', '--ros-args', '-p', 'kp:=[900.0,900.0,900.0]',
         '-p', 'kv:=[60.0,60.0,60.0]', '-p', f"taus:=[{','.join(['0.0'] * 30)}]",
         '-p', f'output_root:={tmp_path / "runs"}', '-p', 'run_name:=killed'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    summary_path = tmp_path / 'runs' / 'killed' / 'summary.json'
    try:
        deadline = time.monotonic() + 120
        while not (summary_path.exists() and json.loads(summary_path.read_text())['episodes']):
            assert time.monotonic() < deadline and tuner.poll() is None, tuner.communicate()
            time.sleep(0.05)  # polling another process's files: there is no event to wait on
        nodes[0].kill()  # the plant, mid-sweep
        _, err = tuner.communicate(timeout=60)
    finally:
        stop(nodes)
    assert tuner.returncode == 2
    # Named by whichever notices first: the driver (no state owed by the plant) or DDS (the node left).
    failure = err.strip().splitlines()[-1]
    assert failure.startswith('tuner: ') and '/plant' in failure and 'Traceback' not in err, err
    assert 'published nothing' in failure or 'left the graph' in failure, failure
    summary = json.loads(summary_path.read_text())
    assert summary['status'] == 'failed' and '/plant' in summary['error']


def test_the_tuner_takes_the_gains_by_joint_and_the_deprecated_positional_form_as_the_same(ros_context):
    keyed = [Parameter(f'gains.joint{i}.{key}', value=value) for i, (p, d) in enumerate(
        [(100.0, 10.0), (200.0, 20.0), (300.0, 30.0)], start=1) for key, value in (('p', p), ('d', d))]
    positional = [Parameter('kp', value=[100.0, 200.0, 300.0]), Parameter('kv', value=[10.0, 20.0, 30.0])]
    specs = []
    for given in (keyed, positional):
        tuner = TunerNode(context=ros_context, parameter_overrides=given)
        try:
            specs.append([spec for _, spec, _ in tuner.specs])
        finally:
            tuner.destroy_node()
    assert specs[0] == specs[1] and specs[0][0].kp == (100.0, 200.0, 300.0) and specs[0][0].kv == (10.0, 20.0, 30.0)
    with pytest.raises(EpisodeError, match='gains given twice'):
        TunerNode(context=ros_context, parameter_overrides=keyed + positional)
    with pytest.raises(EpisodeError, match=r"set the gains: gains.<joint>.p and .d for each joint of \['joint1'"):
        TunerNode(context=ros_context)
    with pytest.raises(EpisodeError, match=r"unknown parameters \['gains.wrist.p'\]"):
        TunerNode(context=ros_context, parameter_overrides=[*keyed, Parameter('gains.wrist.p', value=1.0)])
