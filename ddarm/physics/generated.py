"""The dynamics of one arm as generated straight-line code: RNEA, CRBA and Cholesky unrolled for its chain.

The chain's constants (axes, placements, masses, inertias) are written into the code, and every
product with an exact 0 or ±1 among them is left out while writing it: a joint about z needs no
Rodrigues formula, a link with its centre of mass on an axis no full cross product. What is left
is the same algorithm as Pinocchio's rnea, crba and a Cholesky solve, evaluated in the same order,
per member ("lane") of a chunk, with every intermediate a local variable that the compiler keeps
in registers. Why generate our own: no library writes numba code from a Pinocchio model, and
Pinocchio's own code generation needs its CasADi or CppAD build, which PyPI's `pin` is not.

Each model's code is a module in the user's cache folder named by the hash of the chain and of
this generator, compiled by numba once and cached there (ddarm.physics.dynamics loads it).
"""

from __future__ import annotations

import math

import numpy as np

from ddarm.physics.arm import ModelError
from ddarm.physics.dynamics import COMPILED, REVOLUTE

# Part of every module's hash: a change to what is generated must change it.
GENERATOR_VERSION = 1


def _is_constant(value) -> bool:
    return isinstance(value, float)


def _term(value) -> str:
    if _is_constant(value):
        return f'({value!r})' if value < 0 or math.copysign(1.0, value) < 0 else repr(value)
    return value


class _Code:
    """Straight-line code: every operation on a variable is a new local; operations on constants are done here.

    A value is a float (known now) or the name of a local. Folding x·0 to 0 is exact for finite x;
    a non-finite state reaches the outputs through the terms that remain and the divergence check.
    """

    def __init__(self, indent: str) -> None:
        self.indent = indent
        self.lines: list[str] = []
        self._count = 0

    def let(self, expression: str) -> str:
        name = f'x{self._count}'
        self._count += 1
        self.lines.append(f'{self.indent}{name} = {expression}')
        return name

    def add(self, a, b):
        if _is_constant(a) and _is_constant(b):
            return a + b
        if _is_constant(a) and a == 0.0:
            return b
        if _is_constant(b) and b == 0.0:
            return a
        if _is_constant(b) and b < 0:
            return self.let(f'{_term(a)} - {_term(-b)}')
        return self.let(f'{_term(a)} + {_term(b)}')

    def sub(self, a, b):
        if _is_constant(b):
            return self.add(a, -b)
        if _is_constant(a) and a == 0.0:
            return self.neg(b)
        return self.let(f'{_term(a)} - {_term(b)}')

    def neg(self, a):
        return -a if _is_constant(a) else self.let(f'-{a}')

    def mul(self, a, b):
        if _is_constant(a) and _is_constant(b):
            return a * b
        if _is_constant(b):
            a, b = b, a
        if _is_constant(a):
            if a == 0.0:
                return 0.0
            if a == 1.0:
                return b
            if a == -1.0:
                return self.neg(b)
        return self.let(f'{_term(a)} * {_term(b)}')

    def div(self, a, b):
        if _is_constant(a) and _is_constant(b):
            return a / b
        if _is_constant(a) and a == 0.0:
            return 0.0
        return self.let(f'{_term(a)} / {_term(b)}')

    def call(self, function: str, a):
        if _is_constant(a):
            return float(getattr(np, function)(a))
        return self.let(f'np.{function}({a})')

    # 3-vectors and 3x3 matrices as lists of values.
    def dot(self, a, b):
        total = 0.0
        for x, y in zip(a, b):
            total = self.add(total, self.mul(x, y))
        return total

    def vadd(self, a, b):
        return [self.add(x, y) for x, y in zip(a, b)]

    def vsub(self, a, b):
        return [self.sub(x, y) for x, y in zip(a, b)]

    def scale(self, s, a):
        return [self.mul(s, x) for x in a]

    def cross(self, a, b):
        return [self.sub(self.mul(a[1], b[2]), self.mul(a[2], b[1])),
                self.sub(self.mul(a[2], b[0]), self.mul(a[0], b[2])),
                self.sub(self.mul(a[0], b[1]), self.mul(a[1], b[0]))]

    def matvec(self, m, a):
        return [self.dot(row, a) for row in m]

    def tmatvec(self, m, a):
        return [self.dot([m[0][c], m[1][c], m[2][c]], a) for c in range(3)]

    def matmul(self, a, b):
        return [[self.dot(a[r], [b[0][c], b[1][c], b[2][c]]) for c in range(3)] for r in range(3)]


