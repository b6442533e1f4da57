"""Identification (`ddarm identify`): the regressor, the consistent parametrisation, and a robot whose true parameters
differ from its URDF (armature, damping, a payload on its last link) identified from bags it recorded."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from ddarm.cli.main import main
from ddarm.episodes.spec import EpisodeSpec, gains_from_omega
from ddarm.physics.arm import Arm, load_arm
from ddarm.physics.identification import (IdentificationError, consistency_problems, identified_urdf, identify,
                                          link_parameters, period_samples, pseudo_inertia, _link_from_theta,
                                          _theta_from_link)
from ddarm.physics.regressor import base_columns, parameters, regressor, stacked_regressor
from two_link import URDF, robot_mjcf

ROOT = Path(__file__).resolve().parents[1]
PANDA_MENAGERIE = ROOT / 'config' / 'robots' / 'panda' / 'panda-menagerie.urdf'

# The robot: a two-link arm (shoulder about z, elbow about y) whose elbow link carries a payload of 0.8 kg at
# 0.3 m, with armature, damping and friction its URDF does not have (MuJoCo: RK4 at 1 ms).
PAYLOAD = 0.8
ROBOT_MJCF = robot_mjcf(' armature="0.05" damping="0.4" frictionloss="0.3"',
                        ' armature="0.03" damping="0.2" frictionloss="0.1"', payload=PAYLOAD, model='two-payload')


def excitation(path: Path, duration: float, phase: float) -> Path:
    """A waypoint motion of sums of sin² (at rest at both ends) on both joints, every 0.02 s."""
    omega = 2 * np.pi / duration
    amplitude = np.array([[0.9, 0.7], [-0.5, 0.6], [0.4, -0.5]])
    times = np.arange(1, round(duration / 0.02) + 1) * 0.02
    q, v, a = np.zeros((len(times), 2)), np.zeros((len(times), 2)), np.zeros((len(times), 2))
    for k, row in enumerate(amplitude, start=1):
        x = k * omega * times[:, None] + phase * (k - 1)
        q += row * (np.sin(x) ** 2 - np.sin(phase * (k - 1)) ** 2)
        v += row * k * omega * np.sin(2 * x)
        a += row * 2 * (k * omega) ** 2 * np.cos(2 * x)
    v[-1] = a[-1] = 0.0
    points = [{'positions': p.tolist(), 'velocities': s.tolist(), 'accelerations': c.tolist(),
               'time_from_start': float(t)} for p, s, c, t in zip(q, v, a, times)]
    path.write_text(yaml.safe_dump({'joint_names': ['shoulder', 'elbow'], 'start': [0.0, 0.0], 'points': points}))
    return path


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    """The robot's two excitation episodes as bags (one to fit, one held out), under computed torque on the
    nominal URDF, and the files."""
    folder = tmp_path_factory.mktemp('identify')
    robot, urdf = folder / 'robot.xml', folder / 'nominal.urdf'
    robot.write_text(ROBOT_MJCF)
    urdf.write_text(URDF)
    bags = []
    for name, phase in (('fit', 0.0), ('check', 0.7)):
        motion = excitation(folder / f'{name}.yaml', 6.0, phase)
        bag = folder / name
        assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf), '--motion',
                     str(motion), '--mjcf', str(robot), '--ros', '--bag', str(bag), '--json']) == 0
        bags.append(bag)
    return {'folder': folder, 'robot': robot, 'urdf': urdf, 'fit': bags[0], 'check': bags[1]}


def test_the_regressor_times_the_parameters_is_the_inverse_dynamics_with_friction():
    arm = Arm.from_urdf(PANDA_MENAGERIE)
    phi = parameters(arm)
    rng = np.random.default_rng(4)
    for _ in range(10):
        q, v, a = rng.uniform(-1.5, 1.5, 7), rng.uniform(-2, 2, 7), rng.uniform(-5, 5, 7)
        expected = (pin.rnea(arm.model, arm.data, q, v, a) + arm.model.damping * v
                    + arm.model.friction * np.sign(v))  # rnea includes the armature
        assert np.allclose(regressor(arm, q, v, a) @ phi, expected, rtol=1e-12, atol=1e-10)
    assert arm.model.armature.tolist() == [0.1] * 7


def test_the_log_cholesky_coordinates_give_consistent_links_and_round_trip():
    arm = Arm.from_urdf(PANDA_MENAGERIE)
    phi = parameters(arm)
    for i in range(7):
        link = phi[10 * i:10 * (i + 1)]
        np.testing.assert_allclose(link_parameters(pseudo_inertia(link)), link, rtol=1e-12, atol=1e-15)
        assert np.allclose(_link_from_theta(_theta_from_link(link, 1e-12)), link, rtol=1e-6, atol=1e-9)
    rng = np.random.default_rng(0)
    for _ in range(20):
        assert np.linalg.eigvalsh(pseudo_inertia(_link_from_theta(rng.normal(size=10))))[0] > 0
    bad = phi.copy()
    bad[0] = -1.0
    bad[-1] = -0.5
    problems = consistency_problems(arm, bad)
    assert any('panda_joint1: pseudo-inertia' in p for p in problems) and any('friction' in p for p in problems)


def test_the_robots_damping_friction_and_payload_are_identified_and_predict_a_bag_not_fitted(recorded, capsys):
    out = recorded['folder'] / 'identified.urdf'
    assert main(['identify', str(recorded['fit']), '--validate', str(recorded['check']), '--urdf',
                 str(recorded['urdf']), '--out', str(out), '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    shoulder, elbow = report['joints']
    # Both dampings and frictions are told apart by the data. MuJoCo's frictionloss is a constraint that holds a
    # joint still below it, where the model's C sign(q̇) does not: near rest the two differ, hence the tolerances,
    # chosen on this robot (the Panda's, below, has no friction: 5 % on damping there).
    assert shoulder['damping'] == pytest.approx(0.4, rel=0.05) and elbow['damping'] == pytest.approx(0.2, rel=0.05)
    assert shoulder['friction'] == pytest.approx(0.3, rel=0.15) and elbow['friction'] == pytest.approx(0.1, rel=0.15)
    # Each armature acts only together with its link's inertia about the same axis (on this arm no other joint sees
    # that inertia): the data gives their sum, a base parameter, the elbow's: 0.03 + (0.01 + 1 · 0.15²) + (1e-4 +
    # 0.8 · 0.3²) kg m².
    (combined,) = [entry for entry in report['base_parameters'] if entry['pivot'] in ('elbow.armature', 'elbow.Iyy')]
    assert combined['value'] == pytest.approx(0.03 + 0.01 + 0.15 ** 2 + 1e-4 + PAYLOAD * 0.3 ** 2, rel=0.01)
    assert combined['std'] < 0.01 * combined['value']
    # The elbow link with its payload: 1.8 kg, its centre of mass moved out to (0.15 + 0.8 · 0.3) / 1.8 = 0.217 m.
    identified = load_arm(str(out), None, ('shoulder', 'elbow'), ())
    body = identified.model.inertias[2]
    assert body.mass * body.lever[0] == pytest.approx(1.0 * 0.15 + PAYLOAD * 0.3, rel=0.02)
    assert report['condition_number'] < 1000
    # The identified model predicts the held-out bag's torques to 2 % (RMS, per joint).
    for residuals in (report['fit_residual'], report['validation_residual'][0]):
        assert max(value for key, value in residuals.items() if key != 'bag') < 0.02
    assert not consistency_problems(identified, parameters(identified))


def test_a_payload_at_a_known_point_is_weighed_with_every_joints_armature_damping_and_friction(recorded, capsys):
    """With the URDF's links taken as they are, the payload's mass and both armatures are identifiable too."""
    out = recorded['folder'] / 'payload.urdf'
    assert main(['identify', str(recorded['fit']), '--validate', str(recorded['check']), '--urdf',
                 str(recorded['urdf']), '--out', str(out), '--payload', 'l2=0.3,0,0', '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['payload']['link'] == 'l2' and report['payload']['point'] == [0.3, 0.0, 0.0]
    assert report['payload']['mass'] == pytest.approx(PAYLOAD, rel=0.02) and report['payload']['std'] < 0.01
    shoulder, elbow = report['joints']
    assert shoulder['armature'] == pytest.approx(0.05, rel=0.05) and elbow['armature'] == pytest.approx(0.03, rel=0.05)
    assert shoulder['damping'] == pytest.approx(0.4, rel=0.05) and elbow['damping'] == pytest.approx(0.2, rel=0.05)
    assert shoulder['friction'] == pytest.approx(0.3, rel=0.15) and elbow['friction'] == pytest.approx(0.1, rel=0.15)
    body = load_arm(str(out), None, ('shoulder', 'elbow'), ()).model.inertias[2]
    assert body.mass == pytest.approx(1.0 + report['payload']['mass'], rel=1e-12)
    for link, words in (('l9', "'l9' is not a link"), ('base', 'fixed to the base')):
        assert main(['identify', str(recorded['fit']), '--urdf', str(recorded['urdf']), '--out',
                     str(recorded['folder'] / f'{link}.urdf'), '--payload', f'{link}=0,0,0']) == 2
        assert words in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:  # argparse's refusal
        main(['identify', str(recorded['fit']), '--urdf', str(recorded['urdf']), '--out',
              str(recorded['folder'] / 'bad.urdf'), '--payload', 'l2=0,0'])
    assert refused.value.code == 2 and 'LINK=X,Y,Z' in capsys.readouterr().err


def test_an_episode_on_the_identified_urdf_predicts_the_robot_better_than_the_nominal_one(recorded, capsys):
    out = recorded['folder'] / 'for-prediction.urdf'
    assert main(['identify', str(recorded['fit']), '--urdf', str(recorded['urdf']), '--out', str(out)]) == 0
    capsys.readouterr()
    errors = {}
    for name, urdf in (('nominal', recorded['urdf']), ('identified', out)):
        spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 2, kv=(1.0,) * 2, urdf=str(urdf),
                           motion=str(recorded['folder'] / 'check.yaml'))
        kp, kv = gains_from_omega(spec, 15.0)
        spec = dataclasses.replace(spec, kp=tuple(kp), kv=tuple(kv))
        from ddarm.episodes.engine import run_episode

        predicted = run_episode(spec).indices()['I1']
        measured = run_episode(dataclasses.replace(spec, mjcf=str(recorded['robot']))).indices()['I1']
        errors[name] = abs(predicted - measured) / measured
    assert errors['identified'] < 0.1 < errors['nominal']


def test_the_panda_robots_armature_and_damping_are_identified_where_the_data_tells_them_apart(tmp_path):
    """The MuJoCo Panda (Menagerie's armature 0.1 and damping 1 on every joint, no hand) identified from one
    excitation, in process, starting from the shipped URDF (no armature, damping 0.003, a hand). Joints 3 to 7's
    armature is told apart from their links' inertia (other joints' axes see those links turn); joints 1 and 2's
    acts only with their links' inertia about their own axes, whose sum alone the data gives."""
    from ddarm.episodes.engine import run_episode
    from ddarm.physics.identification import joint_parameters

    duration, omega = 10.0, 2 * np.pi / 10.0
    centre = np.array([0.0, 0.0, 0.0, -1.6, 0.0, 1.6, 0.0])
    amplitude = np.random.default_rng(1).uniform(-1, 1, (4, 7)) * [0.8, 0.5, 0.8, 0.6, 0.9, 0.6, 1.0] / 4
    times = np.arange(1, 201) * 0.05
    q, v, a = np.tile(centre, (200, 1)), np.zeros((200, 7)), np.zeros((200, 7))
    for k, harmonic in enumerate((1, 2, 3, 5)):
        x = harmonic * omega * times[:, None]
        q, v = q + amplitude[k] * np.sin(x) ** 2, v + amplitude[k] * harmonic * omega * np.sin(2 * x)
        a = a + amplitude[k] * 2 * (harmonic * omega) ** 2 * np.cos(2 * x)
    v[-1] = 0.0
    joints = [f'panda_joint{i}' for i in range(1, 8)]
    motion = tmp_path / 'excite.yaml'
    motion.write_text(yaml.safe_dump({'joint_names': joints, 'start': centre.tolist(), 'points': [
        {'positions': p.tolist(), 'velocities': s.tolist(), 'accelerations': c.tolist(), 'time_from_start': float(t)}
        for p, s, c, t in zip(q, v, a, times)]}))
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 7, kv=(1.0,) * 7, urdf=str(PANDA_MENAGERIE),
                       motion=str(motion), mjcf=str(ROOT / 'config' / 'robots' / 'panda' / 'panda.xml'))
    kp, kv = gains_from_omega(spec, 15.0)
    episode = run_episode(dataclasses.replace(spec, kp=tuple(kp), kv=tuple(kv)))
    nominal = load_arm(str(ROOT / 'config' / 'arms' / 'panda' / 'panda.urdf'), None, tuple(joints),
                       (('panda_finger_joint1', 0.02),))
    result = identify(nominal, period_samples(episode.scored('q'), episode.scored('v'), episode.scored('torque'),
                                              0.01))
    found = joint_parameters(result.estimate, 7)
    np.testing.assert_allclose(found['armature'][2:], 0.1, rtol=0.03)
    np.testing.assert_allclose(found['damping'], 1.0, rtol=0.05)
    np.testing.assert_allclose(found['friction'], 0.0, atol=0.01)
    pivots = {result.names[column] for column in result.base}
    assert {f'panda_joint{i}.armature' for i in range(3, 8)} <= pivots
    assert np.max(result.fit_residual) < 0.005 and not consistency_problems(nominal, result.estimate)


