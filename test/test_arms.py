"""Any arm (spec §16): the example arms and small hostile URDFs against an independent implementation.

Everything ddarm computes for a general arm is checked here against code written from the specification
alone: Pinocchio's own algorithms on a reduced model built here with pin.buildReducedModel (the locked
joints' positions written out by hand, mimic joints included), continuous joints given to Pinocchio as
(cos θ, sin θ), and a plain closed loop (spec §4, §5, §7, §8, §11, §12) in NumPy. From ddarm the
independent parts take nothing but the URDF and motion files.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
import xml.etree.ElementTree as ElementTree
from collections import deque
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from ddarm.cli.main import main
from ddarm.control.gains import largest_stable_omega
from ddarm.episodes.engine import run_episode, simulate_batch
from ddarm.episodes.spec import (EpisodeError, EpisodeSpec, check_episode, gains_from_omega, model_arm, plan_episode, plant_arm,
                                 plant_chain)
from ddarm.physics.arm import Arm
from ddarm.physics.dynamics import chain_from_model, inverse_dynamics_at
from dynamics_checks import compiled_mass_matrix_and_acceleration

ROOT = Path(__file__).resolve().parents[1]
ARMS_DIR = ROOT / 'config' / 'arms'
G = 9.81
TOLERANCE = 1e-9
# Every movable joint an example motion does not control, at the position the arm is to hold it, written out
# here from the motion files' comments and the URDFs' <mimic> (panda_finger_joint2 follows panda_finger_joint1).
HELD = {
    'ur5': {},
    'panda': {'panda_finger_joint1': 0.02, 'panda_finger_joint2': 0.02},
    'scara': {},
    'z1': {'jointGripper': 0.0},
}
ARMS = [name for name in HELD if (ARMS_DIR / name / f'{name}.urdf').is_file()]


def urdf_of(arm: str) -> Path:
    return ARMS_DIR / arm / f'{arm}.urdf'


def motion_of(arm: str) -> Path:
    return ARMS_DIR / arm / f'{arm}-motion.yaml'


# ---------------------------------------------------------------------------------------------------------------
# The independent implementation


def read_motion(path: Path) -> dict:
    """A bang-bang motion file, read as plain YAML."""
    document = yaml.safe_load(Path(path).read_text())
    return {'joint_names': list(document['joint_names']), 'start': np.array(document['start'], dtype=float),
            'goal': np.array(document['goal'], dtype=float), 'duration': float(document['duration']),
            'locked': dict(document.get('locked') or {})}


def write_motion(path: Path, joint_names, start, goal, duration, locked=None) -> Path:
    document = {'joint_names': list(joint_names), 'duration': float(duration), 'profile': 'bang_bang',
                'start': [float(x) for x in start], 'goal': [float(x) for x in goal]}
    if locked:
        document['locked'] = {name: float(value) for name, value in locked.items()}
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def urdf_efforts(urdf: Path, names) -> np.ndarray:
    """<limit effort> of the named joints, from the XML (<robot>'s own <joint> elements, as urdfdom reads them)."""
    joints = {joint.get('name'): joint for joint in ElementTree.parse(urdf).getroot().findall('joint')}
    return np.array([float(joints[name].find('limit').get('effort')) for name in names])


def reduced_model(urdf: Path, controlled, held: dict, mass_scale=None) -> pin.Model:
    """The URDF's model with every movable joint not in `controlled` locked at held[name] (default 0)."""
    full = pin.buildModelFromUrdf(str(urdf))
    reference = pin.neutral(full)
    locked_ids = []
    for joint_id in range(1, full.njoints):
        name = full.names[joint_id]
        if name in controlled:
            continue
        joint, value = full.joints[joint_id], held.get(name, 0.0)
        if joint.nq == 2:
            reference[joint.idx_q:joint.idx_q + 2] = (math.cos(value), math.sin(value))
        else:
            reference[joint.idx_q] = value
        locked_ids.append(joint_id)
    model = pin.buildReducedModel(full, locked_ids, reference) if locked_ids else full
    assert list(model.names)[1:] == list(controlled)
    if mass_scale is not None:
        for joint_id, factor in enumerate(mass_scale, start=1):
            inertia = model.inertias[joint_id]
            model.inertias[joint_id] = pin.Inertia(factor * inertia.mass, inertia.lever, factor * inertia.inertia)
    return model


def configuration(model: pin.Model, q) -> np.ndarray:
    """Pinocchio's configuration of the angles and lengths q: (cos θ, sin θ) for an unbounded joint."""
    parts = []
    for joint_id in range(1, model.njoints):
        value = float(q[model.joints[joint_id].idx_v])
        parts += [math.cos(value), math.sin(value)] if model.joints[joint_id].nq == 2 else [value]
    return np.array(parts)


class Dynamics:
    """M, V + G, G, inverse and forward dynamics of a Pinocchio model at angles/lengths q."""

    def __init__(self, model: pin.Model) -> None:
        self.model, self.data = model, model.createData()

    def mass(self, q):
        upper = pin.crba(self.model, self.data, configuration(self.model, q))
        return np.triu(upper) + np.triu(upper, 1).T

    def bias(self, q, v):
        return pin.nonLinearEffects(self.model, self.data, configuration(self.model, q), np.asarray(v)).copy()

    def gravity(self, q):
        return pin.computeGeneralizedGravity(self.model, self.data, configuration(self.model, q)).copy()

    def rnea(self, q, v, a):
        return pin.rnea(self.model, self.data, configuration(self.model, q), np.asarray(v), np.asarray(a)).copy()

    def aba(self, q, v, torque):
        return pin.aba(self.model, self.data, configuration(self.model, q), np.asarray(v), np.asarray(torque)).copy()

    def friction(self, v):
        """F(q̇): the URDF's <dynamics damping friction>, viscous and Coulomb, as Pinocchio's parser reads them."""
        return self.model.damping * v + self.model.friction * np.sign(v)


def bang_bang(q0, qf, duration, t):
    """Spec §4: q^d = q0 + (qf - q0) s(t/T); at T/2 and at T the deceleration applies; qf held after T."""
    u = t / duration
    span = qf - q0
    if u > 1.0 + 1e-9:
        return qf.copy(), np.zeros_like(qf), np.zeros_like(qf)
    u = min(max(u, 0.0), 1.0)
    if u < 0.5 - 1e-9:
        s, ds, dds = 2.0 * u * u, 4.0 * u, 4.0
    else:
        s, ds, dds = 1.0 - 2.0 * (1.0 - u) ** 2, 4.0 * (1.0 - u), -4.0
    return q0 + span * s, span * ds / duration, span * dds / duration**2


def independent_episode(*, urdf, controlled, held, start, goal, duration, controller, kp, kv, delay=1,
                        period=0.01, tau=0.0, torque_limit='none', mass_scale=None, model_urdf=None, substeps=8):
    """One episode from the specification alone (spec §4, §5, §7, §8, §11, §12)."""
    plant = Dynamics(reduced_model(urdf, controlled, held, mass_scale))
    model = Dynamics(reduced_model(model_urdf or urdf, controlled, held))
    n = len(controlled)
    kp, kv = np.asarray(kp, dtype=float), np.asarray(kv, dtype=float)
    k_max = int(round(duration / period))
    times = np.arange(k_max + 1) * period
    reference = [bang_bang(start, goal, duration, t) for t in times]
    nominal = np.array([model.rnea(*point) for point in reference])
    if isinstance(torque_limit, str) and torque_limit == 'none':
        limit = None
    elif isinstance(torque_limit, str) and torque_limit == 'urdf':
        limit = urdf_efforts(urdf, controlled)
    elif isinstance(torque_limit, str) and torque_limit == 'paper':
        limit = 2.0 * np.max(np.abs(nominal), axis=0)
    else:
        limit = np.asarray(torque_limit, dtype=float)
    q, v = start.astype(float).copy(), -bang_bang(start, goal, duration, tau)[1]
    history = deque(maxlen=delay + 1)
    qs, torques, commands = [], [], []
    diverged_at = None
    for k in range(k_max + 1):
        history.append((q, v, k))
        qm, vm, measured = history[0]
        q_ref_m, v_ref_m, _ = reference[measured]
        error, rate = q_ref_m - qm, v_ref_m - vm
        if controller == 'pd_gravity':
            command = kp * error + kv * rate + model.gravity(reference[k][0])
        else:
            command = (model.mass(qm) @ (reference[k][2] + kv * rate + kp * error) + model.bias(qm, vm)
                       + model.friction(vm))
        if not np.all(np.isfinite(command)):
            diverged_at = k
            break
        torque = command if limit is None else np.clip(command, -limit, limit)
        qs.append(q)
        torques.append(torque)
        commands.append(command)
        if k == k_max:
            break
        h = period / substeps
        qn, vn = q, v
        with np.errstate(all='ignore'):
            for _ in range(substeps):
                a1 = plant.aba(qn, vn, torque - plant.friction(vn))
                v2 = vn + 0.5 * h * a1
                a2 = plant.aba(qn + 0.5 * h * vn, v2, torque - plant.friction(v2))
                v3 = vn + 0.5 * h * a2
                a3 = plant.aba(qn + 0.5 * h * v2, v3, torque - plant.friction(v3))
                v4 = vn + h * a3
                a4 = plant.aba(qn + h * v3, v4, torque - plant.friction(v4))
                qn = qn + h / 6.0 * (vn + 2.0 * v2 + 2.0 * v3 + v4)
                vn = vn + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        if not (np.all(np.isfinite(qn)) and np.all(np.isfinite(vn)) and np.max(np.abs(qn)) <= 100.0
                and np.max(np.abs(vn)) <= 1000.0):
            diverged_at = k + 1
            break
        q, v = qn, vn
    qs, torques = np.array(qs).reshape(-1, n), np.array(torques).reshape(-1, n)
    q_ref = np.array([point[0] for point in reference])
    scored = len(qs)
    first = np.sum(np.abs(q_ref[:scored] - qs)) * (360.0 / (2.0 * np.pi)) / k_max
    second = np.sum(np.abs(torques - nominal[:scored]) * (10.0 / np.max(np.abs(nominal), axis=0))) / k_max
    return {'I1': first, 'I2': second, 'I': first + second, 'diverged_at': diverged_at, 'q': qs, 'q_ref': q_ref,
            'torque': torques, 'command': np.array(commands).reshape(-1, n), 'nominal': nominal, 'limit': limit}


def independent_of(spec: EpisodeSpec, held: dict, member: int | None = None, **changes) -> dict:
    """The independent episode of `spec` (its motion file read as YAML; its URDF joints held at `held`)."""
    motion = read_motion(Path(spec.motion))
    arguments = dict(urdf=Path(spec.urdf), controlled=motion['joint_names'], held=held, start=motion['start'],
                     goal=motion['goal'], duration=spec.duration, controller=spec.controller, kp=spec.kp,
                     kv=spec.kv, delay=spec.delay, period=spec.period, tau=spec.tau, torque_limit=spec.torque_limit,
                     mass_scale=spec.mass_scale, model_urdf=Path(spec.model_urdf) if spec.model_urdf else None,
                     substeps=spec.substeps)
    arguments.update(changes)
    return independent_episode(**arguments)


def assert_same_episode(batch, member: int, expected: dict) -> None:
    for key in ('I1', 'I2', 'I'):
        assert batch.indices(member)[key] == pytest.approx(expected[key], rel=TOLERANCE, abs=1e-12), key
    assert batch.diverged_at[member] == (-1 if expected['diverged_at'] is None else expected['diverged_at'])
    assert batch.samples_scored[member] == len(expected['q'])


def frictionless_urdf(arm: str, folder: Path) -> Path:
    """The example arm's URDF without its joints' <dynamics damping friction>: the rigid-body arm, whose sampled
    loop the stability tests check (the z1's wrist has friction that stops it within a period)."""
    path = folder / f'{arm}-frictionless.urdf'
    path.write_text(re.sub(r'<dynamics\b[^>]*/>', '', urdf_of(arm).read_text()))
    return path


def example_spec(arm: str, controller: str, **options) -> EpisodeSpec:
    """The example arm and motion, placeholder gains (see with_omega)."""
    return EpisodeSpec(controller=controller, kp=(1.0,), kv=(1.0,), **{'urdf': str(urdf_of(arm)), **options},
                       motion=str(motion_of(arm)))


def with_omega(spec: EpisodeSpec, omega: float) -> EpisodeSpec:
    kp, kv = gains_from_omega(spec, omega)
    return dataclasses.replace(spec, kp=tuple(kp), kv=tuple(kv))


def random_positions(arm: Arm, rng, count: int) -> np.ndarray:
    """Positions inside each joint's limits (within ±2π); continuous joints anywhere in [-3π, 3π]."""
    lower = np.where(np.isfinite(arm.lower), np.maximum(arm.lower, -2 * np.pi), -3 * np.pi)
    upper = np.where(np.isfinite(arm.upper), np.minimum(arm.upper, 2 * np.pi), 3 * np.pi)
    return rng.uniform(lower, upper, (count, arm.dof))


def assert_dynamics_match(arm: Arm, chain, reference: Dynamics, q, v, a) -> None:
    """Arm's Pinocchio calls and the compiled chain against the independent model, at states (m, n)."""
    torque = inverse_dynamics_at(chain, q, v, a)
    gravity = inverse_dynamics_at(chain, q, np.zeros_like(v), np.zeros_like(a))
    mass, acceleration = compiled_mass_matrix_and_acceleration(chain, q, v, torque)
    for m in range(len(q)):
        expected_mass = reference.mass(q[m])
        scale_mass = np.max(np.abs(expected_mass))
        expected_torque = reference.rnea(q[m], v[m], a[m])
        scale_torque = np.max(np.abs(expected_torque))
        expected_gravity = reference.gravity(q[m])
        scale_gravity = max(np.max(np.abs(expected_gravity)), 1.0)
        expected_acceleration = reference.aba(q[m], v[m], expected_torque)
        np.testing.assert_allclose(arm.mass_matrix(q[m]), expected_mass, rtol=TOLERANCE, atol=TOLERANCE * scale_mass)
        np.testing.assert_allclose(mass[m], expected_mass, rtol=TOLERANCE, atol=TOLERANCE * scale_mass)
        np.testing.assert_allclose(arm.inverse_dynamics(q[m], v[m], a[m]), expected_torque, rtol=TOLERANCE,
                                   atol=TOLERANCE * scale_torque)
        np.testing.assert_allclose(torque[m], expected_torque, rtol=TOLERANCE, atol=TOLERANCE * scale_torque)
        np.testing.assert_allclose(arm.bias(q[m], v[m]), reference.bias(q[m], v[m]), rtol=TOLERANCE,
                                   atol=TOLERANCE * scale_torque)
        np.testing.assert_allclose(arm.gravity(q[m]), expected_gravity, rtol=TOLERANCE, atol=TOLERANCE * scale_gravity)
        np.testing.assert_allclose(gravity[m], expected_gravity, rtol=TOLERANCE, atol=TOLERANCE * scale_gravity)
        np.testing.assert_allclose(arm.forward_dynamics(q[m], v[m], expected_torque), expected_acceleration,
                                   rtol=1e-8, atol=1e-8 * max(1.0, np.max(np.abs(expected_acceleration))))
        np.testing.assert_allclose(acceleration[m], expected_acceleration, rtol=1e-8,
                                   atol=1e-8 * max(1.0, np.max(np.abs(expected_acceleration))))
        np.testing.assert_allclose(expected_acceleration, a[m], rtol=1e-7, atol=1e-7 * max(1.0, np.max(np.abs(a[m]))))


# ---------------------------------------------------------------------------------------------------------------
# Small URDFs


def inertial(mass, xyz='0 0 0', rpy='0 0 0', ixx=0.01, iyy=0.01, izz=0.01, ixy=0.0, ixz=0.0, iyz=0.0) -> str:
    return (f'<inertial><origin xyz="{xyz}" rpy="{rpy}"/><mass value="{mass}"/>'
            f'<inertia ixx="{ixx}" ixy="{ixy}" ixz="{ixz}" iyy="{iyy}" iyz="{iyz}" izz="{izz}"/></inertial>')


def joint(name, kind, parent, child, xyz='0 0 0', rpy='0 0 0', axis='0 0 1', lower=-3.0, upper=3.0, effort=50.0,
          velocity=5.0, mimic='') -> str:
    limit = '' if kind == 'fixed' else (
        f'<limit effort="{effort}" velocity="{velocity}"/>' if kind == 'continuous'
        else f'<limit lower="{lower}" upper="{upper}" effort="{effort}" velocity="{velocity}"/>')
    axis_element = '' if kind == 'fixed' else f'<axis xyz="{axis}"/>'
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz}" rpy="{rpy}"/>{axis_element}{limit}{mimic}</joint>')


