"""The dynamics of one arm as generated code: RNEA, CRBA and Cholesky unrolled for its chain, or looped beyond
UNROLLED_JOINTS joints.

The chain's constants (axes, placements, masses, inertias) are written into the code, and every
product with an exact 0 or ±1 among them is left out while writing it: a joint about z needs no
Rodrigues formula, a link with its centre of mass on an axis no full cross product. What is left
is the same algorithm as Pinocchio's rnea, crba and a Cholesky solve, evaluated in the same order,
per member ("lane") of a chunk, with every intermediate a local variable that the compiler keeps
in registers. Why generate our own: no library writes numba code from a Pinocchio model, and
Pinocchio's own code generation needs its CasADi or CppAD build, which PyPI's `pin` is not. A chain of more than
UNROLLED_JOINTS joints gets the same algorithms as loops over its joints reading its constants from arrays, so
that code size and compile time grow linearly with the joint count (up to dynamics.MAX_JOINTS).

Each model's code is a module in the user's cache folder named by the hash of the chain and of
this generator, compiled by numba once and cached there (ddarm.physics.dynamics loads it).
"""

from __future__ import annotations

import math

import numpy as np

from ddarm.physics.arm import ModelError
from ddarm.physics.dynamics import COMPILED, REVOLUTE, check_joint_count

# Part of every module's hash: a change to what is generated must change it.
GENERATOR_VERSION = 3


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


# The members a kernel evaluates together in blocks, one AVX-512 vector of doubles (two AVX vectors).
VECTOR_LANES = 8
# Up to this many joints the kernels loop over the arguments' lanes directly, and LLVM vectorises that loop.
DIRECT_JOINTS = 5


def _in_blocks(n: int) -> bool:
    """Whether a chain of n joints has its lanes run in blocks on the stack (see _kernel), importing stack_buffer."""
    return DIRECT_JOINTS < n <= UNROLLED_JOINTS


def _kernel(name: str, doc: str, third: str, chain: _Chain, body) -> str:
    """A compiled function (scale, q, v, <third>, out, lanes): arrays of shape (n, lanes), one member per lane.

    LLVM vectorises a loop across lanes only if it can rule out at run time that the loop's stores overlap its
    loads. Over the arguments themselves every row is a pointer of its own, and beyond DIRECT_JOINTS joints it gives
    up ("too many memory checks needed": 24 rows read and 6 written on the UR5). There the lanes run in blocks of
    VECTOR_LANES, each block's inputs copied to a buffer on the stack at constant offsets, which overlaps no
    argument, and its results copied back. Measured per member of 64, forward dynamics: UR5 0.20 µs direct, 0.09 µs
    in blocks; Panda 0.34 µs, 0.13 µs; a Panda member alone 0.38 µs, 0.43 µs. On the arms LLVM vectorises directly,
    the copies would cost a third more (paper's arm 29 ns, 38 ns in blocks).
    """
    n = chain.n
    keys = ('scale', 'q', 'v', third)
    header = ['@generated_kernel(COMPILED)', f'def {name}(scale, q, v, {third}, out, lanes):', f'    """{doc}"""']
    if not _in_blocks(n):
        code = _Code(INDENT)
        values = {key: [code.let(f'{key}[{i}, b]') for i in range(n)] for key in keys}
        code.lines += [f'{INDENT}out[{i}, b] = {_term(value)}' for i, value in enumerate(body(code, values))]
        return '\n'.join([*header, '    for b in range(lanes):', *code.lines, ''])
    indent, width = ' ' * 12, VECTOR_LANES
    code = _Code(indent)
    values = {key: [code.let(f'inputs[{(k * n + i) * width} + j]') for i in range(n)] for k, key in enumerate(keys)}
    code.lines += [f'{indent}result[{i * width} + j] = {_term(value)}' for i, value in enumerate(body(code, values))]
    size = len(keys) * n * width
    return '\n'.join([*header,
                      f'    inputs = numba.carray(stack_buffer({size}), {size})',
                      f'    result = numba.carray(stack_buffer({n * width}), {n * width})',
                      f'    for start in range(0, lanes, {width}):',
                      f'        block = min({width}, lanes - start)',
                      *_copies(f'inputs[{{}} + i * {width} + j] = {{}}[i, start + j]', n,
                               [(k * n * width, key) for k, key in enumerate(keys)]),
                      '        for j in range(block):', *code.lines,
                      *_copies(f'out[i, start + j] = result[i * {width} + j]', n, [()]), ''])