def _constants(array) -> list:
    if not np.all(np.isfinite(array)):
        raise ModelError(f'the chain has a non-finite constant: {np.asarray(array).tolist()}')
    return [float(x) for x in array] if np.ndim(array) == 1 else [_constants(row) for row in array]


def _joint_rotation(code: _Code, axis, angle):
    """X_J's rotation about a unit axis: exact for an axis along x, y or z, else Rodrigues'
    c 1 + s [axis]x + (1 - c) axis axisᵀ."""
    c, s = code.call('cos', angle), code.call('sin', angle)
    along = [k for k in range(3) if axis[k] != 0.0]
    if len(along) == 1 and abs(axis[along[0]]) == 1.0:
        k = along[0]
        sign = axis[k]
        s = s if sign > 0 else code.neg(s)
        i, j = (k + 1) % 3, (k + 2) % 3
        rotation = [[0.0] * 3 for _ in range(3)]
        rotation[k][k] = 1.0
        rotation[i][i], rotation[j][j] = c, c
        rotation[i][j], rotation[j][i] = code.neg(s), s
        return rotation
    k = code.sub(1.0, c)
    ax, ay, az = axis
    return [[code.add(c, code.mul(k, ax * ax)), code.sub(code.mul(k, ax * ay), code.mul(s, az)),
             code.add(code.mul(k, ax * az), code.mul(s, ay))],
            [code.add(code.mul(k, ax * ay), code.mul(s, az)), code.add(c, code.mul(k, ay * ay)),
             code.sub(code.mul(k, ay * az), code.mul(s, ax))],
            [code.sub(code.mul(k, ax * az), code.mul(s, ay)), code.add(code.mul(k, ay * az), code.mul(s, ax)),
             code.add(c, code.mul(k, az * az))]]


class _Chain:
    """The chain's arrays as constants, and the per-lane values of one evaluation."""

    def __init__(self, chain) -> None:
        self.n = len(chain.parent)
        self.parent = [int(p) for p in chain.parent]
        self.kind = [int(k) for k in chain.kind]
        self.axis = _constants(chain.axis)
        self.placement_rotation = [_constants(r) for r in chain.rotation]
        self.placement_translation = _constants(chain.translation)
        self.mass = _constants(chain.mass)
        self.lever = _constants(chain.lever)
        self.inertia = [_constants(i) for i in chain.inertia]
        self.armature = _constants(chain.armature)
        self.gravity = _constants(chain.gravity)


def _transforms(code: _Code, chain: _Chain, q):
    """liMi = jointPlacement · X_J(q_i) per joint: child-to-parent rotation and translation."""
    rotations, translations = [], []
    for i in range(chain.n):
        placement, t, axis = chain.placement_rotation[i], chain.placement_translation[i], chain.axis[i]
        if chain.kind[i] == REVOLUTE:
            rotations.append(code.matmul(placement, _joint_rotation(code, axis, q[i])))
            translations.append(list(t))
        else:
            rotations.append(placement)
            translations.append(code.vadd(t, code.scale(q[i], code.matvec(placement, axis))))
    return rotations, translations


def _to_parent(code: _Code, rotation, translation, f, n):
    """A force (f, n) at a joint's frame expressed at its parent's: R f, R n + t × R f."""
    g = code.matvec(rotation, f)
    return g, code.vadd(code.matvec(rotation, n), code.cross(translation, g))