def robot(*parts, links: dict) -> str:
    body = ''.join(f'<link name="{name}">{content}</link>' for name, content in links.items())
    return f'<?xml version="1.0"?><robot name="test">{body}{"".join(parts)}</robot>'


def tree_urdf(yaw_axis='0 0 1', wrist_axis='1 0 0') -> str:
    """A branching tree: a continuous yaw carrying two arms; unaligned revolute and prismatic axes, turned frames.

    The file lists the right arm first; Pinocchio numbers the left one first (its children in name order).
    """
    links = {
        'base': '',
        'torso': inertial(3.0, '0.02 0.01 0.1', '0.3 0.1 -0.2', 0.05, 0.06, 0.04, 0.002, -0.001, 0.003),
        'right_arm': inertial(1.2, '0.15 0 0', '0 0.2 0', 0.002, 0.01, 0.01),
        'right_hand': inertial(0.5, '0.03 0 0.01', ixx=0.0005, iyy=0.0005, izz=0.0005),
        'left_arm': inertial(1.1, '0.15 0 0', ixx=0.002, iyy=0.01, izz=0.01),
        'left_hand': inertial(0.4, '0.02 0.03 0', ixx=0.0004, iyy=0.0003, izz=0.0005),
    }
    return robot(
        joint('yaw', 'continuous', 'base', 'torso', '0 0 0.5', '0.1 -0.2 0.3', yaw_axis),
        joint('right_shoulder', 'revolute', 'torso', 'right_arm', '0 -0.2 0.2', '0.5 0 0', '0 0 -1', -2, 2),
        joint('right_slide', 'prismatic', 'right_arm', 'right_hand', '0.3 0 0', '0 0 0.4', '1 1 0', -0.1, 0.1),
        joint('left_shoulder', 'revolute', 'torso', 'left_arm', '0 0.2 0.2', '-0.5 0 0', '0 -1 0', -2, 2),
        joint('left_wrist', 'continuous', 'left_arm', 'left_hand', '0.3 0 0', '0 0 0', wrist_axis, effort=5,
              velocity=8),
        links=links)


