"""`ddarm transfer`: tune, validate, identify, re-tune, validate, on a two-link robot that is not its URDF.

The robot is the two-link arm of test_mujoco_plant.py with armature, damping and a payload its URDF lacks (as in
test_identify.py). The run's numbers are checked against the episodes run again from the YAMLs it wrote, and the
verdict against its definition.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
from pathlib import Path

import pytest

from ddarm.cli.main import main
from ddarm.episodes.engine import run_episode
from ddarm.episodes.indices import INDICES
from ddarm.recording.gains_file import read_gains_file, validation_spec
from two_link import MOTION, URDF, robot_mjcf

PAYLOAD = 0.8
ROBOT_MJCF = robot_mjcf(' armature="0.05" damping="0.4"', ' armature="0.03" damping="0.2"', payload=PAYLOAD,
                        model='two-payload')
RUN_FILES = ('nominal.yaml', 'excite.yaml', 'bags/fit', 'bags/check', 'identified.urdf', 'retuned.yaml',
             'transfer.md', 'transfer.html', 'summary.json', 'errors-nominal.png', 'errors-retuned.png')


def transfer(files: dict, runs: Path, *extra: str) -> tuple[int, str, str]:
    """`ddarm transfer` on the files with a small budget: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(['transfer', '--controller', 'computed_torque', '--urdf', str(files['urdf']), '--motion',
                     str(files['motion']), '--mjcf', str(files['robot']), '--budget', '300', '--excite-duration', '6',
                     '--runs', str(runs), *extra])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope='module')
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp('transfer')
    paths = {'robot': folder / 'robot.xml', 'urdf': folder / 'two.urdf', 'motion': folder / 'two-motion.yaml'}
    for key, text in (('robot', ROBOT_MJCF), ('urdf', URDF), ('motion', MOTION)):
        paths[key].write_text(text)
    return paths


@pytest.fixture(scope='module')
def run(files, tmp_path_factory):
    runs = tmp_path_factory.mktemp('runs')
    code, out, _ = transfer(files, runs, '--run', 'two', '--json')
    assert code == 0
    return runs / 'two', json.loads(out)


def relative_error(measured: float, predicted: float) -> float:
    return abs(measured - predicted) / measured


def test_every_artefact_is_in_the_run_folder(run):
    folder, report = run
    for name in RUN_FILES:
        assert (folder / name).exists(), name
    assert report['run'] == str(folder)
    assert report['bags'] == [str(folder / 'bags' / 'fit'), str(folder / 'bags' / 'check')]
    summary = json.loads((folder / 'summary.json').read_text())
    assert summary['status'] == 'complete'
    assert {key: summary[key] for key in report} == report
    assert read_gains_file(folder / 'retuned.yaml').urdf == str((folder / 'identified.urdf').resolve())
    page = (folder / 'transfer.md').read_text()
    assert report['verdict'] in page and 'times lower' in page
    # 300 episodes certify neither search: the report, the page and each gains file say so.
    for phase in ('nominal', 'retuned'):
        assert report[phase]['converged'] is False and report[phase]['certainty'].startswith('not converged: ')
        assert report[phase]['certainty'] in page
        assert 'the search did not converge' in (folder / f'{phase}.yaml').read_text()


def test_the_numbers_are_the_episodes_of_the_yamls_run_again(run, files):
    _, report = run
    for phase in ('nominal', 'retuned'):
        predicted_spec = validation_spec(read_gains_file(report[phase]['gains']), tau=0.0, torque_limit='none')
        measured_spec = dataclasses.replace(predicted_spec, mjcf=str(files['robot']))
        for side, spec in (('predicted', predicted_spec), ('measured', measured_spec)):
            result = run_episode(spec)
            assert report[phase][side]['diverged'] == bool(result.diverged[0])
            for index, value in result.indices().items():
                assert report[phase][side][index] == pytest.approx(value, rel=1e-9, abs=0)
    nominal, retuned = report['nominal']['measured'], report['retuned']['measured']
    assert report['improvement_I1'] == pytest.approx(nominal['I1'] / retuned['I1'], rel=1e-12)


def test_the_robot_is_identified_and_the_retuned_prediction_is_the_robot(run):
    _, report = run
    shoulder, elbow = report['identification']['joints']
    assert shoulder['damping'] == pytest.approx(0.4, rel=0.05) and elbow['damping'] == pytest.approx(0.2, rel=0.05)
    assert set(report['identification']['validation_residual']) == {'bag', 'shoulder', 'elbow'}
    # The nominal gains' prediction is far from the robot; the retuned gains' is within the tolerance.
    before, after = report['nominal'], report['retuned']
    assert before['measured']['I'] > 10 * before['predicted']['I']
    within = relative_error(after['measured']['I'], after['predicted']['I']) <= report['tolerance']
    assert within and report['transfers'] is True
    assert report['verdict'].startswith('transfers')
    assert report['improvement_I1'] > 10


def test_a_tolerance_the_prediction_misses_does_not_transfer(files, tmp_path):
    code, out, _ = transfer(files, tmp_path, '--run', 'tight', '--tolerance', '1e-6')
    assert code == 0
    report = json.loads((tmp_path / 'tight' / 'summary.json').read_text())
    after = report['retuned']
    assert relative_error(after['measured']['I'], after['predicted']['I']) > 1e-6
    assert report['transfers'] is False and report['tolerance'] == 1e-6
    assert 'does not transfer: ' in out and 'transfers: ' not in out
    assert "measured I1 of the retuned gains is" in out
    assert all(f"WARNING: the {phase} search: {report[phase]['certainty']}" in out for phase in ('nominal', 'retuned'))
    for phase in ('nominal', 'retuned'):
        for index in INDICES:
            assert math.isfinite(report[phase]['measured'][index])


def test_a_robot_of_other_joints_is_refused_before_any_work(files, tmp_path):
    robot = tmp_path / 'other.xml'
    robot.write_text(ROBOT_MJCF.replace('"elbow"', '"wrist"'))
    code, out, err = transfer({**files, 'robot': robot}, tmp_path / 'runs')
    assert code == 2 and out == ''
    assert err.count('\n') == 1 and err.startswith('ddarm transfer: ') and 'elbow' in err
    assert not (tmp_path / 'runs').exists()  # refused before any run folder


def test_a_retuning_robust_over_the_identifications_samples_reports_its_predicted_worst_case(files, tmp_path):
    code, out, _ = transfer(files, tmp_path, '--run', 'robust', '--samples', '2')
    assert code == 0
    report = json.loads((tmp_path / 'robust' / 'summary.json').read_text())
    retuned = report['retuned']
    assert [Path(path).name for path in retuned['samples']] == ['identified-sample-1.urdf',
                                                                 'identified-sample-2.urdf']
    assert all(Path(path).is_file() for path in retuned['samples'])
    # The point estimate is one of the scenarios: the worst case is at least its prediction.
    assert retuned['predicted_worst'] >= retuned['predicted']['I'] * (1 - 1e-12)
    assert 'predicted worst I' in out and 'predicted worst I' in (tmp_path / 'robust' / 'transfer.md').read_text()