def test_too_little_or_too_poorly_excited_data_is_refused_saying_what_to_change(recorded):
    arm = load_arm(str(recorded['urdf']), None, ('shoulder', 'elbow'), ())
    rng = np.random.default_rng(1)
    q, v = rng.uniform(-1, 1, (8, 2)), rng.uniform(-1, 1, (8, 2))
    with pytest.raises(IdentificationError, match='too few'):
        identify(arm, period_samples(q, v, rng.uniform(-1, 1, (8, 2)), 0.01))
    # A still arm excites nothing but gravity.
    still = np.tile([0.3, 0.2], (400, 1))
    with pytest.raises(IdentificationError, match=r'the data excites \d+ of the arm\'s \d+ base parameters'):
        identify(arm, period_samples(still + 1e-9 * rng.normal(size=still.shape), np.zeros((400, 2)),
                                     rng.normal(size=(400, 2)), 0.01))
    assert len(base_columns(stacked_regressor(arm, q, v, rng.normal(size=(8, 2))))) > 0


def test_bags_of_other_joints_or_a_urdf_without_them_are_refused_naming_them(recorded, tmp_path, capsys):
    other = tmp_path / 'other.urdf'
    other.write_text(URDF.replace('"elbow"', '"knee"'))
    assert main(['identify', str(recorded['fit']), '--urdf', str(other), '--out', str(tmp_path / 'x.urdf')]) == 2
    assert "'elbow'" in capsys.readouterr().err
    assert main(['identify', str(tmp_path / 'missing'), '--urdf', str(recorded['urdf']), '--out',
                 str(tmp_path / 'y.urdf')]) == 2
    assert 'no such bag' in capsys.readouterr().err
    assert not (tmp_path / 'x.urdf').exists() and not (tmp_path / 'y.urdf').exists()