TREE_ORDER = ['yaw', 'left_shoulder', 'left_wrist', 'right_shoulder', 'right_slide']


def mimic_urdf(follower_lower=-1.0, follower_upper=1.0) -> str:
    """Two controlled revolute joints, a locked 'drive' and a 'follower' mimicking it (multiplier -0.5, offset 0.1)."""
    links = {'base': '', 'l1': inertial(2.0, '0.2 0 0', ixx=0.002, iyy=0.03, izz=0.03),
             'l2': inertial(1.0, '0.15 0.02 0', ixx=0.001, iyy=0.02, izz=0.02),
             'jaw_a': inertial(0.3, '0.05 0 0.02', ixx=0.0003, iyy=0.0004, izz=0.0002),
             'jaw_b': inertial(0.2, '0.04 0 -0.02', ixx=0.0002, iyy=0.0003, izz=0.0002)}
    return robot(
        joint('j1', 'revolute', 'base', 'l1', '0 0 0.2', axis='0 1 0'),
        joint('j2', 'revolute', 'l1', 'l2', '0.4 0 0', axis='0 1 0'),
        joint('drive', 'revolute', 'l2', 'jaw_a', '0.3 0 0', axis='0 0 1', lower=-1, upper=1),
        joint('follower', 'revolute', 'l2', 'jaw_b', '0.3 0 0', axis='1 0 0', lower=follower_lower,
              upper=follower_upper, mimic='<mimic joint="drive" multiplier="-0.5" offset="0.1"/>'),
        links=links)


def vertical_slider_urdf() -> str:
    """A prismatic joint lifting along an axis tilted 30° from the vertical, then a revolute joint."""
    links = {'base': '', 'carriage': inertial(2.0, '0 0 0.05'), 'arm': inertial(1.0, '0.2 0 0', ixx=0.001)}
    return robot(
        joint('lift', 'prismatic', 'base', 'carriage', '0 0 0.1', axis=f'{math.sin(math.pi / 6)} 0 '
              f'{math.cos(math.pi / 6)}', lower=-0.5, upper=0.5, effort=200),
        joint('swing', 'revolute', 'carriage', 'arm', '0 0 0.1', axis='0 1 0'),
        links=links)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------------------------------------------
# 1. Dynamics against Pinocchio's


@pytest.mark.parametrize('arm', ARMS)
def test_the_example_arms_dynamics_are_pinocchios_on_an_independently_reduced_model(arm):
    motion = read_motion(motion_of(arm))
    spec = example_spec(arm, 'computed_torque')
    ours = plant_arm(spec)
    assert ours.joint_names == motion['joint_names']
    reference = Dynamics(reduced_model(urdf_of(arm), motion['joint_names'], HELD[arm]))
    assert dict(ours.locked) == pytest.approx(HELD[arm])
    rng = np.random.default_rng(len(arm))
    q = random_positions(ours, rng, 25)
    v, a = rng.uniform(-3, 3, q.shape), rng.uniform(-10, 10, q.shape)
    assert_dynamics_match(ours, plant_chain(spec), reference, q, v, a)


def test_the_panda_is_reduced_with_both_fingers_where_the_motion_holds_them():
    """The mimic finger follows panda_finger_joint1 = 0.02: the reduced model differs from fingers at 0."""
    motion = read_motion(motion_of('panda'))
    ours = plant_arm(example_spec('panda', 'computed_torque'))
    held = Dynamics(reduced_model(urdf_of('panda'), motion['joint_names'], HELD['panda']))
    closed = Dynamics(reduced_model(urdf_of('panda'), motion['joint_names'], {}))
    ignored = Dynamics(reduced_model(urdf_of('panda'), motion['joint_names'], {'panda_finger_joint1': 0.02}))
    q = motion['start']
    np.testing.assert_allclose(ours.gravity(q), held.gravity(q), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ours.mass_matrix(q), held.mass(q), rtol=1e-12, atol=1e-12)
    # The test can tell them apart: fingers closed, or the mimic finger left at 0.
    assert np.max(np.abs(held.mass(q) - closed.mass(q))) > 1e-6
    assert np.max(np.abs(held.gravity(q) - ignored.gravity(q))) > 1e-4


def test_the_scara_quill_carries_the_weight_below_it_and_the_horizontal_joints_none():
    ours = plant_arm(example_spec('scara', 'computed_torque'))
    chain = plant_chain(example_spec('scara', 'computed_torque'))
    weight = (0.8 + 0.5 + 0.3) * G  # quill, flange and tool (scara.urdf)
    rng = np.random.default_rng(3)
    for q in random_positions(ours, rng, 10):
        expected = np.array([0.0, 0.0, weight, 0.0])
        np.testing.assert_allclose(ours.gravity(q), expected, atol=1e-9)
        np.testing.assert_allclose(inverse_dynamics_at(chain, q, np.zeros(4), np.zeros(4))[0], expected, atol=1e-9)
    assert list(ours.prismatic) == [False, False, True, False]
    assert list(ours.unbounded) == [True, False, False, True]


def test_a_branching_tree_with_unaligned_axes_is_pinocchios(tmp_path):
    urdf = write(tmp_path / 'tree.urdf', tree_urdf())
    ours = Arm.from_urdf(urdf)
    assert ours.joint_names == TREE_ORDER
    chain = chain_from_model(ours.model)
    assert list(chain.parent) == [-1, 0, 1, 0, 3]
    reference = Dynamics(reduced_model(urdf, TREE_ORDER, {}))
    rng = np.random.default_rng(4)
    q = random_positions(ours, rng, 25)
    assert_dynamics_match(ours, chain, reference, q, rng.uniform(-3, 3, q.shape), rng.uniform(-10, 10, q.shape))


@pytest.mark.parametrize('yaw_axis, wrist_axis', [('0.3 -0.4 0.866', '1 0 0'), ('0 0 1', '-1 0 0'),
                                                  ('0 0 -1', '1 0 0')])
