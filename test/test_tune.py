"""`ddarm tune`: a small search improves on its ω-rule starts, the ROS check agrees with it to 1e-9, and the
written YAML loads into the controller node."""

import json
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml

from ddarm_control.node import ControllerNode
from ddarm.recording.bags import score_bag
from ddarm.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize('controller, index, method, delay', [
    ('computed_torque', '2.5', 'nelder-mead', '1'),
    ('pd_gravity', '3.2', 'cma', '0'),
])
def test_tune_improves_on_its_start_and_the_bag_agrees(capsys, tmp_path, controller, index, method, delay):
    assert main(['tune', '--controller', controller, '--index', index, '--method', method, '--delay', delay,
                 '--budget', '150', '--omegas', '10', '15', '--runs', str(tmp_path), '--run', 'small',
                 '--out', str(tmp_path / 'gains.yaml'), '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    key = 'I1' if index == '2.5' else 'I'
    assert report['index'] == key  # the paper's equation numbers are shorthands for the indices' names
    assert report['in_process'][key] < min(report['start_indices'])
    assert report['agree'] and report['max_rel_difference'] <= 1e-9
    assert score_bag(report['bag'])[key] == report['from_bag'][key]
    assert report['episodes'] <= 150
    # Local runs alone certify nothing: the report and the gains file say so beside the number.
    assert report['converged'] is None and 'certificate' not in report
    assert report['certainty'].startswith(f'not certified: --method {method} runs no independent global runs')
    assert f"(**{report['certainty']}**)" in (tmp_path / 'small' / 'report.md').read_text()
    assert f'not certified: --method {method} runs no independent global runs' in (tmp_path / 'gains.yaml').read_text()
    summary = json.loads((tmp_path / 'small' / 'summary.json').read_text())
    assert summary['status'] == 'complete' and summary['tune']['kp'] == report['kp']
    context = rclpy.Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(tmp_path / 'gains.yaml')])
    try:
        node = ControllerNode(controller, context=context)
        np.testing.assert_allclose(node.controller.law.kp, report['kp'], rtol=1e-15)
        assert node.controller.delay == int(delay)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_a_local_method_prints_that_its_minimum_is_not_certified_beside_its_gains(capsys, tmp_path):
    assert main(['tune', '--controller', 'computed_torque', '--index', 'I1', '--method', 'nelder-mead',
                 '--budget', '60', '--omegas', '15', '--runs', str(tmp_path), '--run', 'small']) == 0
    printed = capsys.readouterr().out.splitlines()
    (verdict,) = [line for line in printed if 'certified' in line]
    assert verdict.strip().startswith('WARNING: not certified: --method nelder-mead runs no independent global runs')
    assert printed.index(verdict) < min(printed.index(line) for line in printed if ' kp = ' in line)


def test_a_budget_too_small_for_the_starts_is_refused(capsys, tmp_path):
    assert main(['tune', '--controller', 'computed_torque', '--index', '2.5', '--budget', '3',
                 '--runs', str(tmp_path)]) == 2
    assert 'budget' in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_tune_on_an_arm_of_the_user_writes_gains_by_joint_a_bag_and_a_report_page(capsys, tmp_path):
    """docs/your-arm.md, "Tuning your own arm": the Z1's URDF and motion (its gripper locked) to a controller YAML
    keyed by joint, the bag that confirms it, and report.md with its figure."""
    arm = ROOT / 'config' / 'arms' / 'z1'
    assert main(['tune', '--urdf', str(arm / 'z1.urdf'), '--motion', str(arm / 'z1-motion.yaml'),
                 '--controller', 'computed_torque', '--index', 'I', '--urdf-limits', '--duration', '0.5',
                 '--budget', '120', '--omegas', '15', '--runs', str(tmp_path), '--run', 'z1',
                 '--out', str(tmp_path / 'z1.yaml'), '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    joints = ['joint1', 'joint2', 'joint3', 'joint4', 'joint5', 'joint6']
    assert report['joint_names'] == joints and list(report['gains']) == joints
    assert [report['gains'][name]['p'] for name in joints] == report['kp']
    assert report['agree'] and report['in_process']['I'] < report['start_indices'][0]
    assert score_bag(report['bag'])['joint_names'] == joints
    page = (tmp_path / 'z1' / 'report.md').read_text()
    assert all(f'| {name} |' in page for name in joints) and '![' in page
    assert (tmp_path / 'z1' / 'best-episode.png').stat().st_size > 10_000
    written = yaml.safe_load((tmp_path / 'z1.yaml').read_text())['computed_torque']['ros__parameters']
    assert written['gains'] == {name: {'p': report['gains'][name]['p'], 'd': report['gains'][name]['d']}
                                for name in joints}
    assert written['urdf'] == str(arm / 'z1.urdf') and written['motion'] == str(arm / 'z1-motion.yaml')
    context = rclpy.Context()
    rclpy.init(context=context, args=['--ros-args', '--params-file', str(tmp_path / 'z1.yaml')])
    try:
        node = ControllerNode('computed_torque', context=context)
        np.testing.assert_allclose(node.controller.law.kp, report['kp'], rtol=1e-15)
        assert node.joints == joints
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_a_global_search_that_did_not_converge_says_so_beside_its_gains(capsys, tmp_path):
    assert main(['tune', '--controller', 'pd_gravity', '--index', 'I', '--delay', '0', '--budget', '300',
                 '--omegas', '10', '15', '--runs', str(tmp_path), '--run', 'small',
                 '--out', str(tmp_path / 'gains.yaml')]) == 0
    printed = capsys.readouterr().out.splitlines()
    verdict = [line for line in printed if 'not converged' in line]
    assert len(verdict) == 1 and verdict[0].strip().startswith('WARNING: not converged: ')
    assert 'try --budget 600' in verdict[0]
    assert printed.index(verdict[0]) < min(printed.index(line) for line in printed if ' kp = ' in line)
    report = json.loads((tmp_path / 'small' / 'summary.json').read_text())['tune']
    assert report['converged'] is False and report['certificate']['converged'] is False
    assert report['certificate']['summary'] in verdict[0] and report['certainty'] == report['certificate']['summary']
    assert len(report['certificate']['runs']) == len(report['restarts'])
    # Each run says its family: the Nelder-Mead runs from the ω-rule starts, or a global run.
    rule_start_runs = ('Nelder-Mead', 'CMA-ES polish of the Nelder-Mead')
    assert all(restart['from_rule_starts'] == restart['start'].startswith(rule_start_runs)
               for restart in report['restarts'])
    assert report['episodes'] <= 300
    assert '**Not converged**' in (tmp_path / 'small' / 'report.md').read_text()
    assert 'the search did not converge' in (tmp_path / 'gains.yaml').read_text()