def test_the_written_urdf_carries_exactly_the_identified_parameters(recorded, tmp_path):
    arm = load_arm(str(recorded['urdf']), None, ('shoulder', 'elbow'), ())
    phi = parameters(arm) * 1.1
    text = identified_urdf(arm, phi, 'a test -- with hyphens')
    path = tmp_path / 'written.urdf'
    path.write_text(text)
    np.testing.assert_allclose(parameters(load_arm(str(path), None, ('shoulder', 'elbow'), ())), phi, rtol=1e-12,
                               atol=1e-15)
    assert '--' not in text.split('-->')[0].removeprefix('<?xml version="1.0"?>\n<!--')


def test_a_bag_without_efforts_is_refused_saying_so(tmp_path):
    from ddarm.cli.identify import bag_periods
    from ddarm.recording.bags import BagEpisode

    states = {n: (np.full(2, 0.01 * n), np.full(2, 1.0), None) for n in range(50)}
    bag = BagEpisode(episode={'spec': {'period': 0.01}}, status='complete', joints=['shoulder', 'elbow'],
                     reference_times=np.zeros(0), q_ref=np.zeros((0, 2)), v_ref=np.zeros((0, 2)),
                     a_ref=np.zeros((0, 2)), nominal=np.zeros((0, 2)), states=states, commands={},
                     path=tmp_path / 'no-efforts')
    with pytest.raises(IdentificationError, match='no-efforts: it holds 0 periods with states and efforts'):
        bag_periods(bag, None)