def test_a_continuous_joint_about_any_axis_is_pinocchios(tmp_path, yaw_axis, wrist_axis):
    """A continuous joint whose axis is not +x, +y or +z (e.g. the common axis="0 0 -1") is a
    JointModelRevoluteUnboundedUnaligned in Pinocchio. Spec §16: revolute, continuous and prismatic joints."""
    urdf = write(tmp_path / 'tree.urdf', tree_urdf(yaw_axis, wrist_axis))
    ours = Arm.from_urdf(urdf)
    chain = chain_from_model(ours.model)
    reference = Dynamics(reduced_model(urdf, TREE_ORDER, {}))
    rng = np.random.default_rng(5)
    q = random_positions(ours, rng, 10)
    assert_dynamics_match(ours, chain, reference, q, rng.uniform(-3, 3, q.shape), rng.uniform(-10, 10, q.shape))


def test_an_episode_of_an_arm_with_a_continuous_joint_about_minus_z_runs(tmp_path, capfd):
    """The same through the CLI: an episode, not a traceback."""
    urdf = write(tmp_path / 'tree.urdf', tree_urdf('0 0 -1', '1 0 0'))
    path = write_motion(tmp_path / 'tree.yaml', TREE_ORDER, [0.0, 0.1, 0.0, -0.2, 0.0], [0.5, 0.4, 1.0, 0.2, 0.05],
                        0.3)
    code = main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf), '--motion',
                 str(path), '--json'])
    out, err = capfd.readouterr()
    assert code == 0 and not json.loads(out)['diverged'], err


def test_a_locked_middle_joint_is_folded_into_its_parent(tmp_path):
    """UR5 with the elbow locked at 0.8 rad, the shoulder_pan of a tree locked at 0.7: the chain's parents skip them."""
    names = ['shoulder_pan_joint', 'shoulder_lift_joint', 'wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint']
    ours = Arm.from_urdf(urdf_of('ur5'), None, names, {'elbow_joint': 0.8})
    assert dict(ours.locked) == {'elbow_joint': 0.8}
    reference = Dynamics(reduced_model(urdf_of('ur5'), names, {'elbow_joint': 0.8}))
    rng = np.random.default_rng(6)
    q = random_positions(ours, rng, 15)
    assert_dynamics_match(ours, chain_from_model(ours.model), reference, q, rng.uniform(-3, 3, q.shape),
                          rng.uniform(-10, 10, q.shape))
    urdf = write(tmp_path / 'tree.urdf', tree_urdf())
    names = ['left_shoulder', 'left_wrist', 'right_shoulder', 'right_slide']
    ours = Arm.from_urdf(urdf, None, names, {'yaw': 0.7})
    chain = chain_from_model(ours.model)
    assert list(chain.parent) == [-1, 0, -1, 2]
    reference = Dynamics(reduced_model(urdf, names, {'yaw': 0.7}))
    q = random_positions(ours, rng, 15)
    assert_dynamics_match(ours, chain, reference, q, rng.uniform(-3, 3, q.shape), rng.uniform(-10, 10, q.shape))


def test_a_locked_mimic_joint_follows_its_joint_by_multiplier_and_offset(tmp_path):
    urdf = write(tmp_path / 'mimic.urdf', mimic_urdf())
    ours = Arm.from_urdf(urdf, None, ['j1', 'j2'], {'drive': 0.4})
    assert dict(ours.locked) == pytest.approx({'drive': 0.4, 'follower': -0.5 * 0.4 + 0.1})
    reference = Dynamics(reduced_model(urdf, ['j1', 'j2'], {'drive': 0.4, 'follower': -0.1}))
    rng = np.random.default_rng(7)
    q = random_positions(ours, rng, 10)
    assert_dynamics_match(ours, chain_from_model(ours.model), reference, q, rng.uniform(-3, 3, q.shape),
                          rng.uniform(-10, 10, q.shape))
    # The follower at 0 (ignoring the mimic) gives another arm: the test tells them apart.
    ignored = Dynamics(reduced_model(urdf, ['j1', 'j2'], {'drive': 0.4}))
    assert np.max(np.abs(ignored.gravity(q[0]) - ours.gravity(q[0]))) > 1e-6


def test_a_tilted_prismatic_joint_carries_its_share_of_gravity(tmp_path):
    urdf = write(tmp_path / 'slider.urdf', vertical_slider_urdf())
    ours = Arm.from_urdf(urdf)
    chain = chain_from_model(ours.model)
    for q in ([0.0, 0.0], [0.3, 1.0], [-0.2, -2.0]):
        expected_lift = 3.0 * G * math.cos(math.pi / 6)  # both links ride the carriage, axis 30° from vertical
        assert ours.gravity(np.array(q))[0] == pytest.approx(expected_lift, rel=1e-12)
        assert inverse_dynamics_at(chain, np.array(q), np.zeros(2), np.zeros(2))[0, 0] == pytest.approx(
            expected_lift, rel=1e-12)


