"""The arm's dynamics as compiled loops over a Pinocchio model's arrays: the one definition every path runs.

The model comes from Pinocchio (ddarm.physics.arm reads the URDF); these loops evaluate it for
many states at once: inverse dynamics (RNEA), the joint-space inertia (CRBA) and forward
dynamics (CRBA + Cholesky), each as Pinocchio's algorithm of that name. Why not Pinocchio at
run time: on this project's 2-core machine its abaInParallel takes 0.48 ms for one RK4 stage
of 1,000 states, which caps the batch engine near 650 episodes/s before any other work; these
loops run the whole episode at about 1,700 (bench/batch_throughput.py). The tests check them
against pin.rnea, pin.crba and pin.aba (random states, armature, revolute and prismatic joints).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np
import pinocchio as pin

from ddarm.physics.arm import PINOCCHIO_JOINTS, ModelError, is_prismatic, load_arm, urdf_stamp

REVOLUTE, PRISMATIC = 0, 1
@dataclass(frozen=True)
class Chain:
    """A Pinocchio model as plain arrays: per joint its parent, kind, axis, placement and link inertia.

    Joint i (0-based) is Pinocchio's joint i + 1; parent -1 is the fixed base. Placements are
    Pinocchio's jointPlacements (child-to-parent rotation and translation at q = 0), inertias
    are expressed in the joint's frame: mass, centre of mass (lever) and inertia about it.
    """

    parent: np.ndarray
    kind: np.ndarray
    axis: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    mass: np.ndarray
    lever: np.ndarray
    inertia: np.ndarray
    armature: np.ndarray
    gravity: np.ndarray

    @property
    def dof(self) -> int:
        return len(self.parent)

    def arrays(self) -> tuple:
        """The fields in the order the compiled functions unpack them."""
        return (self.parent, self.kind, self.axis, self.rotation, self.translation, self.armature, self.gravity,
                self.mass, self.lever, self.inertia)


def chain_from_model(model: pin.Model) -> Chain:
    """The arrays the compiled dynamics read, from a model of 1-DOF revolute (bounded or continuous) or prismatic
    joints; positions are angles and lengths."""
    parent, kind, axis, rotation, translation = [], [], [], [], []
    # Each joint's axis from its motion subspace S (linear part for prismatic, angular for revolute joints): the
    # Python bindings expose no axis for every joint model (RevoluteUnboundedUnaligned has none).
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    for joint_id in range(1, model.njoints):
        joint = model.joints[joint_id]
        name = joint.shortname()
        if name not in PINOCCHIO_JOINTS or joint.nv != 1 or joint.idx_v != joint_id - 1:
            raise ModelError(f'joint {model.names[joint_id]!r} is a {name}: the batch engine supports '
                             f'revolute, continuous and prismatic joints only')
        # Continuous joints (RUB*, Pinocchio's (cos θ, sin θ)) are revolute: their position is the angle θ.
        joint_kind = PRISMATIC if is_prismatic(name) else REVOLUTE
        subspace = np.array(data.joints[joint_id].S).ravel()
        parent.append(model.parents[joint_id] - 1)
        kind.append(joint_kind)
        axis.append(subspace[:3] if joint_kind == PRISMATIC else subspace[3:])
        rotation.append(model.jointPlacements[joint_id].rotation)
        translation.append(model.jointPlacements[joint_id].translation)
    inertias = [model.inertias[joint_id] for joint_id in range(1, model.njoints)]
    return Chain(
        parent=np.array(parent, dtype=np.int64), kind=np.array(kind, dtype=np.int64),
        axis=np.array(axis, dtype=float), rotation=np.array(rotation, dtype=float),
        translation=np.array(translation, dtype=float),
        mass=np.array([inertia.mass for inertia in inertias]),
        lever=np.array([inertia.lever for inertia in inertias]),
        inertia=np.array([inertia.inertia for inertia in inertias]),
        armature=np.array(model.armature, dtype=float), gravity=np.array(model.gravity.linear, dtype=float))


def load_chain(urdf: str | None, joints: tuple[str, ...] | None = None,
               locked: tuple[tuple[str, float], ...] = ()) -> Chain:
    """The chain of the URDF's model reduced to `joints` (the others `locked`), built once per process and version
    of the file."""
    return _load_chain(urdf, urdf_stamp(urdf), joints, locked)


@lru_cache(maxsize=16)
def _load_chain(urdf, stamp, joints, locked) -> Chain:
    return chain_from_model(load_arm(urdf, None, joints, locked).model)



# The compiled kernels keep the members of a chunk on the last axis ("lanes") and loop over
# them innermost: every call of a compiled function costs an atomic reference count per
# array argument, which per member would cost as much as the dynamics themselves. The small
# kernels are inlined into their callers (inline='always'), which saves those calls; the two
# called from two places are not, which saves a third of the compile time.
# Compiled once into __pycache__. error_model='numpy': a division by zero gives inf or NaN,
# as in the scalar path, and the divergence check sees it; fastmath 'contract' only fuses
# multiply-adds, and no flag that assumes finite numbers is set.
COMPILED = dict(cache=True, error_model='numpy', fastmath={'contract'})


@numba.njit(**COMPILED)
def joint_transforms(chain_kind, chain_axis, chain_rotation, chain_translation, q, rotation, translation,
                      lanes):
    """liMi = jointPlacement · X_J(q_i) for every joint: the child-to-parent rotation and translation."""
    for i in range(q.shape[0]):
        ax, ay, az = chain_axis[i, 0], chain_axis[i, 1], chain_axis[i, 2]
        p00, p01, p02 = chain_rotation[i, 0, 0], chain_rotation[i, 0, 1], chain_rotation[i, 0, 2]
        p10, p11, p12 = chain_rotation[i, 1, 0], chain_rotation[i, 1, 1], chain_rotation[i, 1, 2]
        p20, p21, p22 = chain_rotation[i, 2, 0], chain_rotation[i, 2, 1], chain_rotation[i, 2, 2]
        t0, t1, t2 = chain_translation[i, 0], chain_translation[i, 1], chain_translation[i, 2]
        if chain_kind[i] == REVOLUTE:
            for b in range(lanes):
                # Rodrigues: c 1 + s [axis]x + (1 - c) axis axisᵀ.
                c, s = np.cos(q[i, b]), np.sin(q[i, b])
                k = 1.0 - c
                j00, j01, j02 = c + k * ax * ax, k * ax * ay - s * az, k * ax * az + s * ay
                j10, j11, j12 = k * ax * ay + s * az, c + k * ay * ay, k * ay * az - s * ax
                j20, j21, j22 = k * ax * az - s * ay, k * ay * az + s * ax, c + k * az * az
                rotation[i, 0, 0, b] = p00 * j00 + p01 * j10 + p02 * j20
                rotation[i, 0, 1, b] = p00 * j01 + p01 * j11 + p02 * j21
                rotation[i, 0, 2, b] = p00 * j02 + p01 * j12 + p02 * j22
                rotation[i, 1, 0, b] = p10 * j00 + p11 * j10 + p12 * j20
                rotation[i, 1, 1, b] = p10 * j01 + p11 * j11 + p12 * j21
                rotation[i, 1, 2, b] = p10 * j02 + p11 * j12 + p12 * j22
                rotation[i, 2, 0, b] = p20 * j00 + p21 * j10 + p22 * j20
                rotation[i, 2, 1, b] = p20 * j01 + p21 * j11 + p22 * j21
                rotation[i, 2, 2, b] = p20 * j02 + p21 * j12 + p22 * j22
                translation[i, 0, b], translation[i, 1, b], translation[i, 2, b] = t0, t1, t2
        else:
            for b in range(lanes):
                for r in range(3):
                    for col in range(3):
                        rotation[i, r, col, b] = chain_rotation[i, r, col]
                shift = q[i, b]
                translation[i, 0, b] = t0 + (p00 * ax + p01 * ay + p02 * az) * shift
                translation[i, 1, b] = t1 + (p10 * ax + p11 * ay + p12 * az) * shift
                translation[i, 2, b] = t2 + (p20 * ax + p21 * ay + p22 * az) * shift


@numba.njit(**COMPILED)
def inverse_dynamics(chain_parent, chain_kind, chain_axis, armature, gravity, chain_mass, lever, chain_inertia,
                      mass_scale, rotation, translation, v, a, spin, velocity, spin_rate, acceleration, force,
                      moment, tau, lanes):
    """τ = M(q) a + V(q, q̇) + G(q) of (1.1): recursive Newton-Euler in each joint's frame, as Pinocchio's rnea.

    Motions are (linear, angular) at the joint frame's origin; a parent's motion m enters the
    child's frame as Rᵀ(m_lin - t × m_ang), Rᵀ m_ang; the base accelerates at -g. Link i's
    mass and inertia are the chain's times mass_scale[i] (spec §2's plant/model mismatch).
    """
    n = v.shape[0]
    for i in range(n):
        p = chain_parent[i]
        revolute = chain_kind[i] == REVOLUTE
        ax, ay, az = chain_axis[i, 0], chain_axis[i, 1], chain_axis[i, 2]
        c0, c1, c2 = lever[i, 0], lever[i, 1], lever[i, 2]
        i00, i01, i02 = chain_inertia[i, 0, 0], chain_inertia[i, 0, 1], chain_inertia[i, 0, 2]
        i10, i11, i12 = chain_inertia[i, 1, 0], chain_inertia[i, 1, 1], chain_inertia[i, 1, 2]
        i20, i21, i22 = chain_inertia[i, 2, 0], chain_inertia[i, 2, 1], chain_inertia[i, 2, 2]
        for b in range(lanes):
            if p < 0:
                pw0, pw1, pw2, pl0, pl1, pl2 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                pdw0, pdw1, pdw2 = 0.0, 0.0, 0.0
                pdl0, pdl1, pdl2 = -gravity[0], -gravity[1], -gravity[2]
            else:
                pw0, pw1, pw2 = spin[p, 0, b], spin[p, 1, b], spin[p, 2, b]
                pl0, pl1, pl2 = velocity[p, 0, b], velocity[p, 1, b], velocity[p, 2, b]
                pdw0, pdw1, pdw2 = spin_rate[p, 0, b], spin_rate[p, 1, b], spin_rate[p, 2, b]
                pdl0, pdl1, pdl2 = acceleration[p, 0, b], acceleration[p, 1, b], acceleration[p, 2, b]
            t0, t1, t2 = translation[i, 0, b], translation[i, 1, b], translation[i, 2, b]
            r00, r01, r02 = rotation[i, 0, 0, b], rotation[i, 0, 1, b], rotation[i, 0, 2, b]
            r10, r11, r12 = rotation[i, 1, 0, b], rotation[i, 1, 1, b], rotation[i, 1, 2, b]
            r20, r21, r22 = rotation[i, 2, 0, b], rotation[i, 2, 1, b], rotation[i, 2, 2, b]
            ul0, ul1, ul2 = pl0 - (t1 * pw2 - t2 * pw1), pl1 - (t2 * pw0 - t0 * pw2), pl2 - (t0 * pw1 - t1 * pw0)
            ua0 = pdl0 - (t1 * pdw2 - t2 * pdw1)
            ua1 = pdl1 - (t2 * pdw0 - t0 * pdw2)
            ua2 = pdl2 - (t0 * pdw1 - t1 * pdw0)
            w0 = r00 * pw0 + r10 * pw1 + r20 * pw2
            w1 = r01 * pw0 + r11 * pw1 + r21 * pw2
            w2 = r02 * pw0 + r12 * pw1 + r22 * pw2
            l0 = r00 * ul0 + r10 * ul1 + r20 * ul2
            l1 = r01 * ul0 + r11 * ul1 + r21 * ul2
            l2 = r02 * ul0 + r12 * ul1 + r22 * ul2
            dw0 = r00 * pdw0 + r10 * pdw1 + r20 * pdw2
            dw1 = r01 * pdw0 + r11 * pdw1 + r21 * pdw2
            dw2 = r02 * pdw0 + r12 * pdw1 + r22 * pdw2
            dl0 = r00 * ua0 + r10 * ua1 + r20 * ua2
            dl1 = r01 * ua0 + r11 * ua1 + r21 * ua2
            dl2 = r02 * ua0 + r12 * ua1 + r22 * ua2
            rate, accel = v[i, b], a[i, b]
            # a_i = X a_parent + S q̈ + v_i × v_J, with v_J = S q̇.
            if revolute:
                jw0, jw1, jw2 = ax * rate, ay * rate, az * rate
                w0, w1, w2 = w0 + jw0, w1 + jw1, w2 + jw2
                dw0 += ax * accel + (w1 * jw2 - w2 * jw1)
                dw1 += ay * accel + (w2 * jw0 - w0 * jw2)
                dw2 += az * accel + (w0 * jw1 - w1 * jw0)
                dl0 += l1 * jw2 - l2 * jw1
                dl1 += l2 * jw0 - l0 * jw2
                dl2 += l0 * jw1 - l1 * jw0
            else:
                jl0, jl1, jl2 = ax * rate, ay * rate, az * rate
                l0, l1, l2 = l0 + jl0, l1 + jl1, l2 + jl2
                dl0 += ax * accel + (w1 * jl2 - w2 * jl1)
                dl1 += ay * accel + (w2 * jl0 - w0 * jl2)
                dl2 += az * accel + (w0 * jl1 - w1 * jl0)
            spin[i, 0, b], spin[i, 1, b], spin[i, 2, b] = w0, w1, w2
            velocity[i, 0, b], velocity[i, 1, b], velocity[i, 2, b] = l0, l1, l2
            spin_rate[i, 0, b], spin_rate[i, 1, b], spin_rate[i, 2, b] = dw0, dw1, dw2
            acceleration[i, 0, b], acceleration[i, 1, b], acceleration[i, 2, b] = dl0, dl1, dl2
            # f = I a + v ×* (I v), with I m = (m (m_lin - c × m_ang), I_c m_ang + c × that).
            scale = mass_scale[i, b]
            m = chain_mass[i] * scale
            hv0 = m * (l0 - (c1 * w2 - c2 * w1))
            hv1 = m * (l1 - (c2 * w0 - c0 * w2))
            hv2 = m * (l2 - (c0 * w1 - c1 * w0))
            nv0 = (i00 * scale) * w0 + (i01 * scale) * w1 + (i02 * scale) * w2 + (c1 * hv2 - c2 * hv1)
            nv1 = (i10 * scale) * w0 + (i11 * scale) * w1 + (i12 * scale) * w2 + (c2 * hv0 - c0 * hv2)
            nv2 = (i20 * scale) * w0 + (i21 * scale) * w1 + (i22 * scale) * w2 + (c0 * hv1 - c1 * hv0)
            ha0 = m * (dl0 - (c1 * dw2 - c2 * dw1))
            ha1 = m * (dl1 - (c2 * dw0 - c0 * dw2))
            ha2 = m * (dl2 - (c0 * dw1 - c1 * dw0))
            na0 = (i00 * scale) * dw0 + (i01 * scale) * dw1 + (i02 * scale) * dw2 + (c1 * ha2 - c2 * ha1)
            na1 = (i10 * scale) * dw0 + (i11 * scale) * dw1 + (i12 * scale) * dw2 + (c2 * ha0 - c0 * ha2)
            na2 = (i20 * scale) * dw0 + (i21 * scale) * dw1 + (i22 * scale) * dw2 + (c0 * ha1 - c1 * ha0)
            force[i, 0, b] = ha0 + (w1 * hv2 - w2 * hv1)
            force[i, 1, b] = ha1 + (w2 * hv0 - w0 * hv2)
            force[i, 2, b] = ha2 + (w0 * hv1 - w1 * hv0)
            moment[i, 0, b] = na0 + (w1 * nv2 - w2 * nv1) + (l1 * hv2 - l2 * hv1)
            moment[i, 1, b] = na1 + (w2 * nv0 - w0 * nv2) + (l2 * hv0 - l0 * hv2)
            moment[i, 2, b] = na2 + (w0 * nv1 - w1 * nv0) + (l0 * hv1 - l1 * hv0)
    for i in range(n - 1, -1, -1):
        p = chain_parent[i]
        revolute = chain_kind[i] == REVOLUTE
        ax, ay, az = chain_axis[i, 0], chain_axis[i, 1], chain_axis[i, 2]
        for b in range(lanes):
            f0, f1, f2 = force[i, 0, b], force[i, 1, b], force[i, 2, b]
            n0, n1, n2 = moment[i, 0, b], moment[i, 1, b], moment[i, 2, b]
            if revolute:
                tau[i, b] = ax * n0 + ay * n1 + az * n2 + armature[i] * a[i, b]
            else:
                tau[i, b] = ax * f0 + ay * f1 + az * f2 + armature[i] * a[i, b]
            if p >= 0:
                g0, g1, g2, e0, e1, e2 = _to_parent(rotation, translation, i, b, f0, f1, f2, n0, n1, n2)
                force[p, 0, b] += g0
                force[p, 1, b] += g1
                force[p, 2, b] += g2
                moment[p, 0, b] += e0
                moment[p, 1, b] += e1
                moment[p, 2, b] += e2


@numba.njit(**COMPILED, inline='always')
def _to_parent(rotation, translation, i, b, f0, f1, f2, n0, n1, n2):
    """A force (linear f, moment n) at joint i's frame, expressed at its parent's: R f, R n + t × R f."""
    g0 = rotation[i, 0, 0, b] * f0 + rotation[i, 0, 1, b] * f1 + rotation[i, 0, 2, b] * f2
    g1 = rotation[i, 1, 0, b] * f0 + rotation[i, 1, 1, b] * f1 + rotation[i, 1, 2, b] * f2
    g2 = rotation[i, 2, 0, b] * f0 + rotation[i, 2, 1, b] * f1 + rotation[i, 2, 2, b] * f2
    t0, t1, t2 = translation[i, 0, b], translation[i, 1, b], translation[i, 2, b]
    e0 = rotation[i, 0, 0, b] * n0 + rotation[i, 0, 1, b] * n1 + rotation[i, 0, 2, b] * n2 + (t1 * g2 - t2 * g1)
    e1 = rotation[i, 1, 0, b] * n0 + rotation[i, 1, 1, b] * n1 + rotation[i, 1, 2, b] * n2 + (t2 * g0 - t0 * g2)
    e2 = rotation[i, 2, 0, b] * n0 + rotation[i, 2, 1, b] * n1 + rotation[i, 2, 2, b] * n2 + (t0 * g1 - t1 * g0)
    return g0, g1, g2, e0, e1, e2


@numba.njit(**COMPILED, inline='always')
def joint_space_inertia(chain_parent, chain_kind, chain_axis, armature, chain_mass, lever, chain_inertia,
                        mass_scale, rotation, translation, composite_mass, first_moment, origin_inertia, mass_matrix,
                        lanes):
    """M(q) of (1.1), both triangles: the composite-rigid-body algorithm, as Pinocchio's crba.

    A composite body is kept as its mass m, first moment h = m c and inertia I about the joint
    frame's origin; it moves to the parent frame as h' = R h + m t and
    I' = R I Rᵀ + (2 t·Rh + m |t|²) 1 - t (Rh)ᵀ - (Rh) tᵀ - m t tᵀ (I stays symmetric).
    """
    n = chain_mass.shape[0]
    for i in range(n):
        c0, c1, c2 = lever[i, 0], lever[i, 1], lever[i, 2]
        cc = c0 * c0 + c1 * c1 + c2 * c2
        for b in range(lanes):
            scale = mass_scale[i, b]
            m = chain_mass[i] * scale
            composite_mass[i, b] = m
            first_moment[i, 0, b], first_moment[i, 1, b], first_moment[i, 2, b] = m * c0, m * c1, m * c2
            for r in range(3):
                for col in range(3):
                    origin_inertia[i, r, col, b] = chain_inertia[i, r, col] * scale - m * lever[i, r] * lever[i, col]
                origin_inertia[i, r, r, b] += m * cc
    for i in range(n - 1, -1, -1):
        p = chain_parent[i]
        revolute = chain_kind[i] == REVOLUTE
        ax, ay, az = chain_axis[i, 0], chain_axis[i, 1], chain_axis[i, 2]
        for b in range(lanes):
            m = composite_mass[i, b]
            h0, h1, h2 = first_moment[i, 0, b], first_moment[i, 1, b], first_moment[i, 2, b]
            # F = I_composite S_i: momentum (linear m v + ω × h, angular h × v + I ω) of the joint's unit motion.
            if revolute:
                f0, f1, f2 = ay * h2 - az * h1, az * h0 - ax * h2, ax * h1 - ay * h0
                n0 = origin_inertia[i, 0, 0, b] * ax + origin_inertia[i, 0, 1, b] * ay + origin_inertia[i, 0, 2, b] * az
                n1 = origin_inertia[i, 1, 0, b] * ax + origin_inertia[i, 1, 1, b] * ay + origin_inertia[i, 1, 2, b] * az
                n2 = origin_inertia[i, 2, 0, b] * ax + origin_inertia[i, 2, 1, b] * ay + origin_inertia[i, 2, 2, b] * az
                mass_matrix[i, i, b] = ax * n0 + ay * n1 + az * n2 + armature[i]
            else:
                f0, f1, f2 = m * ax, m * ay, m * az
                n0, n1, n2 = h1 * az - h2 * ay, h2 * ax - h0 * az, h0 * ay - h1 * ax
                mass_matrix[i, i, b] = ax * f0 + ay * f1 + az * f2 + armature[i]
            j = i
            while chain_parent[j] >= 0:
                f0, f1, f2, n0, n1, n2 = _to_parent(rotation, translation, j, b, f0, f1, f2, n0, n1, n2)
                j = chain_parent[j]
                if chain_kind[j] == REVOLUTE:
                    entry = chain_axis[j, 0] * n0 + chain_axis[j, 1] * n1 + chain_axis[j, 2] * n2
                else:
                    entry = chain_axis[j, 0] * f0 + chain_axis[j, 1] * f1 + chain_axis[j, 2] * f2
                mass_matrix[j, i, b] = entry
                mass_matrix[i, j, b] = entry
            if p >= 0:
                t0, t1, t2 = translation[i, 0, b], translation[i, 1, b], translation[i, 2, b]
                r00, r01, r02 = rotation[i, 0, 0, b], rotation[i, 0, 1, b], rotation[i, 0, 2, b]
                r10, r11, r12 = rotation[i, 1, 0, b], rotation[i, 1, 1, b], rotation[i, 1, 2, b]
                r20, r21, r22 = rotation[i, 2, 0, b], rotation[i, 2, 1, b], rotation[i, 2, 2, b]
                g0 = r00 * h0 + r01 * h1 + r02 * h2
                g1 = r10 * h0 + r11 * h1 + r12 * h2
                g2 = r20 * h0 + r21 * h1 + r22 * h2
                composite_mass[p, b] += m
                first_moment[p, 0, b] += g0 + m * t0
                first_moment[p, 1, b] += g1 + m * t1
                first_moment[p, 2, b] += g2 + m * t2
                # A = I Rᵀ, then R A, for the symmetric I of the child.
                i00, i01, i02 = origin_inertia[i, 0, 0, b], origin_inertia[i, 0, 1, b], origin_inertia[i, 0, 2, b]
                i11, i12, i22 = origin_inertia[i, 1, 1, b], origin_inertia[i, 1, 2, b], origin_inertia[i, 2, 2, b]
                a00, a01, a02 = i00 * r00 + i01 * r01 + i02 * r02, i00 * r10 + i01 * r11 + i02 * r12, \
                    i00 * r20 + i01 * r21 + i02 * r22
                a10, a11, a12 = i01 * r00 + i11 * r01 + i12 * r02, i01 * r10 + i11 * r11 + i12 * r12, \
                    i01 * r20 + i11 * r21 + i12 * r22
                a20, a21, a22 = i02 * r00 + i12 * r01 + i22 * r02, i02 * r10 + i12 * r11 + i22 * r12, \
                    i02 * r20 + i12 * r21 + i22 * r22
                shift = 2.0 * (t0 * g0 + t1 * g1 + t2 * g2) + m * (t0 * t0 + t1 * t1 + t2 * t2)
                e00 = r00 * a00 + r01 * a10 + r02 * a20 - (2.0 * t0 * g0 + m * t0 * t0) + shift
                e11 = r10 * a01 + r11 * a11 + r12 * a21 - (2.0 * t1 * g1 + m * t1 * t1) + shift
                e22 = r20 * a02 + r21 * a12 + r22 * a22 - (2.0 * t2 * g2 + m * t2 * t2) + shift
                e01 = r00 * a01 + r01 * a11 + r02 * a21 - (t0 * g1 + g0 * t1 + m * t0 * t1)
                e02 = r00 * a02 + r01 * a12 + r02 * a22 - (t0 * g2 + g0 * t2 + m * t0 * t2)
                e12 = r10 * a02 + r11 * a12 + r12 * a22 - (t1 * g2 + g1 * t2 + m * t1 * t2)
                origin_inertia[p, 0, 0, b] += e00
                origin_inertia[p, 1, 1, b] += e11
                origin_inertia[p, 2, 2, b] += e22
                origin_inertia[p, 0, 1, b] += e01
                origin_inertia[p, 1, 0, b] += e01
                origin_inertia[p, 0, 2, b] += e02
                origin_inertia[p, 2, 0, b] += e02
                origin_inertia[p, 1, 2, b] += e12
                origin_inertia[p, 2, 1, b] += e12


@numba.njit(**COMPILED, inline='always')
def solve_spd(matrix, rhs, factor, out, lanes):
    """out = matrix⁻¹ rhs for symmetric positive definite matrices (Cholesky, matrix = L Lᵀ)."""
    n = rhs.shape[0]
    for j in range(n):
        for b in range(lanes):
            diagonal = matrix[j, j, b]
            for k in range(j):
                diagonal -= factor[j, k, b] * factor[j, k, b]
            factor[j, j, b] = np.sqrt(diagonal)
        for i in range(j + 1, n):
            for b in range(lanes):
                entry = matrix[i, j, b]
                for k in range(j):
                    entry -= factor[i, k, b] * factor[j, k, b]
                factor[i, j, b] = entry / factor[j, j, b]
    for i in range(n):
        for b in range(lanes):
            entry = rhs[i, b]
            for k in range(i):
                entry -= factor[i, k, b] * out[k, b]
            out[i, b] = entry / factor[i, i, b]
    for i in range(n - 1, -1, -1):
        for b in range(lanes):
            entry = out[i, b]
            for k in range(i + 1, n):
                entry -= factor[k, i, b] * out[k, b]
            out[i, b] = entry / factor[i, i, b]


@numba.njit(**COMPILED, inline='always')
def workspace(n, lanes):
    """Scratch arrays for a chunk's dynamics, the Data of Pinocchio's Model/Data pair: one column per member."""
    return (np.zeros((n, 3, 3, lanes)), np.zeros((n, 3, lanes)), np.zeros((n, 3, lanes)), np.zeros((n, 3, lanes)),
            np.zeros((n, 3, lanes)), np.zeros((n, 3, lanes)), np.zeros((n, 3, lanes)), np.zeros((n, 3, lanes)),
            np.zeros((n, lanes)), np.zeros((n, 3, lanes)), np.zeros((n, 3, 3, lanes)), np.zeros((n, lanes)),
            np.zeros((n, lanes)), np.zeros((n, n, lanes)), np.zeros((n, n, lanes)))


@numba.njit(**COMPILED, inline='always')
def forward_dynamics(chain, mass_scale, q, v, torque, work, out, lanes):
    """q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque (1.1): M by CRBA, V + G by RNEA at q̈ = 0, Cholesky."""
    parent, kind, axis, placement_rotation, placement_translation, armature, gravity, mass, lever, inertia = chain
    (rotation, translation, spin, velocity, spin_rate, acceleration, force, moment, composite_mass,
     first_moment, origin_inertia, zero, bias, mass_matrix, factor) = work
    joint_transforms(kind, axis, placement_rotation, placement_translation, q, rotation, translation, lanes)
    inverse_dynamics(parent, kind, axis, armature, gravity, mass, lever, inertia, mass_scale, rotation,
                     translation, v, zero, spin, velocity, spin_rate, acceleration, force, moment, bias, lanes)
    joint_space_inertia(parent, kind, axis, armature, mass, lever, inertia, mass_scale, rotation, translation,
                 composite_mass, first_moment, origin_inertia, mass_matrix, lanes)
    for i in range(q.shape[0]):
        for b in range(lanes):
            bias[i, b] = torque[i, b] - bias[i, b]
    solve_spd(mass_matrix, bias, factor, out, lanes)



def inverse_dynamics_at(chain: Chain, q: np.ndarray, v: np.ndarray, a: np.ndarray,
                        mass_scale: np.ndarray | None = None) -> np.ndarray:
    """τ = M(q) a + V(q, q̇) + G(q) at m states (arrays of shape (m, n)), the states run as lanes."""
    q, v, a = (np.ascontiguousarray(np.transpose(np.atleast_2d(x)), dtype=float) for x in (q, v, a))
    n, lanes = q.shape
    scale = np.ones((n, lanes)) if mass_scale is None else np.ascontiguousarray(
        np.broadcast_to(np.asarray(mass_scale, dtype=float)[:, None], (n, lanes)))
    parent, kind, axis, placement_rotation, placement_translation, armature, gravity, mass, lever, inertia = (
        chain.arrays())
    rotation, translation = np.empty((n, 3, 3, lanes)), np.empty((n, 3, lanes))
    links = [np.empty((n, 3, lanes)) for _ in range(6)]
    tau = np.empty((n, lanes))
    joint_transforms(kind, axis, placement_rotation, placement_translation, q, rotation, translation, lanes)
    inverse_dynamics(parent, kind, axis, armature, gravity, mass, lever, inertia, scale, rotation, translation, v, a,
                     *links, tau, lanes)
    return np.ascontiguousarray(tau.T)