def _copies(line: str, n: int, fills: list) -> list[str]:
    """The loops copying a block's rows: over a constant count of lanes for a whole block, which LLVM turns into
    vector moves (Panda, forward dynamics per member of 64: 0.126 µs, against 0.140 µs copied lane by lane)."""
    def loop(count) -> list[str]:
        return [f'            for i in range({n}):', f'                for j in range({count}):',
                *(f'                    {line.format(*fill)}' for fill in fills)]
    return [f'        if block == {VECTOR_LANES}:', *loop(VECTOR_LANES), '        else:', *loop('block')]


def _unrolled(constants: _Chain) -> str:
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

    return '\n'.join([
        _kernel('forward_dynamics', 'q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque, link masses scaled by scale.',
                'torque', constants, forward), '',
        _kernel('inverse_dynamics', 'τ = M(q) a + V(q, q̇) + G(q), link masses scaled by scale.', 'a', constants,
                inverse)])


# Beyond this many joints the kernels loop over the joints and read the chain's constants from arrays: unrolled
# code grows as n·depth (CRBA) to n³ (Cholesky) lines, numba's compile time and memory faster still (30 joints:
# 750 kB, 49 s; 200: past 11 GB), while the looped module is the same code for every chain plus its constants,
# a few hundred bytes a joint. Every example arm (at most 7 joints) is unrolled.
UNROLLED_JOINTS = 8