def test_mass_scale_scales_each_reduced_link_locked_links_folded_in():
    names = read_motion(motion_of('panda'))['joint_names']
    scale = np.linspace(0.7, 1.4, 7)
    spec = dataclasses.replace(example_spec('panda', 'computed_torque'), mass_scale=tuple(scale))
    reference = Dynamics(reduced_model(urdf_of('panda'), names, HELD['panda'], scale))
    ours = plant_arm(spec)
    rng = np.random.default_rng(8)
    for q in random_positions(ours, rng, 5):
        np.testing.assert_allclose(ours.mass_matrix(q), reference.mass(q), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ours.gravity(q), reference.gravity(q), rtol=1e-12, atol=1e-12)
    # The controller's model stays unscaled.
    unscaled = Dynamics(reduced_model(urdf_of('panda'), names, HELD['panda']))
    np.testing.assert_allclose(model_arm(spec).gravity(np.zeros(7)), unscaled.gravity(np.zeros(7)),
                               rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------------
# 2. In-process = batch = an independent loop


def member_gains(spec: EpisodeSpec):
    """The spec's gains and two perturbations of them, one row each."""
    kp, kv = np.array(spec.kp), np.array(spec.kv)
    n = len(kp)
    tilt = np.linspace(0.7, 1.3, n)
    return np.array([kp, kp * tilt, kp * tilt[::-1]]), np.array([kv, kv * tilt[::-1], kv * tilt])


def weakened(arm: str, tmp_path: Path, duration: float, factor: float) -> Path:
    """A copy of the arm's URDF whose controlled joints' efforts are `factor` x their largest nominal torque."""
    motion = read_motion(motion_of(arm))
    model = Dynamics(reduced_model(urdf_of(arm), motion['joint_names'], HELD[arm]))
    times = np.arange(int(round(duration / 0.01)) + 1) * 0.01
    nominal = np.array([model.rnea(*bang_bang(motion['start'], motion['goal'], duration, t)) for t in times])
    text = urdf_of(arm).read_text()
    for name, largest in zip(motion['joint_names'], np.max(np.abs(nominal), axis=0)):
        pattern = f'(<joint name="{name}"[^>]*>(?:(?!</joint>).)*?<limit[^>]*?effort=")[^"]*"'
        text, count = re.subn(pattern, f'\\g<1>{float(factor * largest)!r}"', text, count=1, flags=re.S)
        assert count == 1, name
    return write(tmp_path / f'{arm}-weak.urdf', text)


# ω of each law's gains here: computed torque at the paper's ω; PD + gravity well inside each arm's coupled
# sampled boundary at delay 0 (see test_pd_gravity_is_stable_where_the_coupled_sampled_model_says).
OMEGA = {'computed_torque': 15.0, 'pd_gravity': 1.0}
DELAY = {'computed_torque': 1, 'pd_gravity': 0}


@pytest.mark.parametrize('arm', ARMS)
@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
@pytest.mark.parametrize('variant', ['plain', 'urdf_limits', 'mass_scale'])
def test_every_batch_member_is_the_in_process_and_the_independent_episode(tmp_path, arm, controller, variant):
    options = dict(duration=0.4, tau=0.05, delay=DELAY[controller])
    n = len(read_motion(motion_of(arm))['joint_names'])
    if variant == 'urdf_limits':
        options['torque_limit'] = 'urdf'
    if variant == 'mass_scale':
        options['mass_scale'] = tuple(np.linspace(0.8, 1.25, n))
    spec = with_omega(example_spec(arm, controller, **options), OMEGA[controller])
    if variant == 'urdf_limits':  # efforts below the largest nominal torques: the actuators saturate
        factor = 0.9 if controller == 'computed_torque' else 0.3  # PD at ω = 1 asks for less than P^nom
        spec = dataclasses.replace(spec, urdf=str(weakened(arm, tmp_path, spec.duration, factor)))
    kp, kv = member_gains(spec)
    batch = simulate_batch(spec, kp, kv, threads=2)
    for member in range(len(kp)):
        member_spec = dataclasses.replace(spec, kp=tuple(kp[member]), kv=tuple(kv[member]))
        expected = independent_of(member_spec, HELD[arm])
        assert_same_episode(batch, member, expected)
        alone = run_episode(member_spec)
        assert alone.indices() == pytest.approx(batch.indices(member), rel=1e-12, abs=1e-15)
        np.testing.assert_allclose(alone.scored('q'), expected['q'], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(alone.scored('torque'), expected['torque'], rtol=1e-9,
                                   atol=1e-9 * np.max(np.abs(expected['torque'])))
    np.testing.assert_allclose(batch.plan.nominal, expected['nominal'], rtol=1e-12, atol=1e-12)
    if variant == 'urdf_limits':
        limit = urdf_efforts(Path(spec.urdf), batch.joint_names)
        np.testing.assert_array_equal(batch.plan.torque_limit, limit)
        assert any(run_episode(dataclasses.replace(spec, kp=tuple(kp[m]), kv=tuple(kv[m]))).summary()
                   ['saturated_joints'] for m in range(len(kp))), 'no member reached its effort limit'


@pytest.mark.parametrize('arm', ARMS)
def test_per_member_mass_scale_and_limits_are_each_members_own_episode(arm):
    spec = with_omega(example_spec(arm, 'computed_torque', duration=0.3, tau=0.05), 15.0)
    n = len(spec.kp)
    kp, kv = member_gains(spec)
    scales = np.array([np.ones(n), np.linspace(0.8, 1.2, n), np.linspace(1.3, 0.9, n)])
    efforts = urdf_efforts(urdf_of(arm), read_motion(motion_of(arm))['joint_names'])
    limits = np.array([efforts, efforts * 0.05, efforts * 0.5])
    batch = simulate_batch(spec, kp, kv, mass_scale=scales, torque_limit=limits)
    for member in range(3):
        expected = independent_of(dataclasses.replace(spec, kp=tuple(kp[member]), kv=tuple(kv[member])),
                                  HELD[arm], mass_scale=scales[member], torque_limit=limits[member])
        assert_same_episode(batch, member, expected)


def heavier_ur5(tmp_path: Path, link='upper_arm_link', mass='8.393', new='11.0') -> Path:
    """A copy of ur5.urdf with one link's mass changed (its inertia tensor kept)."""
    text = urdf_of('ur5').read_text()
    pattern = f'(<link name="{link}">.*?<mass value=")' + re.escape(mass) + '"'
    changed, count = re.subn(pattern, f'\\g<1>{new}"', text, count=1, flags=re.S)
    assert count == 1 and changed != text
    return write(tmp_path / 'ur5-heavier.urdf', changed)


@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
def test_a_model_urdf_is_the_controllers_model_and_the_plant_integrates_the_true_arm(tmp_path, controller):
    model_urdf = heavier_ur5(tmp_path)
    spec = example_spec('ur5', controller, duration=0.4, tau=0.05, delay=DELAY[controller],
                        model_urdf=str(model_urdf))
    spec = with_omega(spec, OMEGA[controller])
    names = read_motion(motion_of('ur5'))['joint_names']
    heavy = Dynamics(reduced_model(model_urdf, names, {}))
    true = Dynamics(reduced_model(urdf_of('ur5'), names, {}))
    motion = read_motion(motion_of('ur5'))
    # The ω rule's m_ii, P^nom and Ĝ are the model's.
    if controller == 'pd_gravity':
        np.testing.assert_allclose(spec.kp, np.diag(heavy.mass(motion['goal'])) * OMEGA[controller] ** 2,
                                   rtol=1e-12)
    plan = plan_episode(spec)
    np.testing.assert_allclose(plan.nominal[7], heavy.rnea(*bang_bang(motion['start'], motion['goal'], 0.4, 0.07)),
                               rtol=1e-12)
    assert np.max(np.abs(plan.nominal[7] - true.rnea(*bang_bang(motion['start'], motion['goal'], 0.4, 0.07)))) > 0.1
    kp, kv = member_gains(spec)
    batch = simulate_batch(spec, kp, kv)
    for member in range(3):
        member_spec = dataclasses.replace(spec, kp=tuple(kp[member]), kv=tuple(kv[member]))
        expected = independent_of(member_spec, {})
        assert_same_episode(batch, member, expected)
        # And it is not the episode of the model run as its own plant.
        same = independent_of(member_spec, {}, urdf=model_urdf)
        assert abs(same['I1'] - expected['I1']) > 1e-6 * expected['I1']
    # Through the CLI, with --model-urdf and --urdf-limits.
    assert main(['episode', '--controller', controller, '--omega', str(OMEGA[controller]), '--delay',
                 str(DELAY[controller]), '--urdf', str(urdf_of('ur5')), '--model-urdf', str(model_urdf), '--motion',
                 str(motion_of('ur5')), '--duration', '0.4', '--tau', '0.05', '--urdf-limits', '--json']) == 0


def test_the_cli_episode_is_the_independent_episode_with_model_urdf_and_urdf_limits(tmp_path, capsys):
    model_urdf = heavier_ur5(tmp_path)
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf_of('ur5')),
                 '--model-urdf', str(model_urdf), '--motion', str(motion_of('ur5')), '--duration', '0.3', '--tau',
                 '0.1', '--urdf-limits', '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    spec = EpisodeSpec(**{**summary['spec'], 'kp': tuple(summary['spec']['kp']),
                          'kv': tuple(summary['spec']['kv'])})
    expected = independent_of(spec, {})
    for key in ('I1', 'I2', 'I'):
        assert summary[key] == pytest.approx(expected[key], rel=TOLERANCE)
    assert summary['torque_limit'] == list(urdf_efforts(urdf_of('ur5'), summary['joint_names']))


def test_computed_torque_with_a_mass_mismatch_settles_at_the_steady_state_error_of_section_6(tmp_path):
    """K_p e = M̂⁻¹(q_f) [G(q_f) - Ĝ(q_f)], the model heavier than the arm (spec §6)."""
    model_urdf = heavier_ur5(tmp_path, new='12.0')
    motion = read_motion(motion_of('ur5'))
    goal = motion['start'].copy()
    goal[0] += 0.01  # a slow, tiny move: the arm is at rest at q_f long before T
    path = write_motion(tmp_path / 'hold.yaml', motion['joint_names'], motion['start'], goal, 3.0)
    spec = EpisodeSpec(controller='computed_torque', kp=(100.0,) * 6, kv=(20.0,) * 6, urdf=str(urdf_of('ur5')),
                       model_urdf=str(model_urdf), motion=str(path))
    episode = run_episode(spec)
    heavy = Dynamics(reduced_model(model_urdf, motion['joint_names'], {}))
    true = Dynamics(reduced_model(urdf_of('ur5'), motion['joint_names'], {}))
    at_goal = np.linalg.solve(heavy.mass(goal), true.gravity(goal) - heavy.gravity(goal)) / 100.0
    assert np.max(np.abs(at_goal)) > 1e-3
    # The arm rests at q = q_f - e, where the law evaluates M̂, G and Ĝ: the fixed point of the same formula.
    error = at_goal
    for _ in range(50):
        rest = goal - error
        error = np.linalg.solve(heavy.mass(rest), true.gravity(rest) - heavy.gravity(rest)) / 100.0
    final = episode.scored('errors')[-1]
    np.testing.assert_allclose(final, error, rtol=1e-3, atol=1e-7)
    np.testing.assert_allclose(final, at_goal, rtol=0.1, atol=5e-4)


# ---------------------------------------------------------------------------------------------------------------
# 3. Stability


@pytest.mark.parametrize('arm', ARMS)
def test_computed_torque_tracks_inside_the_sampled_boundary_and_diverges_beyond_it(tmp_path, arm):
    boundary = largest_stable_omega(0.01, 1)
    assert 15.0 < boundary
    rigid = example_spec(arm, 'computed_torque', delay=1, urdf=str(frictionless_urdf(arm, tmp_path)))
    inside = run_episode(with_omega(rigid, 15.0))
    assert not inside.diverged[0]
    errors = np.abs(inside.scored('errors'))
    prismatic = np.array(inside.plan.prismatic)
    assert np.all(errors[:, ~prismatic] < np.radians(0.5)) and np.all(errors[:, prismatic] < 1e-3)
    beyond = run_episode(with_omega(rigid, 2.0 * boundary))
    growth = np.abs(beyond.scored('errors'))
    assert beyond.diverged[0] or np.max(growth) > 100 * np.max(errors)