def test_samples_within_the_standard_deviations_are_consistent_urdfs_a_robust_tuning_takes(recorded, capsys):
    from ddarm.tuning.robust import scenario_grid

    out = recorded['folder'] / 'sampled.urdf'
    assert main(['identify', str(recorded['fit']), '--urdf', str(recorded['urdf']), '--out', str(out),
                 '--samples', '3', '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    paths = [Path(path) for path in report['samples_written']]
    assert [path.name for path in paths] == [f'sampled-sample-{k}.urdf' for k in (1, 2, 3)]
    joints = ('shoulder', 'elbow')
    estimate = parameters(load_arm(str(out), None, joints, ()))
    stds = {entry['pivot']: entry['std'] for entry in report['base_parameters']}
    names = [*(f'{joint}.{p}' for joint in joints for p in ('m', 'mcx', 'mcy', 'mcz', 'Ixx', 'Ixy', 'Iyy', 'Ixz',
                                                             'Iyz', 'Izz')),
             *(f'{joint}.{p}' for p in ('armature', 'damping', 'friction') for joint in joints)]
    for path in paths:
        arm = load_arm(str(path), None, joints, ())
        sample = parameters(arm)
        assert not consistency_problems(arm, sample) and not np.array_equal(sample, estimate)
        for name, value, centre in zip(names, sample, estimate):
            assert abs(value - centre) <= (6 * stds[name] if name in stds else 1e-12 * max(1.0, abs(centre)))
    template = EpisodeSpec(controller='computed_torque', kp=(225.0, 225.0), kv=(30.0, 30.0), urdf=str(out),
                           motion=str(recorded['folder'] / 'check.yaml'))
    scenarios = scenario_grid(template, urdfs=[str(path) for path in paths])
    assert [s.urdf for s in scenarios] == [str(path) for path in paths]
    assert all(s.model_urdf == str(out) for s in scenarios)


def test_the_cutoff_filters_measured_noise_out_before_the_differences():
    """--cutoff: a zero-phase low-pass over q, q̇ and the torque; the acceleration of a slow motion measured with
    noise comes out near the true one, and a recording too short to filter is refused."""
    period = 0.001
    times = np.arange(2001) * period
    q = np.sin(2 * np.pi * times)[:, None]
    v = (2 * np.pi * np.cos(2 * np.pi * times))[:, None]
    noise = 1e-3 * np.random.default_rng(0).standard_normal(v.shape)
    true = -(2 * np.pi) ** 2 * np.sin(2 * np.pi * (times[:-1] + 0.5 * period))[:, None]
    raw = period_samples(q, v + noise, np.zeros_like(q), period)
    filtered = period_samples(q, v + noise, np.zeros_like(q), period, cutoff=20.0)
    interior = slice(200, -200)  # away from the filter's edges
    assert np.max(np.abs(filtered.a - true)[interior]) < 0.1 * np.max(np.abs(raw.a - true)[interior])
    with pytest.raises(IdentificationError, match='too few to filter'):
        period_samples(q[:10], v[:10], np.zeros((10, 1)), period, cutoff=20.0)
    with pytest.raises(IdentificationError, match='cutoff must be within'):
        period_samples(q, v, np.zeros_like(q), period, cutoff=600.0)