# The kernels for any chain: the unrolled code's algorithms, step by step as _transforms, _inverse_dynamics,
# _joint_space_inertia and _solve_spd write them, with every product computed. The module defines N, the chain's
# arrays and REVOLUTE before them. Vectors are tuples, which numba keeps in registers. A chain singular at every
# configuration is not found while writing them, as the unrolled code's constant pivots are: its zero pivot gives
# NaN, which the divergence check sees (and Arm.from_urdf refuses such a URDF first).
_LOOPED_KERNELS = '''
PART = {**COMPILED, 'cache': False}  # compiled into the kernels that call them, and cached with them


@numba.njit(**PART)
def add(a, b):
    return a[0] + b[0], a[1] + b[1], a[2] + b[2]


@numba.njit(**PART)
def sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@numba.njit(**PART)
def scaled(s, a):
    return s * a[0], s * a[1], s * a[2]


@numba.njit(**PART)
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@numba.njit(**PART)
def cross(a, b):
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


@numba.njit(**PART)
def row(matrix, i):
    return matrix[i, 0], matrix[i, 1], matrix[i, 2]


@numba.njit(**PART)
def times(rotation, x):
    return dot(row(rotation, 0), x), dot(row(rotation, 1), x), dot(row(rotation, 2), x)


@numba.njit(**PART)
def scaled_times(matrix, s, x):
    """(s matrix) x, each entry of the matrix scaled first."""
    return (dot((matrix[0, 0] * s, matrix[0, 1] * s, matrix[0, 2] * s), x),
            dot((matrix[1, 0] * s, matrix[1, 1] * s, matrix[1, 2] * s), x),
            dot((matrix[2, 0] * s, matrix[2, 1] * s, matrix[2, 2] * s), x))


@numba.njit(**PART)
def transposed_times(rotation, x):
    return (dot((rotation[0, 0], rotation[1, 0], rotation[2, 0]), x),
            dot((rotation[0, 1], rotation[1, 1], rotation[2, 1]), x),
            dot((rotation[0, 2], rotation[1, 2], rotation[2, 2]), x))


@numba.njit(**PART)
def to_parent(rotation, translation, f, n):
    """A force (f, n) at a joint's frame expressed at its parent's: R f, R n + t × R f."""
    g = times(rotation, f)
    return g, add(times(rotation, n), cross(translation, g))


@numba.njit(**PART)
def transforms(q, b, rotation, translation):
    """liMi = jointPlacement · X_J(q_i) per joint of lane b: child-to-parent rotation and translation."""
    for i in range(N):
        placement, t, axis = PLACEMENT_ROTATION[i], PLACEMENT_TRANSLATION[i], AXIS[i]
        if KIND[i] == REVOLUTE:
            c, s = np.cos(q[i, b]), np.sin(q[i, b])
            k = 1.0 - c
            x, y, z = axis[0], axis[1], axis[2]
            joint = ((c + k * (x * x), k * (x * y) - s * z, k * (x * z) + s * y),
                     (k * (x * y) + s * z, c + k * (y * y), k * (y * z) - s * x),
                     (k * (x * z) - s * y, k * (y * z) + s * x, c + k * (z * z)))
            for r in range(3):
                for col in range(3):
                    rotation[i, r, col] = dot(row(placement, r), (joint[0][col], joint[1][col], joint[2][col]))
                translation[i, r] = t[r]
        else:
            moved = scaled(q[i, b], times(placement, (axis[0], axis[1], axis[2])))
            for r in range(3):
                for col in range(3):
                    rotation[i, r, col] = placement[r, col]
                translation[i, r] = t[r] + moved[r]


@numba.njit(**PART)
def rnea(scale, v, a, b, rotation, translation, motion, force, tau):
    """τ = M(q) a + V(q, q̇) + G(q) of lane b into tau: recursive Newton-Euler in each joint's frame, as
    Pinocchio's rnea; motion[i] holds joint i's spin, velocity and their rates, force[i] its force and moment."""
    for i in range(N):
        p = PARENT[i]
        if p < 0:
            pw, pl, pdw = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
            pdl = (-GRAVITY[0], -GRAVITY[1], -GRAVITY[2])
        else:
            pw, pl, pdw, pdl = row(motion[p], 0), row(motion[p], 1), row(motion[p], 2), row(motion[p], 3)
        r, t, axis = rotation[i], row(translation, i), row(AXIS, i)
        w = transposed_times(r, pw)
        lin = transposed_times(r, sub(pl, cross(t, pw)))
        dw = transposed_times(r, pdw)
        dl = transposed_times(r, sub(pdl, cross(t, pdw)))
        joint_motion = scaled(v[i, b], axis)
        if KIND[i] == REVOLUTE:
            w = add(w, joint_motion)
            dw = add(dw, add(scaled(a[i, b], axis), cross(w, joint_motion)))
            dl = add(dl, cross(lin, joint_motion))
        else:
            lin = add(lin, joint_motion)
            dl = add(dl, add(scaled(a[i, b], axis), cross(w, joint_motion)))
        for k in range(3):
            motion[i, 0, k], motion[i, 1, k], motion[i, 2, k], motion[i, 3, k] = w[k], lin[k], dw[k], dl[k]
        m = MASS[i] * scale[i, b]
        c = row(LEVER, i)
        hv = scaled(m, sub(lin, cross(c, w)))
        nv = add(scaled_times(INERTIA[i], scale[i, b], w), cross(c, hv))
        ha = scaled(m, sub(dl, cross(c, dw)))
        na = add(scaled_times(INERTIA[i], scale[i, b], dw), cross(c, ha))
        f, n = add(ha, cross(w, hv)), add(add(na, cross(w, nv)), cross(lin, hv))
        for k in range(3):
            force[i, 0, k], force[i, 1, k] = f[k], n[k]
    for i in range(N - 1, -1, -1):
        p = PARENT[i]
        f, n = row(force[i], 0), row(force[i], 1)
        tau[i] = dot(row(AXIS, i), n if KIND[i] == REVOLUTE else f) + ARMATURE[i] * a[i, b]
        if p >= 0:
            g, e = to_parent(rotation[i], row(translation, i), f, n)
            for k in range(3):
                force[p, 0, k] += g[k]
                force[p, 1, k] += e[k]


@numba.njit(**PART)
def crba(scale, b, rotation, translation, composite, inner, mass_matrix):
    """M(q) of lane b, both triangles: the composite-rigid-body algorithm, as Pinocchio's crba; composite[i] holds
    link i's composite mass, first moment h = m c and inertia about the joint frame's origin, as rows 0 to 4;
    inner is a 3x3 scratch."""
    mass_matrix[:, :] = 0.0  # a tree's joints on different branches do not couple
    for i in range(N):
        m = MASS[i] * scale[i, b]
        c = row(LEVER, i)
        cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        h = scaled(m, c)
        composite[i, 0, 0] = m
        for r in range(3):
            composite[i, 1, r] = h[r]
            for col in range(3):
                composite[i, 2 + r, col] = (INERTIA[i, r, col] * scale[i, b] - m * (c[r] * c[col])
                                            + (m * cc if r == col else 0.0))
    for i in range(N - 1, -1, -1):
        p, axis = PARENT[i], row(AXIS, i)
        m, h, inertia = composite[i, 0, 0], row(composite[i], 1), composite[i, 2:]
        if KIND[i] == REVOLUTE:
            f, n = cross(axis, h), times(inertia, axis)
            mass_matrix[i, i] = dot(axis, n) + ARMATURE[i]
        else:
            f, n = scaled(m, axis), cross(h, axis)
            mass_matrix[i, i] = dot(axis, f) + ARMATURE[i]
        j = i
        while PARENT[j] >= 0:
            f, n = to_parent(rotation[j], row(translation, j), f, n)
            j = PARENT[j]
            mass_matrix[j, i] = mass_matrix[i, j] = dot(row(AXIS, j), n if KIND[j] == REVOLUTE else f)
        if p >= 0:
            r, t = rotation[i], row(translation, i)
            g = times(r, h)
            composite[p, 0, 0] += m
            moment = add(g, scaled(m, t))
            for k in range(3):
                composite[p, 1, k] += moment[k]
            # R I Rᵀ + (2 t·Rh + m |t|²) 1 - t (Rh)ᵀ - (Rh) tᵀ - m t tᵀ, for the symmetric I.
            for k in range(3):
                for col in range(3):
                    inner[k, col] = dot(row(inertia, k), row(r, col))  # I Rᵀ
            shift = 2.0 * dot(t, g) + m * dot(t, t)
            for k in range(3):
                for col in range(k, 3):
                    rotated = dot(row(r, k), (inner[0, col], inner[1, col], inner[2, col]))
                    entry = rotated - (t[k] * g[col] + g[k] * t[col] + m * (t[k] * t[col]))
                    if k == col:
                        entry += shift
                    composite[p, 2 + k, col] += entry
                    if k != col:
                        composite[p, 2 + col, k] = composite[p, 2 + k, col]


@numba.njit(**PART)
def solve_spd(matrix, rhs, factor, reciprocal, x):
    """matrix⁻¹ rhs into x for a symmetric positive definite matrix: Cholesky (matrix = L Lᵀ), then the two
    triangular solves, each division by a diagonal entry done as a product with its reciprocal."""
    for j in range(N):
        diagonal = matrix[j, j]
        for k in range(j):
            diagonal -= factor[j, k] * factor[j, k]
        factor[j, j] = np.sqrt(diagonal)
        reciprocal[j] = 1.0 / factor[j, j]
        for i in range(j + 1, N):
            entry = matrix[i, j]
            for k in range(j):
                entry -= factor[i, k] * factor[j, k]
            factor[i, j] = entry * reciprocal[j]
    for i in range(N):
        entry = rhs[i]
        for k in range(i):
            entry -= factor[i, k] * x[k]
        x[i] = entry * reciprocal[i]
    for i in range(N - 1, -1, -1):
        entry = x[i]
        for k in range(i + 1, N):
            entry -= factor[k, i] * x[k]
        x[i] = entry * reciprocal[i]


@generated_kernel(COMPILED)
def forward_dynamics(scale, q, v, torque, out, lanes):
    """q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque, link masses scaled by scale."""
    rotation, translation = np.empty((N, 3, 3)), np.empty((N, 3))
    motion, force, bias = np.empty((N, 4, 3)), np.empty((N, 2, 3)), np.empty(N)
    composite, inner, mass_matrix = np.empty((N, 5, 3)), np.empty((3, 3)), np.empty((N, N))
    rhs, factor, reciprocal, acceleration = np.empty(N), np.zeros((N, N)), np.empty(N), np.empty(N)
    zero = np.zeros((N, lanes))
    for b in range(lanes):
        transforms(q, b, rotation, translation)
        rnea(scale, v, zero, b, rotation, translation, motion, force, bias)
        crba(scale, b, rotation, translation, composite, inner, mass_matrix)
        for i in range(N):
            rhs[i] = torque[i, b] - bias[i]
        solve_spd(mass_matrix, rhs, factor, reciprocal, acceleration)
        out[:, b] = acceleration


@generated_kernel(COMPILED)
def inverse_dynamics(scale, q, v, a, out, lanes):
    """τ = M(q) a + V(q, q̇) + G(q), link masses scaled by scale."""
    rotation, translation = np.empty((N, 3, 3)), np.empty((N, 3))
    motion, force, tau = np.empty((N, 4, 3)), np.empty((N, 2, 3)), np.empty(N)
    for b in range(lanes):
        transforms(q, b, rotation, translation)
        rnea(scale, v, a, b, rotation, translation, motion, force, tau)
        out[:, b] = tau
'''