def mode_radius(kp: float, kv: float, period: float, delay: int) -> float:
    """Spectral radius of one mode ë = -(kp e + kv ė)(t_{n-d}) held over a period (spec §13's construction)."""
    size = 2 * (delay + 1)
    matrix = np.zeros((size, size))
    matrix[:2, :2] = [[1.0, period], [0.0, 1.0]]
    matrix[:2, 2 * delay:2 * delay + 2] -= np.array([[period**2 / 2.0], [period]]) @ np.array([[kp, kv]])
    matrix[2:, :-2] = np.eye(size - 2)
    return float(np.max(np.abs(np.linalg.eigvals(matrix))))


def coupled_pd_boundary(mass: np.ndarray, period: float, delay: int) -> float:
    """The largest ω for which PD with k_p = m_ii ω², k_v = 2 m_ii ω is stable on the arm linearised at rest:
    M ë = -D(ω² e + 2ω ė), D = diag(M), i.e. modes ë = -λ(ω² e + 2ω ė) for each eigenvalue λ of M⁻¹D."""
    modes = np.linalg.eigvals(np.linalg.solve(mass, np.diag(np.diag(mass)))).real

    def stable(omega):
        return all(mode_radius(lam * omega**2, 2 * lam * omega, period, delay) < 1.0 for lam in modes)

    low, high = 0.0, 500.0
    for _ in range(60):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if stable(middle) else (low, middle)
    return low


@pytest.mark.parametrize('arm', ARMS)
@pytest.mark.parametrize('delay', [0, 1])
def test_pd_gravity_is_stable_where_the_coupled_sampled_model_says(tmp_path, arm, delay):
    """A short move into q_f (the arm stays near its linearisation point): stable at half the coupled boundary,
    growing at twice it. (The paper's per-joint model, which ignores M's coupling, puts the boundary at
    ω* = 1/Δ or 0.426/Δ; for these arms it is far lower, e.g. the Panda's ≈ 2.7 at d = 0.)"""
    motion = read_motion(motion_of(arm))
    start = motion['goal'] + np.minimum(0.05, np.abs(motion['start'] - motion['goal'])) * np.sign(
        motion['start'] - motion['goal'])
    path = write_motion(tmp_path / 'near.yaml', motion['joint_names'], start, motion['goal'], 1.0, motion['locked'])
    spec = EpisodeSpec(controller='pd_gravity', kp=(1.0,), kv=(1.0,), delay=delay,
                       urdf=str(frictionless_urdf(arm, tmp_path)), motion=str(path))
    mass = Dynamics(reduced_model(urdf_of(arm), motion['joint_names'], HELD[arm])).mass(motion['goal'])
    boundary = coupled_pd_boundary(mass, 0.01, delay)
    assert boundary < largest_stable_omega(0.01, delay)
    stable = run_episode(with_omega(spec, 0.5 * boundary))
    assert not stable.diverged[0]
    calm = np.max(np.abs(stable.scored('errors')))
    assert calm < 0.2
    unstable = run_episode(with_omega(spec, 2.0 * boundary))
    wild = np.max(np.abs(unstable.scored('errors')))
    assert unstable.diverged[0] or (wild > 5 * calm and wild > 0.5)


# ---------------------------------------------------------------------------------------------------------------
# 4. Refusals, each through the CLI


PANDA_START = [-0.6, -0.7, 0.0, -2.2, 0.0, 1.5, 0.2]
PANDA_GOAL = [0.3, -0.2, 0.1, -1.8, 0.1, 1.6, -0.6]
PANDA_JOINTS = [f'panda_joint{i}' for i in range(1, 8)]


def panda_motion(**changes) -> str:
    document = {'joint_names': PANDA_JOINTS, 'duration': 0.3, 'profile': 'bang_bang', 'start': PANDA_START,
                'goal': PANDA_GOAL, 'locked': {'panda_finger_joint1': 0.02}}
    document.update(changes)
    return yaml.safe_dump({key: value for key, value in document.items() if value is not None}, sort_keys=False)


def scara_with(old: str, new: str) -> str:
    text = urdf_of('scara').read_text()
    assert old in text
    return text.replace(old, new, 1)


def massless_scara() -> str:
    text = urdf_of('scara').read_text()
    for link in ('flange', 'tool'):
        text = re.sub(f'(<link name="{link}">).*?(</link>)', r'\1\2', text, flags=re.S)
    return text


SCARA_MOTION = urdf_of('scara').parent / 'scara-motion.yaml'
REFUSALS = [
    # (id, URDF text or None for the Panda's, motion text or None for the example's, extra options, named)
    ('unknown joint', None, panda_motion(joint_names=PANDA_JOINTS[:6] + ['panda_jointX']), [], ['panda_jointX']),
    ('a fixed joint listed', None, panda_motion(joint_names=PANDA_JOINTS + ['panda_hand_joint'],
                                                 start=PANDA_START + [0.0], goal=PANDA_GOAL + [0.0]), [],
     ['panda_hand_joint']),
    ('a joint named twice', None, panda_motion(joint_names=PANDA_JOINTS[:6] + ['panda_joint6']), [],
     ['panda_joint6']),
    ('out of order', None, panda_motion(joint_names=[PANDA_JOINTS[1], PANDA_JOINTS[0]] + PANDA_JOINTS[2:]), [],
     ['panda_joint2', str(PANDA_JOINTS)]),
    ('start too short', None, panda_motion(start=PANDA_START[:6]), [], ['start']),
    ('goal too long', None, panda_motion(goal=PANDA_GOAL + [0.0]), [], ['goal']),
    ('start outside limits', None, panda_motion(start=PANDA_START[:3] + [-0.01] + PANDA_START[4:]), [],
     ['start', 'panda_joint4']),
    ('goal outside limits', None, panda_motion(goal=PANDA_GOAL[:5] + [-0.5] + PANDA_GOAL[6:]), [],
     ['goal', 'panda_joint6']),
    ('locked unknown', None, panda_motion(locked={'panda_finger_joint1': 0.02, 'thumb': 0.0}), [], ['thumb']),
    ('locked fixed', None, panda_motion(locked={'panda_finger_joint1': 0.02, 'panda_hand_joint': 0.0}), [],
     ['panda_hand_joint']),
    ('locked controlled', None, panda_motion(locked={'panda_finger_joint1': 0.02, 'panda_joint3': 0.0}), [],
     ['panda_joint3']),
    ('locked outside limits', None, panda_motion(locked={'panda_finger_joint1': 0.05}), [],
     ['panda_finger_joint1']),
    ('mimic controlled', None, panda_motion(joint_names=PANDA_JOINTS + ['panda_finger_joint2'],
                                             start=PANDA_START + [0.01], goal=PANDA_GOAL + [0.01]), [],
     ['panda_finger_joint2']),
    ('mimic locked', None, panda_motion(locked={'panda_finger_joint1': 0.02, 'panda_finger_joint2': 0.02}), [],
     ['panda_finger_joint2']),
    ('zero duration', None, panda_motion(duration=0.0), [], ['duration']),
    ('zero --duration', None, None, ['--duration', '0'], ['duration']),
    ('duration not a multiple of the period', None, panda_motion(duration=0.255), [], ['duration', '0.255']),
    ('--duration not a multiple of the period', None, None, ['--duration', '0.255'], ['duration', '0.255']),
    ('floating joint', scara_with('type="fixed"', 'type="floating"'), SCARA_MOTION, [], ['base_joint', 'floating']),
    ('planar joint', scara_with('type="fixed"', 'type="planar"'), SCARA_MOTION, [], ['base_joint', 'planar']),
    ('massless joint', massless_scara(), SCARA_MOTION, [], ['wrist_joint']),
    ('urdf-limits with effort 0', scara_with('effort="20.0"', 'effort="0"'), SCARA_MOTION, ['--urdf-limits'],
     ['elbow_joint', 'effort']),
    ('mimic outside its limits', mimic_urdf(-0.05, 0.05),
     yaml.safe_dump({'joint_names': ['j1', 'j2'], 'duration': 0.3, 'profile': 'bang_bang', 'start': [0.0, 0.0],
                     'goal': [0.3, 0.3], 'locked': {'drive': 0.4}}),
     [], ['follower']),
]


