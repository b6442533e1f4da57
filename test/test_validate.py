"""`ddarm validate`: a controller YAML on a MuJoCo robot beside ddarm's prediction; the YAML's reader and refusals."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import time
import json
from pathlib import Path

import pytest
import yaml

from ddarm.cli.main import main
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec, arm_joints, gains_from_omega
from ddarm.recording.gains_file import read_gains_file, validation_spec
from ddarm.recording.runs import controller_yaml
from two_link import robot_mjcf, write_files

ROOT = Path(__file__).resolve().parents[1]
UR5 = ROOT / 'config' / 'arms' / 'ur5'
PANDA = ROOT / 'config' / 'arms' / 'panda'
PANDA_ROBOT = ROOT / 'config' / 'robots' / 'panda' / 'panda.xml'

# A two-link robot with nothing that bounds its torques (no actuator, no force range), and ddarm's model of it.
TWO_LINK_MJCF = robot_mjcf(option='<option timestep="0.001"/>')


def tuned_spec(urdf: Path, motion: Path, omega: float, controller: str = 'computed_torque') -> EpisodeSpec:
    """The episode a tuning would have written a YAML for: the ω-rule gains on the URDF and motion."""
    spec = EpisodeSpec(controller, (1.0,), (1.0,), urdf=str(urdf), motion=str(motion))
    kp, kv = gains_from_omega(spec, omega)
    return dataclasses.replace(spec, kp=kp, kv=kv)


def write_yaml(path: Path, spec: EpisodeSpec) -> Path:
    """The controller YAML `ddarm tune --out` writes for `spec`."""
    path.write_text(controller_yaml(spec.controller, spec.kp, spec.kv, spec.delay, spec.period, 'a test',
                                    joint_names=arm_joints(spec)[0], urdf=spec.urdf, motion=spec.motion,
                                    duration=spec.duration))
    return path


def validate_json(capsys, tmp_path, gains: Path, mjcf: Path, *extra) -> dict:
    assert main(['validate', '--gains', str(gains), '--mjcf', str(mjcf), '--runs', str(tmp_path), '--json',
                 *extra]) == 0
    return json.loads(capsys.readouterr().out)


def compared(summary: dict) -> dict:
    return {key: summary[key] for key in ('I1', 'I2', 'I', 'diverged', 'diverged_at', 'samples_scored',
                                          'max_abs_error', 'max_abs_torque', 'joint_names')}


def test_the_prediction_and_the_measurement_are_the_episodes_themselves(capsys, tmp_path):
    spec = tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0)
    gains = write_yaml(tmp_path / 'ur5.yaml', spec)
    report = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf')
    predicted, measured = run_episode(spec), run_episode(dataclasses.replace(spec, mjcf=str(UR5 / 'ur5.urdf')))
    assert compared(report['predicted']) == compared(predicted.summary())
    assert compared(report['measured']) == compared(measured.summary())
    assert report['measured']['robot']['mjcf'] == str(UR5 / 'ur5.urdf')
    assert report['bag'] is None and report['gains'] == str(gains)
    for index in ('I1', 'I2', 'I'):
        assert report['ratio'][index] == measured.indices()[index] / predicted.indices()[index]
    on_disk = json.loads((Path(report['run']) / 'summary.json').read_text())
    assert on_disk['status'] == 'complete'
    assert compared(on_disk['predicted']) == compared(report['predicted'])
    assert compared(on_disk['measured']) == compared(report['measured'])
    assert on_disk['ratio'] == report['ratio']


def test_the_measurement_through_the_graph_is_the_in_process_one_and_its_bag_is_kept(capsys, tmp_path):
    spec = dataclasses.replace(tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0), duration=0.4)
    gains = write_yaml(tmp_path / 'ur5.yaml', spec)
    over_ros = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf', '--ros', '--run', 'ros')
    in_process = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf', '--run', 'in-process')
    assert over_ros['measured']['transport'] == 'ros-lockstep' and in_process['measured']['transport'] == 'in-process'
    for index in ('I1', 'I2', 'I'):
        assert over_ros['measured'][index] == pytest.approx(in_process['measured'][index], rel=1e-9)
        assert over_ros['predicted'][index] == in_process['predicted'][index]
    bag = Path(over_ros['bag'])
    assert bag == tmp_path / 'ros' / 'bags' / 'measured' and (bag / 'metadata.yaml').is_file()
    assert main(['score', str(bag), '--json']) == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored['I'] == pytest.approx(in_process['measured']['I'], rel=1e-9)
    assert scored['spec']['mjcf'] == str(UR5 / 'ur5.urdf')


def test_the_measurement_on_ddarm_robot_in_lockstep_is_the_in_process_one_and_its_bag_scores_it(capsys, tmp_path):
    spec = dataclasses.replace(tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0), duration=0.4)
    gains = write_yaml(tmp_path / 'ur5.yaml', spec)
    on_robot = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf', '--robot', '--run', 'robot')
    in_process = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf', '--run', 'in-process')
    assert on_robot['measured']['transport'] == 'ros-robot-lockstep'
    assert not [warning for warning in on_robot['warnings'] if 'ddarm robot' in warning]  # no fault counted
    for index in ('I1', 'I2', 'I'):
        assert on_robot['measured'][index] == pytest.approx(in_process['measured'][index], rel=1e-12)
    bag = Path(on_robot['bag'])
    assert bag == tmp_path / 'robot' / 'bags' / 'measured'
    assert main(['score', str(bag), '--json']) == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored['I'] == on_robot['measured']['I']
    assert scored['samples_scored'] == in_process['measured']['samples_scored']


def test_free_running_the_measurement_is_recorded_scored_and_its_faults_said(capsys, tmp_path):
    spec = dataclasses.replace(tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0), duration=0.5)
    gains = write_yaml(tmp_path / 'ur5.yaml', spec)
    report = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf', '--robot', 'realtime', '--run', 'free')
    assert report['measured']['transport'] == 'ros-robot-realtime'
    assert main(['score', report['bag'], '--json']) == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored['I'] == report['measured']['I'] and scored['samples_scored'] == 51


def test_robot_needs_a_motion_file_and_excludes_ros(capsys, tmp_path):
    gains = write_yaml(tmp_path / 'ur5.yaml', tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0))
    with pytest.raises(SystemExit):
        main(['validate', '--gains', str(gains), '--mjcf', str(UR5 / 'ur5.urdf'), '--ros', '--robot'])
    assert 'not allowed with argument' in capsys.readouterr().err


def test_the_panda_robot_tracks_far_worse_than_its_urdf_predicts(capsys, tmp_path):
    gains = write_yaml(tmp_path / 'panda.yaml', tuned_spec(PANDA / 'panda.urdf', PANDA / 'panda-motion.yaml', 15.0))
    assert main(['validate', '--gains', str(gains), '--mjcf', str(PANDA_ROBOT), '--runs', str(tmp_path),
                 '--run', 'panda']) == 0
    out = capsys.readouterr().out
    run = tmp_path / 'panda'
    assert f'run folder {run}' in out and 'I1 (2.5)' in out and 'max |e| panda_joint7 (deg)' in out
    assert 'DIVERGED' not in out
    summary = json.loads((run / 'summary.json').read_text())
    assert summary['measured']['I1'] > 10 * summary['predicted']['I1']
    assert summary['ratio']['I1'] == summary['measured']['I1'] / summary['predicted']['I1']
    assert (run / 'errors.png').read_bytes().startswith(b'\x89PNG')
    page = (run / 'validation.md').read_text()
    assert '![' in page and '(errors.png)' in page and '| I1 (2.5) |' in page


def test_the_positional_form_is_read_as_the_keyed_form_with_a_notice(tmp_path):
    spec = tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0, 'pd_gravity')
    keyed = write_yaml(tmp_path / 'keyed.yaml', spec)
    document = yaml.safe_load(keyed.read_text())
    parameters = document['pd_gravity']['ros__parameters']
    gains = parameters.pop('gains')
    parameters['kp'] = [gains[joint]['p'] for joint in gains]
    parameters['kv'] = [gains[joint]['d'] for joint in gains]
    positional = tmp_path / 'positional.yaml'
    positional.write_text(yaml.safe_dump(document))
    from ddarm.deprecation import DeprecatedName

    with pytest.warns(DeprecatedName, match="'kp and kv' is deprecated, read as 'gains \\(by joint\\)'"):
        read = read_gains_file(positional)
    assert read == dataclasses.replace(read_gains_file(keyed), path=str(positional))
    assert validation_spec(read) == spec


def test_a_yaml_without_a_motion_is_the_paper_arm_on_trajectory_1_unless_told(tmp_path):
    path = tmp_path / 'paper.yaml'
    path.write_text(controller_yaml('pd_gravity', [2800, 2700, 350], [560, 540, 70], 0, 0.01, 'the paper',
                                    joint_names=['joint1', 'joint2', 'joint3']))
    gains = read_gains_file(path)
    assert (gains.urdf, gains.motion, gains.delay) == (None, None, 0)
    assert validation_spec(gains).trajectory == 1
    assert validation_spec(gains, trajectory=2).trajectory == 2


def refusal(capsys, tmp_path, gains, mjcf=UR5 / 'ur5.urdf', *extra) -> str:
    assert main(['validate', '--gains', str(gains), '--mjcf', str(mjcf), '--runs', str(tmp_path), *extra]) == 2
    captured = capsys.readouterr()
    assert captured.out == '' and 'Traceback' not in captured.err
    assert captured.err.count('\n') == 1 and captured.err.startswith('ddarm validate: ')
    return captured.err


def edited(tmp_path, name: str, edit) -> Path:
    """A UR5 controller YAML (computed torque, ω = 10) changed by `edit(document, parameters)`."""
    path = write_yaml(tmp_path / name, tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0))
    document = yaml.safe_load(path.read_text())
    edit(document, document['computed_torque']['ros__parameters'])
    path.write_text(yaml.safe_dump(document))
    return path


@pytest.mark.parametrize('name, edit, problem', [
    ('no-law.yaml', lambda document, parameters: document.update(plant=document.pop('computed_torque')),
     "no node key naming a law (pd_gravity or computed_torque)"),
    ('both.yaml', lambda document, parameters: parameters.update(kp=[1.0] * 6, kv=[1.0] * 6),
     'gives the gains twice, keyed by joint (gains) and positional (kp and kv)'),
    ('stranger.yaml', lambda document, parameters: parameters['gains'].update(gripper={'p': 1.0, 'd': 1.0}),
     "has gains for 'gripper', which the motion does not control"),
    ('negative.yaml', lambda document, parameters: parameters['gains']['elbow_joint'].update(p=-5.0),
     'gains.elbow_joint.p is -5.0, not a finite number > 0'),
    ('text-gain.yaml', lambda document, parameters: parameters['gains']['elbow_joint'].update(d='fast'),
     "gains.elbow_joint.d is 'fast', not a finite number > 0"),
    ('no-urdf.yaml', lambda document, parameters: parameters.update(urdf='/nonexistent/arm.urdf'),
     'its urdf /nonexistent/arm.urdf does not exist'),
    ('delay.yaml', lambda document, parameters: parameters.update(delay=1.5),
     'delay is 1.5, not a whole number of samples'),
    ('period.yaml', lambda document, parameters: parameters.update(period='0.01'),
     "period is '0.01', not a number of s"),
    ('omega.yaml', lambda document, parameters: parameters.update(omega=15.0),
     'omega is 15.0: the controller node would replace its gains by the ω rule'),
    ('no-parameters.yaml', lambda document, parameters: document.update(computed_torque={'gains': {}}),
     'computed_torque has no ros__parameters mapping'),
])
def test_a_bad_yaml_is_refused_naming_the_problem(capsys, tmp_path, name, edit, problem):
    gains = edited(tmp_path, name, edit)
    message = refusal(capsys, tmp_path, gains)
    assert problem in message and str(gains) in message


def test_a_missing_file_is_refused(capsys, tmp_path):
    assert 'gains file /nonexistent/gains.yaml does not exist' in refusal(capsys, tmp_path, '/nonexistent/gains.yaml')


def test_a_robot_of_other_joints_is_refused_naming_them(capsys, tmp_path):
    mjcf = tmp_path / 'two.xml'
    mjcf.write_text(TWO_LINK_MJCF)
    gains = write_yaml(tmp_path / 'ur5.yaml', tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0))
    message = refusal(capsys, tmp_path, gains, mjcf)
    assert "has no joint ['shoulder_pan_joint'" in message and "joints ['elbow', 'shoulder'] the motion" in message
    assert list(tmp_path.glob('validate-*')) == []  # refused before any run folder


def test_options_that_do_not_fit_are_refused(capsys, tmp_path):
    gains = write_yaml(tmp_path / 'ur5.yaml', tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0))
    assert 'a paper trajectory (--trajectory) is for a file without one' in refusal(
        capsys, tmp_path, gains, UR5 / 'ur5.urdf', '--trajectory', '2')
    assert main(['validate', '--gains', str(gains), '--runs', str(tmp_path)]) == 2
    assert '--mjcf FILE is required' in capsys.readouterr().err


@pytest.fixture
def two_link(tmp_path):
    return write_files(tmp_path, TWO_LINK_MJCF)


def test_a_robot_that_diverges_says_so_beside_its_numbers(capsys, tmp_path, two_link):
    mjcf, urdf, motion = two_link
    gains = write_yaml(tmp_path / 'stiff.yaml', tuned_spec(urdf, motion, 300.0))
    report = validate_json(capsys, tmp_path, gains, mjcf)
    assert report['measured']['diverged'] is True
    assert report['ratio'] == {'I1': None, 'I2': None, 'I': None}
    assert main(['validate', '--gains', str(gains), '--mjcf', str(mjcf), '--runs', str(tmp_path), '--run', 'text']) == 0
    out = capsys.readouterr().out
    at = report['measured']['diverged_at']
    assert f'measured: DIVERGED at sample {at}' in out
    outcome = next(line for line in out.splitlines() if line.strip().startswith('outcome'))
    assert f'DIVERGED at sample {at}' in outcome
    i1 = next(line for line in out.splitlines() if line.strip().startswith('I1 (2.5)'))
    assert f"{report['measured']['I1']:.6g}*" in i1 and i1.rstrip().endswith('-')


def test_a_prediction_that_diverges_gives_no_ratio_and_the_saturating_robot_is_named(capsys, tmp_path):
    gains = write_yaml(tmp_path / 'ur5.yaml', tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 300.0))
    report = validate_json(capsys, tmp_path, gains, UR5 / 'ur5.urdf')
    assert report['predicted']['diverged'] is True and report['measured']['diverged'] is False
    assert report['ratio'] == {'I1': None, 'I2': None, 'I': None}
    # MuJoCo bounds the UR5's torques by its URDF efforts: the law asked for more than the robot applied.
    assert report['saturated']['measured'] and report['saturated']['predicted'] == []
    page = (Path(report['run']) / 'validation.md').read_text()
    assert 'predicted: DIVERGED at sample' in page and 'measured: saturated: ' in page


def children(pid: int) -> dict[int, str]:
    """The processes whose parent is `pid`, with their command lines."""
    found = {}
    for entry in Path('/proc').iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / 'stat').read_text().rsplit(')', 1)[1].split()[1])
                if ppid == pid:
                    found[int(entry.name)] = (entry / 'cmdline').read_bytes().replace(b'\0', b' ').decode()
            except (OSError, IndexError, ValueError):
                continue
    return found


@pytest.mark.parametrize('stop', [signal.SIGINT, signal.SIGTERM])
def test_a_robot_measurement_stopped_leaves_no_bag_and_no_node(tmp_path, stop):
    spec = dataclasses.replace(tuned_spec(UR5 / 'ur5.urdf', UR5 / 'ur5-motion.yaml', 10.0), duration=60.0)
    gains = write_yaml(tmp_path / 'ur5.yaml', spec)
    process = subprocess.Popen([sys.executable, '-m', 'ddarm.cli.main', 'validate', '--gains', str(gains), '--mjcf',
                                str(UR5 / 'ur5.urdf'), '--robot', 'realtime', '--runs', str(tmp_path), '--run',
                                'stopped'], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        nodes = {}
        while len(nodes) < 2:  # the robot and the controller, running
            assert time.monotonic() < deadline and process.poll() is None, 'the measurement never started'
            nodes = {pid: line for pid, line in children(process.pid).items() if 'ddarm.cli.main' in line}
            time.sleep(0.1)
        time.sleep(2.0)  # into the episode: the controller commanding, the recorder recording
        process.send_signal(stop)
        _, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode != 0 and 'stopped cleanly' in err, err
    assert not (tmp_path / 'stopped' / 'bags' / 'measured').exists()  # no bag rather than half of one
    for pid in nodes:
        assert not Path(f'/proc/{pid}').exists() or 'Z' in Path(f'/proc/{pid}/stat').read_text().split()[2], \
            f'{nodes[pid]} outlived the measurement'