def _array(values, dtype: str = 'np.float64') -> str:
    return f'np.array({np.asarray(values).tolist()!r}, dtype={dtype})'


def _looped(chain, constants: _Chain) -> str:
    return '\n'.join([
        f'N = {constants.n}', f'REVOLUTE = {REVOLUTE}',
        f'PARENT = {_array(chain.parent, "np.int64")}', f'KIND = {_array(chain.kind, "np.int64")}',
        f'AXIS = {_array(constants.axis)}', f'PLACEMENT_ROTATION = {_array(constants.placement_rotation)}',
        f'PLACEMENT_TRANSLATION = {_array(constants.placement_translation)}', f'MASS = {_array(constants.mass)}',
        f'LEVER = {_array(constants.lever)}', f'INERTIA = {_array(constants.inertia)}',
        f'ARMATURE = {_array(constants.armature)}', f'GRAVITY = {_array(constants.gravity)}', '',
        _LOOPED_KERNELS])


def dynamics_source(chain) -> str:
    """The module of `chain`'s compiled forward and inverse dynamics (see the module's doc): unrolled up to
    UNROLLED_JOINTS joints, looped beyond, refused beyond MAX_JOINTS before anything is written."""
    check_joint_count(len(chain.parent))
    constants = _Chain(chain)
    looped = constants.n > UNROLLED_JOINTS
    blocks = _in_blocks(constants.n)
    header = '\n'.join([
        f'"""Generated by ddarm.physics.generated (version {GENERATOR_VERSION}) for a chain of {constants.n} '
        f'joints; do not edit."""',
        *(['import numba'] if looped or blocks else []), 'import numpy as np',
        f'from ddarm.physics.dynamics import generated_kernel{", stack_buffer" if blocks else ""}', '',
        # Written out, not imported: numba's cache does not see the options, the file's hash must.
        f'COMPILED = {COMPILED!r}', '', ''])
    return header + (_looped(chain, constants) if looped else _unrolled(constants))