def _inverse_dynamics(code: _Code, chain: _Chain, scale, rotations, translations, v, a):
    """τ = M(q) a + V(q, q̇) + G(q): recursive Newton-Euler in each joint's frame, as Pinocchio's rnea."""
    spin, velocity, spin_rate, acceleration, force, moment = [], [], [], [], [], []
    for i in range(chain.n):
        p = chain.parent[i]
        if p < 0:
            pw, pl, pdw, pdl = [0.0] * 3, [0.0] * 3, [0.0] * 3, [-g for g in chain.gravity]
        else:
            pw, pl, pdw, pdl = spin[p], velocity[p], spin_rate[p], acceleration[p]
        r, t, axis = rotations[i], translations[i], chain.axis[i]
        w = code.tmatvec(r, pw)
        lin = code.tmatvec(r, code.vsub(pl, code.cross(t, pw)))
        dw = code.tmatvec(r, pdw)
        dl = code.tmatvec(r, code.vsub(pdl, code.cross(t, pdw)))
        joint_motion = code.scale(v[i], axis)
        if chain.kind[i] == REVOLUTE:
            w = code.vadd(w, joint_motion)
            dw = code.vadd(dw, code.vadd(code.scale(a[i], axis), code.cross(w, joint_motion)))
            dl = code.vadd(dl, code.cross(lin, joint_motion))
        else:
            lin = code.vadd(lin, joint_motion)
            dl = code.vadd(dl, code.vadd(code.scale(a[i], axis), code.cross(w, joint_motion)))
        spin.append(w), velocity.append(lin), spin_rate.append(dw), acceleration.append(dl)
        m = code.mul(chain.mass[i], scale[i])
        inertia = [[code.mul(x, scale[i]) for x in row] for row in chain.inertia[i]]
        c = chain.lever[i]
        hv = code.scale(m, code.vsub(lin, code.cross(c, w)))
        nv = code.vadd(code.matvec(inertia, w), code.cross(c, hv))
        ha = code.scale(m, code.vsub(dl, code.cross(c, dw)))
        na = code.vadd(code.matvec(inertia, dw), code.cross(c, ha))
        force.append(code.vadd(ha, code.cross(w, hv)))
        moment.append(code.vadd(code.vadd(na, code.cross(w, nv)), code.cross(lin, hv)))
    tau = [0.0] * chain.n
    for i in range(chain.n - 1, -1, -1):
        p, axis = chain.parent[i], chain.axis[i]
        along = moment[i] if chain.kind[i] == REVOLUTE else force[i]
        tau[i] = code.add(code.dot(axis, along), code.mul(chain.armature[i], a[i]))
        if p >= 0:
            g, e = _to_parent(code, rotations[i], translations[i], force[i], moment[i])
            force[p], moment[p] = code.vadd(force[p], g), code.vadd(moment[p], e)
    return tau


def _joint_space_inertia(code: _Code, chain: _Chain, scale, rotations, translations):
    """M(q), both triangles: the composite-rigid-body algorithm, as Pinocchio's crba (composites kept as mass,
    first moment h = m c and inertia about the joint frame's origin)."""
    n = chain.n
    composite_mass, first_moment, origin_inertia = [], [], []
    for i in range(n):
        m = code.mul(chain.mass[i], scale[i])
        c = chain.lever[i]
        cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        composite_mass.append(m)
        first_moment.append(code.scale(m, c))
        origin_inertia.append([[code.add(code.sub(code.mul(chain.inertia[i][r][col], scale[i]),
                                                  code.mul(m, c[r] * c[col])),
                                         code.mul(m, cc) if r == col else 0.0) for col in range(3)]
                               for r in range(3)])
    mass_matrix = [[0.0] * n for _ in range(n)]
    for i in range(n - 1, -1, -1):
        p, axis = chain.parent[i], chain.axis[i]
        m, h, inertia = composite_mass[i], first_moment[i], origin_inertia[i]
        if chain.kind[i] == REVOLUTE:
            f, moment = code.cross(axis, h), code.matvec(inertia, axis)
            mass_matrix[i][i] = code.add(code.dot(axis, moment), chain.armature[i])
        else:
            f, moment = code.scale(m, axis), code.cross(h, axis)
            mass_matrix[i][i] = code.add(code.dot(axis, f), chain.armature[i])
        j = i
        while chain.parent[j] >= 0:
            f, moment = _to_parent(code, rotations[j], translations[j], f, moment)
            j = chain.parent[j]
            entry = code.dot(chain.axis[j], moment if chain.kind[j] == REVOLUTE else f)
            mass_matrix[j][i] = mass_matrix[i][j] = entry
        if p >= 0:
            r, t = rotations[i], translations[i]
            g = code.matvec(r, h)
            composite_mass[p] = code.add(composite_mass[p], m)
            first_moment[p] = code.vadd(first_moment[p], code.vadd(g, code.scale(m, t)))
            # R I Rᵀ + (2 t·Rh + m |t|²) 1 - t (Rh)ᵀ - (Rh) tᵀ - m t tᵀ, for the symmetric I.
            rotated = code.matmul(r, code.matmul(inertia, [[r[col][row] for col in range(3)] for row in range(3)]))
            shift = code.add(code.mul(2.0, code.dot(t, g)), code.mul(m, code.dot(t, t)))
            for row in range(3):
                for col in range(row, 3):
                    entry = code.sub(rotated[row][col], code.add(code.add(code.mul(t[row], g[col]),
                                                                          code.mul(g[row], t[col])),
                                                                 code.mul(m, code.mul(t[row], t[col]))))
                    if row == col:
                        entry = code.add(entry, shift)
                    origin_inertia[p][row][col] = code.add(origin_inertia[p][row][col], entry)
                    if row != col:
                        origin_inertia[p][col][row] = origin_inertia[p][row][col]
    return mass_matrix