def refused(capfd, tmp_path, monkeypatch, urdf_text, motion, extra) -> tuple[str, str]:
    """Run `ddarm episode` on them in tmp_path; assert exit 2 and that nothing was written; return (out, err)."""
    monkeypatch.chdir(tmp_path)
    urdf = write(tmp_path / 'arm.urdf', urdf_text) if urdf_text is not None else urdf_of('panda')
    if isinstance(motion, Path):
        motion_path = motion
    else:
        motion_path = write(tmp_path / 'motion.yaml', motion if motion is not None else panda_motion())
    before = sorted(tmp_path.rglob('*'))
    capfd.readouterr()
    code = main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf), '--motion',
                 str(motion_path), '--json', *extra])
    out, err = capfd.readouterr()
    assert code == 2, (out, err)
    assert sorted(tmp_path.rglob('*')) == before, 'a refused episode wrote files'
    return out, err


@pytest.mark.parametrize('case, urdf_text, motion, extra, named', REFUSALS, ids=[case[0] for case in REFUSALS])
def test_every_refusal_is_one_line_naming_the_problem_and_exit_2(capfd, tmp_path, monkeypatch, case, urdf_text,
                                                                   motion, extra, named):
    out, err = refused(capfd, tmp_path, monkeypatch, urdf_text, motion, extra)
    assert out == ''
    assert 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1, err
    for text in named:
        assert text in err, (text, err)


def test_an_unknown_joint_type_is_one_line_naming_the_joint(capfd, tmp_path, monkeypatch):
    """urdf_joints names a joint type URDF does not define; Pinocchio's parser (urdfdom) must not get there first,
    printing its own lines to the process's stderr and a message without the joint."""
    out, err = refused(capfd, tmp_path, monkeypatch, scara_with('type="fixed"', 'type="ball"'), SCARA_MOTION, [])
    assert out == '' and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1, err
    assert 'base_joint' in err and 'ball' in err, err


def test_an_arm_whose_mass_matrix_is_singular_is_refused(capfd, tmp_path, monkeypatch):
    """Two coaxial joints moving one body through a massless link: every M_ii > 0, yet M(q) is singular, so the
    plant cannot be integrated (spec §16's reason for refusing M_ii = 0). It must be refused, not reported as an
    episode that diverged at sample 1 with I = 0 and exit 0."""
    links = {'base': '', 'ghost': '', 'arm': inertial(1.0, '0.2 0 0', ixx=0.001)}
    urdf_text = robot(joint('a', 'revolute', 'base', 'ghost'), joint('b', 'revolute', 'ghost', 'arm'), links=links)
    motion = yaml.safe_dump({'joint_names': ['a', 'b'], 'duration': 0.3, 'profile': 'bang_bang', 'start': [0.0, 0.0],
                             'goal': [0.5, 0.5]})
    out, err = refused(capfd, tmp_path, monkeypatch, urdf_text, motion, [])
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err, err


def test_a_motion_with_no_torque_scale_for_a_joint_is_refused_naming_the_joint(capfd, tmp_path, monkeypatch):
    """Only the SCARA's quill moves: the other joints neither move nor carry gravity, max |P^nom| = 0 (spec §16)."""
    motion = yaml.safe_dump({'joint_names': ['shoulder_joint', 'elbow_joint', 'quill_joint', 'wrist_joint'],
                             'duration': 0.3, 'profile': 'bang_bang', 'start': [0.3, 1.0, -0.02, 0.5],
                             'goal': [0.3, 1.0, -0.12, 0.5]})
    out, err = refused(capfd, tmp_path, monkeypatch, urdf_of('scara').read_text(), motion, [])
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err, err
    assert 'shoulder_joint' in err, err


def test_a_refusal_shows_the_value_as_the_file_has_it(capfd, tmp_path, monkeypatch):
    out, err = refused(capfd, tmp_path, monkeypatch, None,
                       panda_motion(goal=PANDA_GOAL[:3] + [-0.01] + PANDA_GOAL[4:]), [])
    assert 'np.float64' not in err, err


def test_a_joint_the_motion_omits_is_locked_at_zero_as_if_it_were_given():
    """Spec §16: every other movable joint is locked at its `locked` position, default 0."""
    omitted = Arm.from_urdf(urdf_of('panda'), None, PANDA_JOINTS[:6], {'panda_finger_joint1': 0.02})
    given = Arm.from_urdf(urdf_of('panda'), None, PANDA_JOINTS[:6],
                          {'panda_joint7': 0.0, 'panda_finger_joint1': 0.02})
    assert dict(omitted.locked) == dict(given.locked) == {'panda_joint7': 0.0, 'panda_finger_joint1': 0.02,
                                                          'panda_finger_joint2': 0.02}
    q = np.array(PANDA_START[:6])
    np.testing.assert_array_equal(omitted.mass_matrix(q), given.mass_matrix(q))


def test_joints_in_the_files_order_but_not_pinocchios_are_refused_with_pinocchios(capfd, tmp_path, monkeypatch):
    """The tree's file lists the right arm first; Pinocchio numbers the left arm first."""
    file_order = ['yaw', 'right_shoulder', 'right_slide', 'left_shoulder', 'left_wrist']
    motion = yaml.safe_dump({'joint_names': file_order, 'duration': 0.3, 'profile': 'bang_bang',
                             'start': [0.0] * 5, 'goal': [0.5, 0.3, 0.05, 0.4, 1.0]})
    out, err = refused(capfd, tmp_path, monkeypatch, tree_urdf(), motion, [])
    assert str(TREE_ORDER) in err and len(err.strip().splitlines()) == 1, err


def test_a_motion_faster_than_a_velocity_limit_warns_naming_the_joint_and_runs(capsys):
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf_of('scara')),
                 '--motion', str(motion_of('scara')), '--duration', '0.4', '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    # Peaks 2|Δq|/T at T = 0.4 s: 5.0, 3.5 rad/s, 0.5 m/s, 7.5 rad/s against limits 3, 3, 0.5, 6.
    warned = [name for name in summary['joint_names'] if any(f"'{name}'" in w for w in summary['warnings'])]
    assert warned == ['shoulder_joint', 'elbow_joint', 'wrist_joint']
    assert all('velocity' in warning for warning in summary['warnings'])
    assert summary['samples_scored'] == summary['k_max'] + 1 and not summary['diverged']
    # The quill's error is a length: no degrees for it.
    assert [value is None for value in summary['max_abs_error_deg']] == [False, False, True, False]


def test_a_bang_bang_peak_beyond_the_velocity_limit_warns_even_between_samples(tmp_path):
    """The peak 2|Δq|/T is at T/2; with an odd T/Δ no sample lands there. A motion 3 % beyond a limit still is."""
    motion = read_motion(motion_of('scara'))
    goal = motion['start'].copy()
    goal[0] += 1.03 * 3.0 * 0.25 / 2.0  # the shoulder's peak: 1.03 x its 3.0 rad/s limit
    path = write_motion(tmp_path / 'fast.yaml', motion['joint_names'], motion['start'], goal, 0.25)
    goal_velocity = 2.0 * (goal[0] - motion['start'][0]) / 0.25
    assert goal_velocity > 3.0
    warnings = check_episode(EpisodeSpec(controller='computed_torque', kp=(225.0,) * 4, kv=(30.0,) * 4,
                                         urdf=str(urdf_of('scara')), motion=str(path))).warnings
    assert any("'shoulder_joint'" in warning for warning in warnings), warnings


# ---------------------------------------------------------------------------------------------------------------
# 5. Continuous joints, branches, files that change


