"""MuJoCo as the plant (`ddarm episode --mjcf`): against an independent MuJoCo loop written here, and its refusals.

The independent loop takes from ddarm nothing but the files: it reads the motion as YAML, computes the laws with
Pinocchio on the URDF (test_arms' independent dynamics), holds the torque by MuJoCo's own ctrl and applied forces,
and steps MuJoCo the period's timesteps.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import deque
from pathlib import Path

import mujoco
import numpy as np
import pytest

from ddarm.cli.main import main
from ddarm.episodes.engine import BatchError, run_episode, simulate_batch
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, check_episode, gains_from_omega, plan_episode, plant_chain
from ddarm.episodes.stepwise import run_stepwise
from ddarm.physics.plant import Plant, PlantOptions
from test_arms import HELD, Dynamics, bang_bang, read_motion, reduced_model
from two_link import robot_mjcf, write_files

ROOT = Path(__file__).resolve().parents[1]
ARMS = ROOT / 'config' / 'arms'

# A two-link arm with what MuJoCo models and ddarm's plant does not: armature, damping, frictionloss, a motor with a
# gear, a control and a force range, an actuator force range on an unactuated joint; RK4 at 1 ms.
TWO_LINK_MJCF = robot_mjcf(' armature="0.02" damping="0.3" frictionloss="0.05"',
                           ' armature="0.01" damping="0.1" actuatorfrcrange="-1.5 1.5"',
                           actuators='<motor name="shoulder_motor" joint="shoulder" gear="2" ctrlrange="-3 3" '
                                     'forcerange="-2 2"/>')


@pytest.fixture
def two_link(tmp_path):
    return write_files(tmp_path, TWO_LINK_MJCF)


def independent_mujoco_episode(mjcf: Path, urdf: Path, motion_path: Path, controller: str, kp, kv, delay: int,
                               period: float, tau: float = 0.0, held: dict | None = None,
                               duration: float | None = None, servo_limits: dict | None = None) -> dict:
    """One episode of the law on the URDF's model against MuJoCo's robot, from the files alone (the bang-bang
    motion stretched to `duration`, if given)."""
    motion = read_motion(motion_path)
    names, start, goal = motion['joint_names'], motion['start'], motion['goal']
    duration = duration or motion['duration']
    robot = mujoco.MjModel.from_xml_path(str(mjcf))
    data = mujoco.MjData(robot)
    joints = [robot.joint(name).id for name in names]
    qpos, dofs = robot.jnt_qposadr[joints], robot.jnt_dofadr[joints]
    motors = {int(robot.actuator_trnid[a, 0]): a for a in range(robot.nu)}
    if servo_limits is not None:  # the robot's servos off, every torque an applied force within the servo's range
        robot.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
        motors = {}
    model = Dynamics(reduced_model(urdf, names, held or {}))
    steps = round(period / robot.opt.timestep)
    k_max = round(duration / period)
    reference = [bang_bang(start, goal, duration, k * period) for k in range(k_max + 1)]
    kp, kv = np.asarray(kp, dtype=float), np.asarray(kv, dtype=float)
    data.qpos[qpos], data.qvel[dofs] = start, -bang_bang(start, goal, duration, tau)[1]
    mujoco.mj_forward(robot, data)
    history = deque(maxlen=delay + 1)
    qs, commands, torques = [], [], []
    for k in range(k_max + 1):
        q, v = data.qpos[qpos].copy(), data.qvel[dofs].copy()
        history.append((q, v, reference[k]))
        qm, vm, (q_ref_m, v_ref_m, _) = history[0]
        error, rate = q_ref_m - qm, v_ref_m - vm
        if controller == 'pd_gravity':
            command = kp * error + kv * rate + model.gravity(reference[k][0])
        else:
            command = (model.mass(qm) @ (reference[k][2] + kp * error + kv * rate) + model.bias(qm, vm)
                       + model.friction(vm))
        qs.append(q)
        commands.append(command)
        if k == k_max:
            break
        data.ctrl[:], data.qfrc_applied[:] = 0.0, 0.0
        for joint, dof, value in zip(joints, dofs, command):
            if joint in motors:  # MuJoCo bounds ctrl, force and the joint's actuator force itself
                data.ctrl[motors[joint]] = value / (robot.actuator_gear[motors[joint], 0]
                                                    * robot.actuator_gainprm[motors[joint], 0])
            elif servo_limits is not None and robot.joint(joint).name in servo_limits:
                data.qfrc_applied[dof] = np.clip(value, *servo_limits[robot.joint(joint).name])
            elif robot.jnt_actfrclimited[joint]:
                data.qfrc_applied[dof] = np.clip(value, *robot.jnt_actfrcrange[joint])
            else:
                data.qfrc_applied[dof] = value
        for _ in range(steps):
            mujoco.mj_step(robot, data)
        torques.append(data.qfrc_actuator[dofs] + data.qfrc_applied[dofs])
    return {'q': np.array(qs), 'command': np.array(commands), 'torque': np.array(torques)}


def robot_spec(urdf: Path, motion: Path, mjcf: Path, controller: str, omega: float, **options) -> EpisodeSpec:
    spec = EpisodeSpec(controller=controller, kp=(1.0,), kv=(1.0,), urdf=str(urdf), motion=str(motion),
                       mjcf=str(mjcf), **options)
    kp, kv = gains_from_omega(spec, omega)
    return dataclasses.replace(spec, kp=tuple(kp), kv=tuple(kv))


def assert_same_as_independent(episode, expected: dict) -> None:
    assert not episode.diverged[0]
    np.testing.assert_allclose(episode.scored('q'), expected['q'], rtol=0, atol=1e-9)
    np.testing.assert_allclose(episode.scored('command'), expected['command'], rtol=1e-9,
                               atol=1e-9 * np.max(np.abs(expected['command'])))
    np.testing.assert_allclose(episode.scored('torque')[:-1], expected['torque'], rtol=1e-12,
                               atol=1e-12 * np.max(np.abs(expected['torque'])))


@pytest.mark.parametrize('controller, omega, delay', [('pd_gravity', 6.0, 0), ('computed_torque', 12.0, 1),
                                                      ('computed_torque', 8.0, 2)])
def test_the_mjcf_episode_is_the_independent_mujoco_loop_on_a_two_link_arm(two_link, controller, omega, delay):
    mjcf, urdf, motion = two_link
    spec = robot_spec(urdf, motion, mjcf, controller, omega, delay=delay, tau=0.1)
    episode = run_episode(spec)
    expected = independent_mujoco_episode(mjcf, urdf, motion, controller, spec.kp, spec.kv, delay, spec.period,
                                          tau=0.1)
    assert_same_as_independent(episode, expected)
    # The motor's force range (2 N at gear 2: 4 N m) and the elbow's actuator force range (1.5 N m) were reached.
    torque = episode.scored('torque')
    assert np.max(np.abs(torque), axis=0).tolist() == [4.0, 1.5]


@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
def test_the_mjcf_episode_is_the_independent_mujoco_loop_on_the_ur5_urdf_mujoco_compiles(controller):
    """A URDF as the robot: MuJoCo compiles it (its own integrator, Euler at 2 ms; joint limits as constraints)."""
    urdf, motion = ARMS / 'ur5' / 'ur5.urdf', ARMS / 'ur5' / 'ur5-motion.yaml'
    spec = robot_spec(urdf, motion, urdf, controller, 10.0 if controller == 'computed_torque' else 3.0, delay=1,
                      duration=0.5)
    episode = run_episode(spec)
    expected = independent_mujoco_episode(urdf, urdf, motion, controller, spec.kp, spec.kv, 1, spec.period,
                                          duration=0.5)
    assert len(episode.scored('q')) == 51
    assert_same_as_independent(episode, expected)


@pytest.mark.parametrize('controller, omega', [('pd_gravity', 2.0), ('computed_torque', 15.0)])
def test_the_mjcf_episode_is_the_independent_mujoco_loop_on_the_shipped_panda_robot(controller, omega):
    """The shipped Panda robot (Menagerie's armature and damping, implicitfast) under the law on panda.urdf."""
    urdf, motion = ARMS / 'panda' / 'panda.urdf', ARMS / 'panda' / 'panda-motion.yaml'
    mjcf = ROOT / 'config' / 'robots' / 'panda' / 'panda.xml'
    spec = robot_spec(urdf, motion, mjcf, controller, omega, delay=1, tau=0.05)
    expected = independent_mujoco_episode(mjcf, urdf, motion, controller, spec.kp, spec.kv, 1, spec.period, tau=0.05,
                                          held=HELD['panda'])
    assert_same_as_independent(run_episode(spec), expected)


@pytest.mark.parametrize('arm', ['ur5', 'panda', 'scara'])
@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
def test_the_stepwise_loop_on_ddarms_plant_is_the_batch_engines_episode(arm, controller):
    """The loop a MuJoCo episode runs, given ddarm's own plant, is the batch engine's episode: a MuJoCo episode
    differs from ddarm's by the plant alone."""
    spec = EpisodeSpec(controller=controller, kp=(1.0,), kv=(1.0,), urdf=str(ARMS / arm / f'{arm}.urdf'),
                       motion=str(ARMS / arm / f'{arm}-motion.yaml'), tau=0.05, delay=2, duration=0.5,
                       torque_limit='urdf', viscous_friction=None)
    kp, kv = gains_from_omega(spec, 10.0 if controller == 'computed_torque' else 2.0)
    spec = dataclasses.replace(spec, kp=tuple(kp), kv=tuple(kv))
    plan = check_episode(spec)
    plant = Plant(plant_chain(spec), PlantOptions(period=spec.period, substeps=spec.substeps,
                                                  torque_limit=plan.torque_limit), plan.q0, plan.v0)
    stepwise, batch = run_stepwise(spec, plan, plant), run_episode(spec, plan)
    assert stepwise.indices() == pytest.approx(batch.indices(), rel=1e-12)
    for name in ('q', 'v', 'command', 'torque'):
        np.testing.assert_allclose(stepwise.scored(name), batch.scored(name), rtol=1e-11, atol=1e-11)


def test_a_robots_servos_are_switched_off_said_and_their_force_range_bounds_the_applied_torque(two_link, tmp_path,
                                                                                                  capsys):
    _, urdf, motion = two_link
    servo = mjcf_with(tmp_path, '<motor name="shoulder_motor" joint="shoulder" gear="2" ctrlrange="-3 3" '
                                'forcerange="-2 2"/>', '<position name="servo" joint="shoulder" kp="100" '
                                                       'forcerange="-3 3"/>')
    spec = robot_spec(urdf, motion, servo, 'computed_torque', 12.0, delay=1, tau=0.1)
    episode = run_episode(spec)
    expected = independent_mujoco_episode(servo, urdf, motion, 'computed_torque', spec.kp, spec.kv, 1, spec.period,
                                          tau=0.1, servo_limits={'shoulder': (-3.0, 3.0), 'elbow': (-1.5, 1.5)})
    assert_same_as_independent(episode, expected)
    assert np.max(np.abs(episode.scored('torque')), axis=0).tolist() == [3.0, 1.5]
    assert main(['episode', '--controller', 'computed_torque', '--urdf', str(urdf), '--motion', str(motion),
                 '--mjcf', str(servo), '--omega', '12', '--json']) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed['robot']['bypassed_actuators'] == ['servo']
    assert any("servo actuators ['servo']" in warning and 'switched off' in warning for warning in printed['warnings'])


def test_a_diverging_robot_episode_ends_at_the_sample_it_left_the_bounds(two_link, tmp_path):
    _, urdf, motion = two_link
    unlimited = tmp_path / 'unlimited.xml'
    unlimited.write_text(TWO_LINK_MJCF.replace(' ctrlrange="-3 3" forcerange="-2 2"', '')
                         .replace(' actuatorfrcrange="-1.5 1.5"', ''))
    spec = robot_spec(urdf, motion, unlimited, 'computed_torque', 400.0, delay=1)
    episode = run_episode(spec)
    assert episode.diverged[0]
    at = int(episode.diverged_at[0])
    assert 0 < at <= episode.plan.k_max and episode.samples_scored[0] == at
    assert np.all(np.abs(episode.scored('q')) <= 100.0)


def test_ddarm_episode_mjcf_prints_the_robots_indices_and_what_the_robot_is(two_link, capsys):
    mjcf, urdf, motion = two_link
    assert main(['episode', '--controller', 'computed_torque', '--urdf', str(urdf), '--motion', str(motion),
                 '--mjcf', str(mjcf), '--omega', '12', '--json']) == 0
    printed = json.loads(capsys.readouterr().out)
    spec = robot_spec(urdf, motion, mjcf, 'computed_torque', 12.0)
    assert printed['I'] == run_episode(spec).indices()['I']
    assert printed['spec']['mjcf'] == str(mjcf)
    robot = printed['robot']
    assert robot['mjcf'] == str(mjcf) and robot['timestep'] == 0.001 and robot['steps_per_period'] == 10
    assert robot['integrator'] == 'rk4' and robot['engine'].startswith('MuJoCo ')
    assert robot['joint_map'] == {'shoulder': 'shoulder', 'elbow': 'elbow'}


def test_a_joint_map_names_the_mjcfs_joints(two_link, tmp_path, capsys):
    mjcf, urdf, motion = two_link
    renamed = tmp_path / 'renamed.xml'
    renamed.write_text(TWO_LINK_MJCF.replace('"shoulder"', '"j1"').replace('"elbow"', '"j2"'))
    arguments = ['episode', '--controller', 'computed_torque', '--urdf', str(urdf), '--motion', str(motion),
                 '--omega', '12', '--json']
    assert main([*arguments, '--mjcf', str(mjcf)]) == 0
    same = json.loads(capsys.readouterr().out)
    assert main([*arguments, '--mjcf', str(renamed), '--joint-map', 'shoulder=j1', 'elbow=j2']) == 0
    mapped = json.loads(capsys.readouterr().out)
    assert mapped['I'] == same['I'] and mapped['robot']['joint_map'] == {'shoulder': 'j1', 'elbow': 'j2'}
    assert main([*arguments, '--mjcf', str(renamed)]) == 2
    refusal = capsys.readouterr().err
    assert "has no joint ['shoulder', 'elbow']" in refusal and "['j1', 'j2']" in refusal and '--joint-map' in refusal


def mjcf_with(tmp_path: Path, old: str, new: str) -> Path:
    path = tmp_path / 'edited.xml'
    assert old in TWO_LINK_MJCF
    path.write_text(TWO_LINK_MJCF.replace(old, new))
    return path


@pytest.mark.parametrize('edit, words', [
    (('<motor name="shoulder_motor" joint="shoulder" gear="2" ctrlrange="-3 3" forcerange="-2 2"/>',
      '<motor name="a" joint="shoulder"/><motor name="b" joint="shoulder"/>'), ["'shoulder' has two motors"]),
    (('<actuator>', '<tendon><fixed name="t"><joint joint="shoulder" coef="1"/></fixed></tendon><actuator>'
                    '<motor name="pull" tendon="t"/>'),
     ["actuator 'pull' does not drive one of the controlled joints directly"]),
    (('<option timestep="0.001"', '<option timestep="0.003"'), ['0.01 s is not a whole number', '0.003']),
    (('<joint name="elbow" type="hinge"', '<joint name="elbow" type="slide"'), ["'elbow' is a slide joint",
                                                                               'revolute']),
    (('<inertial pos="0.15 0 0"', '<joint name="wrist" type="hinge"/><inertial pos="0.15 0 0"'),
     ["has joints ['wrist'] the motion does not control"]),
    (('<joint name="shoulder" type="hinge" axis="0 0 1" armature="0.02" damping="0.3" frictionloss="0.05"/>',
      '<freejoint name="shoulder"/>'), ["['shoulder'] are free or ball joints"]),
    (('<worldbody>', '<worldbody><body'), ['is not a model MuJoCo compiles']),
])
def test_a_robot_that_is_not_the_arm_is_refused_naming_why(two_link, tmp_path, capsys, edit, words):
    _, urdf, motion = two_link
    path = mjcf_with(tmp_path, *edit)
    assert main(['episode', '--controller', 'computed_torque', '--urdf', str(urdf), '--motion', str(motion),
                 '--mjcf', str(path), '--omega', '12']) == 2
    captured = capsys.readouterr()
    assert captured.out == '' and 'Traceback' not in captured.err
    for word in words:
        assert word in captured.err


def test_options_of_ddarms_own_plant_and_the_batch_engine_refuse_a_robot(two_link, tmp_path, capsys):
    mjcf, urdf, motion = two_link
    for option in (['--mass-scale', '1', '1'], ['--viscous-friction', '1', '1'], ['--external-torque', '0', '1']):
        assert main(['episode', '--controller', 'pd_gravity', '--urdf', str(urdf), '--motion', str(motion),
                     '--mjcf', str(mjcf), '--omega', '5', *option]) == 2
        assert "change ddarm's own plant" in capsys.readouterr().err
    missing = tmp_path / 'missing.xml'
    assert main(['episode', '--controller', 'pd_gravity', '--urdf', str(urdf), '--motion', str(motion),
                 '--mjcf', str(missing), '--omega', '5']) == 2
    assert f'MJCF {missing} cannot be read: No such file or directory' in capsys.readouterr().err
    spec = robot_spec(urdf, motion, mjcf, 'pd_gravity', 5.0)
    with pytest.raises(BatchError, match='one episode at a time'):
        simulate_batch(spec, [spec.kp], [spec.kv])
    with pytest.raises(EpisodeError, match='give its mjcf'):
        EpisodeSpec(controller='pd_gravity', kp=(1.0,), kv=(1.0,), mjcf_joints=('a', 'b'))
    with pytest.raises(EpisodeError, match='names 1 joints'):
        check_episode(dataclasses.replace(spec, mjcf_joints=('shoulder',)))
    assert plan_episode(spec).joint_names == ('shoulder', 'elbow')
    assert math.isfinite(run_episode(spec).I[0])


# ---------------------------------------------------------------------------------------------------------------
# Through the ROS graph: the plant node steps the robot (its `mjcf` parameter)


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    from ddarm.ros.session import GraphSession

    with GraphSession(tmp_path_factory.mktemp('nodes'), timeout=60.0) as session:
        yield session


def test_the_panda_robot_through_the_graph_is_the_in_process_episode_and_its_bag_scores_the_same(graph, tmp_path):
    urdf, motion = ARMS / 'panda' / 'panda.urdf', ARMS / 'panda' / 'panda-motion.yaml'
    mjcf = ROOT / 'config' / 'robots' / 'panda' / 'panda.xml'
    spec = robot_spec(urdf, motion, mjcf, 'computed_torque', 15.0, duration=0.4, tau=0.05, torque_limit='paper')
    recorded, scored = graph.record_and_score(spec, tmp_path / 'bag')
    in_process = run_episode(spec)
    np.testing.assert_allclose(recorded.scored('q'), in_process.scored('q'), rtol=0, atol=1e-9)
    np.testing.assert_allclose(recorded.scored('torque'), in_process.scored('torque'), rtol=0, atol=1e-9)
    for key in ('I1', 'I2', 'I'):
        assert recorded.indices()[key] == pytest.approx(in_process.indices()[key], rel=1e-9)
        assert scored[key] == pytest.approx(in_process.indices()[key], rel=1e-9)
    assert scored['spec']['mjcf'] == str(mjcf)


def test_a_robot_of_other_joint_names_through_the_graph_is_the_in_process_episode(graph, two_link, tmp_path):
    _, urdf, motion = two_link
    renamed = tmp_path / 'renamed.xml'
    renamed.write_text(TWO_LINK_MJCF.replace('"shoulder"', '"j1"').replace('"elbow"', '"j2"'))
    spec = robot_spec(urdf, motion, renamed, 'pd_gravity', 6.0, delay=0, mjcf_joints=('j1', 'j2'))
    recorded, scored = graph.record_and_score(spec, tmp_path / 'bag')
    in_process = run_episode(spec)
    np.testing.assert_allclose(recorded.scored('q'), in_process.scored('q'), rtol=0, atol=1e-9)
    assert scored['I'] == pytest.approx(in_process.indices()['I'], rel=1e-9)


def test_a_plant_node_refuses_a_robot_that_is_not_its_arm_and_options_of_its_own_plant(two_link, tmp_path,
                                                                                        ros_context):
    import subprocess
    import sys

    from rclpy.parameter import Parameter

    from ddarm_sim.node import PlantNode

    mjcf, urdf, motion = two_link
    wrong = mjcf_with(tmp_path, '<joint name="elbow" type="hinge"', '<joint name="knee" type="hinge"')
    done = subprocess.run([sys.executable, '-m', 'ddarm_sim.node', '--ros-args', '-p', f'urdf:={urdf}',
                           '-p', f'motion:={motion}', '-p', f'mjcf:={wrong}'], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2, done.stdout + done.stderr
    assert 'plant: refused to start' in done.stdout and "has no joint ['elbow']" in done.stdout
    node = PlantNode(context=ros_context, parameter_overrides=[
        Parameter('urdf', value=str(urdf)), Parameter('motion', value=str(motion)), Parameter('mjcf', value=str(mjcf)),
        Parameter('autostart', value=False)])
    try:
        refused = node.set_parameters([Parameter('mass_scale', value=[1.0, 2.0])])[0]
        assert not refused.successful and "change ddarm's own plant" in refused.reason
        refused = node.set_parameters([Parameter('period', value=0.0105)])[0]
        assert not refused.successful and 'not a whole number of its timestep' in refused.reason
        assert node.set_parameters([Parameter('period', value=0.02)])[0].successful
        node.start_episode()  # the next episode's settings
        assert node.plant.robot.steps_per_period == 20 and node.plant.robot.period == 0.02
    finally:
        node.destroy_node()


def test_without_mujoco_installed_mjcf_says_how_to_install_it(two_link):
    import subprocess
    import sys

    mjcf, urdf, motion = two_link
    script = ('import sys; sys.modules["mujoco"] = None; from ddarm.cli.main import main; '
              f'sys.exit(main(["episode", "--controller", "pd_gravity", "--urdf", {str(urdf)!r}, "--motion", '
              f'{str(motion)!r}, "--mjcf", {str(mjcf)!r}, "--omega", "5"]))')
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ''
    assert "MuJoCo is not installed: pip install 'ddarm[mujoco]'" in done.stderr and 'Traceback' not in done.stderr


def test_a_stop_that_lands_in_mujocos_import_is_the_stop_not_a_missing_mujoco(monkeypatch):
    """mujoco's C initialisation turns an exception raised in it by a signal handler into ImportError
    ('initialization failed'): with a stop asked for, that ImportError is the stop (a robot node stopped as it
    configured said MuJoCo was not installed); without one, it is the missing MuJoCo it seems."""
    import signal
    import sys

    from ddarm import interrupts
    from ddarm.physics.mujoco_plant import RobotError, import_mujoco

    monkeypatch.setitem(sys.modules, 'mujoco', None)  # `import mujoco` raises ImportError
    with pytest.raises(RobotError, match='MuJoCo is not installed'):
        import_mujoco()
    monkeypatch.setattr(interrupts, '_requested', signal.SIGINT)
    with pytest.raises(interrupts.Interrupted):
        import_mujoco()


def test_mujoco_is_imported_only_when_a_robot_is_given(two_link):
    import subprocess
    import sys

    _, urdf, motion = two_link
    script = ('import sys; from ddarm.cli.main import main; '
              f'code = main(["episode", "--controller", "pd_gravity", "--urdf", {str(urdf)!r}, "--motion", '
              f'{str(motion)!r}, "--omega", "5", "--json"]); print("mujoco" in sys.modules, file=sys.stderr); '
              'sys.exit(code)')
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stderr.strip().splitlines()[-1] == 'False'