def _solve_spd(code: _Code, matrix, rhs):
    """matrix⁻¹ rhs for a symmetric positive definite matrix: Cholesky (matrix = L Lᵀ), then the two
    triangular solves, each division by a diagonal entry done as a product with its reciprocal."""
    n = len(rhs)
    factor = [[0.0] * n for _ in range(n)]
    reciprocal = [0.0] * n
    for j in range(n):
        diagonal = matrix[j][j]
        for k in range(j):
            diagonal = code.sub(diagonal, code.mul(factor[j][k], factor[j][k]))
        if _is_constant(diagonal) and not diagonal > 0:
            raise ModelError(f'the joint-space inertia is singular at every configuration (pivot {j} is '
                             f'{diagonal!r}): a joint moves no mass and has no armature')
        factor[j][j] = code.call('sqrt', diagonal)
        reciprocal[j] = code.div(1.0, factor[j][j])
        for i in range(j + 1, n):
            entry = matrix[i][j]
            for k in range(j):
                entry = code.sub(entry, code.mul(factor[i][k], factor[j][k]))
            factor[i][j] = code.mul(entry, reciprocal[j])
    out = [0.0] * n
    for i in range(n):
        entry = rhs[i]
        for k in range(i):
            entry = code.sub(entry, code.mul(factor[i][k], out[k]))
        out[i] = code.mul(entry, reciprocal[i])
    for i in range(n - 1, -1, -1):
        entry = out[i]
        for k in range(i + 1, n):
            entry = code.sub(entry, code.mul(factor[k][i], out[k]))
        out[i] = code.mul(entry, reciprocal[i])
    return out


INDENT = ' ' * 8


def _kernel(name: str, doc: str, third: str, chain: _Chain, body) -> str:
    """A compiled function (scale, q, v, <third>, out, lanes): arrays of shape (n, lanes), one member per lane."""
    code = _Code(INDENT)
    n = chain.n
    values = {key: [code.let(f'{key}[{i}, b]') for i in range(n)] for key in ('scale', 'q', 'v', third)}
    outputs = body(code, values)
    for i, value in enumerate(outputs):
        code.lines.append(f'{INDENT}out[{i}, b] = {_term(value)}')
    return '\n'.join([f'@numba.njit(SIGNATURE, **COMPILED)',
                      f'def {name}(scale, q, v, {third}, out, lanes):',
                      f'    """{doc}"""',
                      '    for b in range(lanes):', *code.lines, ''])


def dynamics_source(chain) -> str:
    """The module of `chain`'s compiled forward and inverse dynamics (see the module's doc)."""
    constants = _Chain(chain)

    def forward(code, values):
        rotations, translations = _transforms(code, constants, values['q'])
        bias = _inverse_dynamics(code, constants, values['scale'], rotations, translations, values['v'],
                                 [0.0] * constants.n)
        mass_matrix = _joint_space_inertia(code, constants, values['scale'], rotations, translations)
        return _solve_spd(code, mass_matrix, [code.sub(x, y) for x, y in zip(values['torque'], bias)])

    def inverse(code, values):
        rotations, translations = _transforms(code, constants, values['q'])
        return _inverse_dynamics(code, constants, values['scale'], rotations, translations, values['v'],
                                 values['a'])

    header = '\n'.join([
        f'"""Generated by ddarm.physics.generated (version {GENERATOR_VERSION}) for a chain of {constants.n} '
        f'joints; do not edit."""',
        'import numba', 'import numpy as np', 'from ddarm.physics.dynamics import KERNEL_SIGNATURE as SIGNATURE', '',
        # Written out, not imported: numba's cache does not see the options, the file's hash must.
        f'COMPILED = {COMPILED!r}', '', ''])
    return header + '\n'.join([
        _kernel('forward_dynamics', 'q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque, link masses scaled by scale.',
                'torque', constants, forward), '',
        _kernel('inverse_dynamics', 'τ = M(q) a + V(q, q̇) + G(q), link masses scaled by scale.', 'a', constants,
                inverse)])