def test_continuous_joints_pass_through_plus_and_minus_pi_without_wrapping(tmp_path):
    motion = read_motion(motion_of('scara'))
    start = np.array([2.6, 1.2, -0.02, -2.9])
    goal = np.array([3.6, 0.5, -0.12, -3.6])
    path = write_motion(tmp_path / 'through-pi.yaml', motion['joint_names'], start, goal, 1.0)
    spec = with_omega(EpisodeSpec(controller='computed_torque', kp=(1.0,), kv=(1.0,), urdf=str(urdf_of('scara')),
                                  motion=str(path), tau=0.05), 15.0)
    episode = run_episode(spec)
    assert not episode.diverged[0] and not check_episode(spec).warnings
    q = episode.scored('q')
    assert q[:, 0].max() > np.pi + 0.4 and q[:, 3].min() < -np.pi - 0.4
    assert np.max(np.abs(np.diff(q, axis=0))) < 0.1  # no jump of 2π
    assert np.max(np.abs(episode.scored('errors'))) < np.radians(2.0)
    expected = independent_of(spec, {})
    assert episode.indices()['I'] == pytest.approx(expected['I'], rel=TOLERANCE)
    # The same move two turns on is the same episode: the arm does not see 4π, the angles are never wrapped.
    turned = write_motion(tmp_path / 'turned.yaml', motion['joint_names'], start + [4 * np.pi, 0, 0, -4 * np.pi],
                          goal + [4 * np.pi, 0, 0, -4 * np.pi], 1.0)
    again = run_episode(dataclasses.replace(spec, motion=str(turned)))
    assert again.indices() == pytest.approx(episode.indices(), rel=1e-8)
    np.testing.assert_allclose(again.scored('q') - [4 * np.pi, 0, 0, -4 * np.pi], q, atol=1e-9)


def test_a_continuous_joint_beyond_the_divergence_bound_is_refused_and_a_turn_changes_nothing(tmp_path):
    """A continuous joint's angle is never wrapped (spec §16), so a wrist that has turned 24 times sits at
    150 rad, beyond §12's |q| ≤ 100 rad divergence bound: the plan refuses it, naming the joint, rather than
    let the episode end as diverged. Whole turns change nothing else: the dynamics are periodic in the angle."""
    motion = read_motion(motion_of('scara'))
    start, goal = motion['start'].copy(), motion['goal'].copy()
    start[3], goal[3] = 150.0, 151.5
    path = write_motion(tmp_path / 'turned.yaml', motion['joint_names'], start, goal, 1.0)
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 4, kv=(1.0,) * 4, urdf=str(urdf_of('scara')),
                       motion=str(path))
    with pytest.raises(EpisodeError, match="joint 'wrist_joint' reaches q\\^d = 150.0 .*divergence bound"):
        run_episode(spec)
    turns = 2 * np.pi * 10
    start[3], goal[3] = 150.0 - turns, 151.5 - turns
    near = write_motion(tmp_path / 'near.yaml', motion['joint_names'], start, goal, 1.0)
    start[3], goal[3] = 150.0 - turns - 2 * np.pi, 151.5 - turns - 2 * np.pi
    turned = write_motion(tmp_path / 'turned-once-more.yaml', motion['joint_names'], start, goal, 1.0)
    first, second = (run_episode(with_omega(dataclasses.replace(spec, motion=str(file)), 15.0)).indices()
                     for file in (near, turned))
    for key in first:
        assert second[key] == pytest.approx(first[key], rel=1e-9)


def test_a_branching_tree_episode_is_the_independent_episode(tmp_path):
    urdf = write(tmp_path / 'tree.urdf', tree_urdf())
    path = write_motion(tmp_path / 'tree.yaml', TREE_ORDER, [0.0, 0.1, 0.0, -0.2, 0.0], [0.5, 0.4, 1.0, 0.2, 0.05],
                        0.5)
    for controller in ('computed_torque', 'pd_gravity'):
        spec = with_omega(EpisodeSpec(controller=controller, kp=(1.0,), kv=(1.0,), urdf=str(urdf), motion=str(path),
                                      tau=0.05, delay=DELAY[controller], torque_limit='urdf'), OMEGA[controller])
        kp, kv = member_gains(spec)
        batch = simulate_batch(spec, kp, kv)
        for member in range(3):
            expected = independent_of(dataclasses.replace(spec, kp=tuple(kp[member]), kv=tuple(kv[member])), {})
            assert_same_episode(batch, member, expected)


def test_a_locked_middle_joint_episode_is_the_independent_episode(tmp_path):
    motion = read_motion(motion_of('ur5'))
    keep = [0, 1, 3, 4, 5]
    names = [motion['joint_names'][i] for i in keep]
    path = write_motion(tmp_path / 'elbow-locked.yaml', names, motion['start'][keep], motion['goal'][keep], 0.4,
                        {'elbow_joint': 0.8})
    spec = with_omega(EpisodeSpec(controller='computed_torque', kp=(1.0,), kv=(1.0,), urdf=str(urdf_of('ur5')),
                                  motion=str(path), tau=0.05), 15.0)
    expected = independent_of(spec, {'elbow_joint': 0.8})
    episode = run_episode(spec)
    assert episode.joint_names == tuple(names)
    assert episode.indices()['I'] == pytest.approx(expected['I'], rel=TOLERANCE)


def test_a_urdf_changed_on_disk_is_read_again(tmp_path):
    """A motion file is read again when it changes on disk; the URDF it drives must be too, not served stale
    from load_arm's cache (an in-process caller editing an arm between episodes gets the old arm's numbers)."""
    urdf = tmp_path / 'arm.urdf'
    shutil.copy(urdf_of('ur5'), urdf)
    spec = EpisodeSpec(controller='computed_torque', kp=(225.0,) * 6, kv=(30.0,) * 6, urdf=str(urdf),
                       motion=str(motion_of('ur5')), duration=0.3)
    before = plan_episode(spec).nominal
    urdf.write_text(heavier_ur5(tmp_path, new='20.0').read_text())
    after = plan_episode(spec).nominal
    assert not np.array_equal(after, before), 'the episode still uses the URDF as it was before the change'
    names = read_motion(motion_of('ur5'))['joint_names']
    expected = Dynamics(reduced_model(urdf, names, {}))
    motion = read_motion(motion_of('ur5'))
    np.testing.assert_allclose(after[5], expected.rnea(*bang_bang(motion['start'], motion['goal'], 0.3, 0.05)),
                               rtol=1e-12)
    assert np.max(np.abs(after - before)) > 1.0


def test_the_paper_motion_on_another_arm_is_refused_naming_its_joints(capsys):
    assert main(['episode', '--urdf', str(urdf_of('z1')), '--controller', 'computed_torque', '--omega', '15']) == 2
    error = capsys.readouterr().err.strip()
    assert "give a motion file (--motion) for its joints ['joint1'" in error and "'jointGripper'" in error
    assert len(error.splitlines()) == 1


def test_an_episode_shorter_than_its_waypoints_is_refused(tmp_path, capsys):
    path = tmp_path / 'waypoints.yaml'
    path.write_text('joint_names: [joint1, joint2]\nstart: [0.0, 0.0]\npoints:\n'
                    '  - {positions: [0.4, -0.2], velocities: [0.5, 0.0], time_from_start: 0.5}\n'
                    '  - {positions: [0.8, 0.1], velocities: [0.0, 0.0], time_from_start: 1.0}\n')
    arguments = ['episode', '--motion', str(path), '--controller', 'computed_torque', '--omega', '15', '--json']
    assert main([*arguments, '--duration', '0.6']) == 2
    assert 'T = 0.6 s ends before its last point at 1.0 s' in capsys.readouterr().err
    assert main([*arguments, '--duration', '1.5']) == 0
    assert json.loads(capsys.readouterr().out)['locked_joints'] == {'joint3': 0.0}


def test_a_motion_that_moves_at_t0_starts_the_arm_at_rest_and_tau_sets_the_velocity_error(tmp_path):
    """(3.1) as e(0) = 0, ė(0) = q̇^d(τ) (spec §16): positions-only waypoints move from t = 0 (a linear segment),
    yet the arm starts at rest at τ = 0; for a bang-bang motion it is q̇(0) = -q̇^d(τ) exactly."""
    path = tmp_path / 'linear.yaml'
    path.write_text('joint_names: [joint1, joint2, joint3]\npoints:\n'
                    '  - {positions: [0.0, 1.0, -2.0], time_from_start: 0.0}\n'
                    '  - {positions: [0.5, 0.8, -1.5], time_from_start: 1.0}\n')
    for tau in (0.0, 0.3):
        plan = plan_episode(EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3,
                                        motion=str(path), tau=tau))
        moving = np.array([0.5, -0.2, 0.5])  # the linear segment's velocity, at 0 and at τ alike
        np.testing.assert_allclose(plan.v_ref[0], moving, rtol=1e-12)
        np.testing.assert_allclose(plan.v0, moving - moving, atol=0.0)
    bang_bang = plan_episode(EpisodeSpec(controller='computed_torque', kp=(225.0,) * 3, kv=(30.0,) * 3, tau=0.1))
    _, at_tau, _ = bang_bang.motion.sample(0.1)
    np.testing.assert_array_equal(bang_bang.v0, -at_tau)
