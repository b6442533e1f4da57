"""The arm's joint torques as linear in its dynamic parameters: τ = Y(q, q̇, q̈) φ, for identification.

φ holds per link Pinocchio's ten dynamic parameters (m, m c, and the inertia about the joint frame's origin: Ixx,
Ixy, Iyy, Ixz, Iyz, Izz), then per joint its armature, viscous damping and Coulomb friction. Y is Pinocchio's
joint-torque regressor with three columns per joint added: q̈_i (armature), q̇_i (damping) and sign(q̇_i) (Coulomb
friction, as ddarm's plant models it). Only some combinations of φ move the torques (the base parameters):
`base_columns` finds them from the data, as a QR decomposition with column pivoting does.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from ddarm.physics.arm import Arm

LINK_PARAMETERS = ('m', 'mcx', 'mcy', 'mcz', 'Ixx', 'Ixy', 'Iyy', 'Ixz', 'Iyz', 'Izz')
JOINT_PARAMETERS = ('armature', 'damping', 'friction')
# A column of the data's R (QR with pivoting) below this fraction of the largest moves no torque the data can tell
# from the others': its parameter combination is not identifiable from this data.
BASE_TOLERANCE = 1e-8


def parameter_names(arm: Arm) -> list[str]:
    """The names of φ's entries, `<joint>.<parameter>` (each link named by the joint that moves it)."""
    joints = arm.joint_names
    return ([f'{joint}.{name}' for joint in joints for name in LINK_PARAMETERS]
            + [f'{joint}.{name}' for name in JOINT_PARAMETERS for joint in joints])


def parameters(arm: Arm) -> np.ndarray:
    """φ of the arm as its URDF (and ddarm's extensions) give it."""
    model = arm.model
    links = [model.inertias[joint].toDynamicParameters() for joint in range(1, model.njoints)]
    return np.concatenate([*links, np.asarray(model.armature), np.asarray(model.damping),
                           np.asarray(model.friction)])


def regressor(arm: Arm, q, v, a) -> np.ndarray:
    """Y(q, q̇, q̈), of shape (n, 13 n): τ = Y φ for every φ (`parameters`' order)."""
    v, a = np.asarray(v, dtype=float), np.asarray(a, dtype=float)
    links = pin.computeJointTorqueRegressor(arm.model, arm.data, arm.configuration(q), v, a)
    return np.hstack([links, np.diag(a), np.diag(v), np.diag(np.sign(v))])


def stacked_regressor(arm: Arm, q, v, a) -> np.ndarray:
    """The regressors of many samples (rows of q, q̇, q̈) stacked: shape (samples · n, 13 n)."""
    return np.vstack([regressor(arm, *sample) for sample in zip(q, v, a)])


def base_columns(stacked: np.ndarray, tolerance: float = BASE_TOLERANCE) -> np.ndarray:
    """The indices (ascending) of a largest set of φ's columns of `stacked` that are independent: the base
    parameters are these entries of φ plus the combinations of the others that map onto them."""
    scale = np.linalg.norm(stacked, axis=0)
    # A column of rounding errors alone (a first moment along a joint's axis, say) moves no torque at all.
    used = np.flatnonzero(scale > tolerance * np.max(scale, initial=0.0))
    import scipy.linalg  # here, not at the top: 0.2 s that every ddarm command waited for (through identify)

    _, r, pivots = scipy.linalg.qr(stacked[:, used] / scale[used], mode='economic', pivoting=True)
    diagonal = np.abs(np.diag(r))
    rank = int(np.sum(diagonal > tolerance * diagonal[0])) if len(diagonal) else 0
    return np.sort(used[pivots[:rank]])


def condition_number(stacked: np.ndarray, columns: np.ndarray) -> float:
    """The condition number of the base regressor, its columns scaled to unit norm (so that units do not count)."""
    base = stacked[:, columns]
    return float(np.linalg.cond(base / np.linalg.norm(base, axis=0)))
