"""The arm's dynamic parameters from recorded motion and torques: least squares on the joint-torque regressor.

Data: per sampling period, the state at its two ends and the torque held over it (the zero-order hold of every
ddarm episode). The dynamics are written at the period's midpoint, q̈ = (q̇_{n+1} − q̇_n)/Δ: a centred difference,
so zero-phase (no lag between the torque and the acceleration it causes), exact for the period's mean acceleration.
An optional zero-phase low-pass (Butterworth, filtered forwards and backwards) smooths measured noise first.

Two estimates. The base parameters (the combinations of φ the data can tell apart: ddarm.physics.regressor) by
ordinary least squares, with their standard deviations; they are what the data says. The full parameters written
to a URDF must be physically consistent (each link's pseudo-inertia positive definite: a positive mass, an inertia
positive definite at the centre of mass and within the triangle inequality; armature, damping and friction not
negative), which least squares alone does not give: they are fitted again with each link's pseudo-inertia
parametrised as U Uᵀ (U upper triangular, its diagonal exponentials: consistent by construction, Rucker and
Wensing's log-Cholesky parametrisation) and the joint parameters bounded at 0, the directions the data cannot see
held near the URDF's values by a small pull toward them. `Identification.constrained` says where that fit moved
away from the least-squares base estimate.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from ddarm.errors import DdarmError
from ddarm.physics.arm import ARMATURE_ELEMENT, ARMATURE_NAMESPACE, Arm, read_urdf
from ddarm.physics.regressor import (BASE_TOLERANCE, JOINT_PARAMETERS, LINK_PARAMETERS, base_columns,
                                     condition_number, parameter_names, parameters, stacked_regressor)

# Above this condition number of the (column-normalised) base regressor, the data cannot separate the base
# parameters: a relative torque error of 1e-3 becomes a parameter error of order one.
MAX_CONDITION = 1000.0
# A joint slower than this (rad/s, m/s) is at rest: there friction holds it with whatever torque it takes up to its
# level (stiction), not C sign(q̇), so those rows are left out of the fit. On the UR5 robot (frictionloss 0.2 to
# 1 N m) the damping and friction came out 5 to 30 % off with them, within 3.5 % at 0.02 rad/s, 1.7 % at 0.05.
REST_VELOCITY = 0.05
# Samples (periods) per base parameter at least: fewer leave the least squares without the redundancy that makes
# its standard deviations mean anything.
MIN_SAMPLES_PER_PARAMETER = 5
# The pull toward the URDF's values in the directions the data does not see, against the data's (each joint's
# torque scaled to RMS 1): where a constraint binds, it trades them no more than this.
PRIOR_WEIGHT = 1e-6
LINK_SIZE, JOINT_SIZE = len(LINK_PARAMETERS), len(JOINT_PARAMETERS)


class IdentificationError(DdarmError, ValueError):
    """Data that cannot identify the arm, or an identification that cannot be trusted."""


@dataclass(frozen=True)
class PeriodSamples:
    """Per sampling period: the midpoint state (q, q̇), the mean acceleration q̈ and the torque held over it."""

    q: np.ndarray
    v: np.ndarray
    a: np.ndarray
    torque: np.ndarray
    source: str = ''

    def __len__(self) -> int:
        return len(self.torque)


def period_samples(q, v, torque, period: float, source: str = '', cutoff: float | None = None) -> PeriodSamples:
    """The periods of one recording: q, v of samples 0 … K and the torque held over each of the K periods.

    `cutoff` (Hz, below the Nyquist frequency 1/(2Δ)): a 4th-order Butterworth low-pass run forwards and backwards
    (zero phase) over q, q̇ and the torque alike before the differences, for measured noise.
    """
    q, v, torque = (np.asarray(x, dtype=float) for x in (q, v, torque))
    if cutoff is not None:
        nyquist = 0.5 / period
        if not 0 < cutoff < nyquist:
            raise IdentificationError(f'the filter cutoff must be within (0, {nyquist:g}) Hz (the Nyquist frequency '
                                      f'of Δ = {period:g} s), got {cutoff!r}')
        # Imported here, not at the top: scipy.signal (with scipy.stats) took 0.4 s that every ddarm command, which
        # imports this module through its `identify`, waited at its start.
        import scipy.signal

        sections = scipy.signal.butter(4, cutoff / nyquist, output='sos')
        padding = 3 * 2 * len(sections) + 1  # sosfiltfilt's default, which needs more samples than this
        if len(q) <= padding:
            raise IdentificationError(f'{source}: {len(q)} samples are too few to filter ({padding + 1} at least)')
        q, v = (scipy.signal.sosfiltfilt(sections, x, axis=0) for x in (q, v))
        torque = scipy.signal.sosfiltfilt(sections, torque, axis=0)
    return PeriodSamples(q=0.5 * (q[:-1] + q[1:]), v=0.5 * (v[:-1] + v[1:]), a=(v[1:] - v[:-1]) / period,
                         torque=torque[:len(q) - 1], source=source)


def joined(recordings: list[PeriodSamples]) -> PeriodSamples:
    return PeriodSamples(*(np.vstack([getattr(r, name) for r in recordings]) for name in ('q', 'v', 'a', 'torque')),
                         source=', '.join(r.source for r in recordings))


# Pseudo-inertia J = [[Σ, h], [hᵀ, m]], Σ = ½ tr(Ī) 1 − Ī, of a link's ten parameters (m, h = m c, Ī about the frame's
# origin): J ≻ 0 exactly when some positive mass density has these parameters (Wensing, Kim and Slotine 2017).
def pseudo_inertia(link: np.ndarray) -> np.ndarray:
    m, h = link[0], link[1:4]
    xx, xy, yy, xz, yz, zz = link[4:]
    inertia = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    matrix = np.empty((4, 4))
    matrix[:3, :3] = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    matrix[:3, 3] = matrix[3, :3] = h
    matrix[3, 3] = m
    return matrix


def link_parameters(matrix: np.ndarray) -> np.ndarray:
    """The ten parameters of a pseudo-inertia (inverse of pseudo_inertia)."""
    sigma = matrix[:3, :3]
    inertia = np.trace(sigma) * np.eye(3) - sigma
    return np.array([matrix[3, 3], *matrix[:3, 3], inertia[0, 0], inertia[0, 1], inertia[1, 1], inertia[0, 2],
                     inertia[1, 2], inertia[2, 2]])


_UPPER = np.triu_indices(4, 1)


def _factor(theta: np.ndarray) -> np.ndarray:
    factor = np.diag(np.exp(theta[:4]))
    factor[_UPPER] = theta[4:]
    return factor


def _link_from_theta(theta: np.ndarray) -> np.ndarray:
    factor = _factor(theta)
    return link_parameters(factor @ factor.T)


def _theta_from_link(link: np.ndarray, floor: float) -> np.ndarray:
    """log-Cholesky coordinates of a link, its pseudo-inertia's eigenvalues raised to `floor` first where they are
    below it: the nearest consistent link (in the Frobenius norm) to one that is not, or to a massless or point-mass
    link of the URDF."""
    values, vectors = np.linalg.eigh(pseudo_inertia(link))
    matrix = (vectors * np.maximum(values, floor)) @ vectors.T
    flip = np.eye(4)[::-1]
    factor = flip @ np.linalg.cholesky(flip @ matrix @ flip) @ flip  # upper triangular U with U Uᵀ = J
    return np.concatenate([np.log(np.diag(factor)), factor[_UPPER]])


def consistency_problems(arm: Arm, phi: np.ndarray) -> list[str]:
    """What makes φ physically inconsistent, per link or joint parameter (empty: consistent)."""
    problems = []
    for i, joint in enumerate(arm.joint_names):
        values = np.linalg.eigvalsh(pseudo_inertia(phi[LINK_SIZE * i:LINK_SIZE * (i + 1)]))
        if values[0] <= 0:
            problems.append(f'the link of {joint}: pseudo-inertia not positive definite (eigenvalue {values[0]:.3g})')
    offset = LINK_SIZE * arm.dof
    for k, name in enumerate(JOINT_PARAMETERS):
        for i, joint in enumerate(arm.joint_names):
            value = phi[offset + k * arm.dof + i]
            if value < 0:
                problems.append(f'{joint}: {name} {value:.6g} < 0')
    return problems


@dataclass(frozen=True)
class Payload:
    """A point mass on a link, at a point of the link's frame: its mass identified, with its standard deviation."""

    link: str
    point: tuple[float, float, float]
    mass: float
    std: float


@dataclass(frozen=True)
class Identification:
    """What the data says (base estimate, with standard deviations) and the consistent parameters written."""

    joint_names: tuple[str, ...]
    names: tuple[str, ...]  # of φ's entries
    prior: np.ndarray  # φ of the URDF
    estimate: np.ndarray  # φ, physically consistent
    base: np.ndarray  # the columns of φ the base parameters are pivoted on
    base_estimate: np.ndarray  # least squares
    base_std: np.ndarray
    condition_number: float
    samples: int
    fit_residual: np.ndarray  # per joint, relative RMS of the torque the consistent estimate predicts, fit data
    base_residual: np.ndarray  # the same of the least-squares base estimate
    least_squares_problems: tuple[str, ...] = field(default=())  # what the unconstrained solution got wrong
    payload: Payload | None = None  # identify_payload's point mass

    def std_of(self, index: int) -> float | None:
        """The standard deviation of φ's entry `index` where it is a base parameter of its own, else None."""
        where = np.flatnonzero(self.base == index)
        return float(self.base_std[where[0]]) if len(where) else None


def _weights(torque: np.ndarray) -> np.ndarray:
    """Each joint's torque scale (RMS), so that a wrist of 1 N m counts as much as a shoulder of 80."""
    scale = np.sqrt(np.mean(torque ** 2, axis=0))
    return np.where(scale > 0, scale, 1.0)


def moving(data: PeriodSamples) -> np.ndarray:
    """Per sample and joint, whether the joint moves: |q̇| at least REST_VELOCITY."""
    return np.abs(data.v) >= REST_VELOCITY


def relative_residual(arm: Arm, phi: np.ndarray, data: PeriodSamples, moving_only: bool = True) -> np.ndarray:
    """Per joint, RMS(Y φ − τ) / RMS(τ) over the data: over the samples where the joint moves (`moving`), the ones
    the model describes, or over all of them."""
    predicted = (stacked_regressor(arm, data.q, data.v, data.a) @ phi).reshape(-1, arm.dof)
    counted = moving(data) if moving_only else np.ones_like(data.v, dtype=bool)
    errors = np.where(counted, predicted - data.torque, 0.0)
    torques = np.where(counted, data.torque, 0.0)
    count = np.maximum(np.sum(counted, axis=0), 1)
    scale = np.sqrt(np.sum(torques ** 2, axis=0) / count)
    return np.sqrt(np.sum(errors ** 2, axis=0) / count) / np.where(scale > 0, scale, 1.0)


def _fitted_rows(arm: Arm, data: PeriodSamples) -> tuple[np.ndarray, np.ndarray]:
    """The regressor's rows and the torques the fit takes: each joint's where it moves (`moving`), each scaled by
    its joint's torque RMS (`_weights`)."""
    weights = np.tile(_weights(data.torque), len(data))
    rows = moving(data).ravel()
    regressor = stacked_regressor(arm, data.q, data.v, data.a)
    return (regressor / weights[:, None])[rows], (data.torque.ravel() / weights)[rows]


def structural_base_count(arm: Arm, samples: int = 200) -> int:
    """How many base parameters the arm has: those of data that excites everything (random states, seeded)."""
    rng = np.random.default_rng(0)
    lower = np.where(np.isfinite(arm.lower), arm.lower, -np.pi)
    upper = np.where(np.isfinite(arm.upper), arm.upper, np.pi)
    q = rng.uniform(lower, upper, (samples, arm.dof))
    return len(base_columns(stacked_regressor(arm, q, *rng.uniform(-1.0, 1.0, (2, samples, arm.dof)))))


def identify(arm: Arm, data: PeriodSamples, max_condition: float = MAX_CONDITION) -> Identification:
    """Identify `arm`'s φ from the periods of `data`; IdentificationError if the data cannot (too few periods, too
    poorly excited)."""
    n = arm.dof
    if data.torque.shape[1:] != (n,):
        raise IdentificationError(f'the data has {data.torque.shape[1:]} torques per sample; the arm {n} joints')
    weighted, target = _fitted_rows(arm, data)
    columns = base_columns(weighted)
    structural = structural_base_count(arm)
    if len(columns) < structural:
        seen = set(parameter_names(arm)[column] for column in columns)
        unseen = [name for name in parameter_names(arm) if name.split('.')[1] in JOINT_PARAMETERS and name not in seen]
        raise IdentificationError(f'the data excites {len(columns)} of the arm\'s {structural} base parameters'
                                  + (f' (not {", ".join(unseen[:6])}{", …" if len(unseen) > 6 else ""})' if unseen
                                     else '') + ': record an excitation motion (ddarm motion --excite) that moves '
                                  'every joint, in both directions, with changing speed')
    if len(data) < MIN_SAMPLES_PER_PARAMETER * len(columns):
        raise IdentificationError(f'{len(data)} sampling periods are too few for the {len(columns)} parameters the '
                                  f'data can tell apart: record at least {MIN_SAMPLES_PER_PARAMETER * len(columns)} '
                                  '(a longer or a second excitation)')
    condition = condition_number(weighted, columns)
    if not condition <= max_condition:
        raise IdentificationError(f'the data excites the parameters poorly: the base regressor\'s condition number is '
                                  f'{condition:.4g}, above {max_condition:g}; record an excitation motion (ddarm motion '
                                  '--excite) that moves every joint, longer or with more harmonics')
    base = weighted[:, columns]
    base_estimate, *_ = np.linalg.lstsq(base, target, rcond=None)
    residual = target - base @ base_estimate
    variance = float(residual @ residual) / max(len(target) - len(columns), 1)
    base_std = np.sqrt(np.diag(variance * np.linalg.inv(base.T @ base)))
    # The least-squares solution nearest the URDF's: what the data says, completed by the prior where it is silent.
    prior = parameters(arm)
    least_squares = prior + np.linalg.lstsq(weighted, target - weighted @ prior, rcond=None)[0]
    estimate = _consistent_fit(arm, weighted, target, prior, least_squares)
    base_phi = np.zeros_like(prior)
    base_phi[columns] = base_estimate
    return Identification(
        joint_names=tuple(arm.joint_names), names=tuple(parameter_names(arm)), prior=prior, estimate=estimate,
        base=columns, base_estimate=base_estimate, base_std=base_std, condition_number=condition, samples=len(data),
        fit_residual=relative_residual(arm, estimate, data), base_residual=relative_residual(arm, base_phi, data),
        least_squares_problems=tuple(consistency_problems(arm, least_squares)))


def parameter_samples(arm: Arm, result: Identification, count: int, seed: int = 0) -> list[np.ndarray]:
    """`count` draws of φ within the identification's uncertainty: its base parameters from the normal
    distribution of their estimate and standard deviations (each drawn alone: their covariance is not kept), added
    to the written parameters' base entries, which moves the torques as the base parameters do. A draw that is not
    physically consistent is drawn again."""
    rng = np.random.default_rng(seed)
    samples = []
    while len(samples) < count:
        for _ in range(100):
            phi = result.estimate.copy()
            phi[result.base] += rng.normal(0.0, result.base_std)
            if not consistency_problems(arm, phi):
                samples.append(phi)
                break
        else:
            raise IdentificationError('no physically consistent parameters within the standard deviations in 100 '
                                      'draws: the identification is too uncertain to sample')
    return samples


def point_mass_parameters(arm: Arm, link: str, point) -> tuple[int, np.ndarray]:
    """The controlled joint (0-based) that moves `link`, and the ten parameters per kilogram of a point mass at
    `point` of the link's frame, in that joint's frame."""
    model = arm.model
    if not model.existFrame(link, pin.FrameType.BODY):
        raise IdentificationError(f'the payload\'s link {link!r} is not a link of {arm.urdf_path}')
    frame = model.frames[model.getFrameId(link, pin.FrameType.BODY)]
    if frame.parentJoint == 0:
        raise IdentificationError(f'the payload\'s link {link!r} is fixed to the base: no joint moves it')
    x, y, z = frame.placement.act(np.asarray(point, dtype=float))
    return frame.parentJoint - 1, np.array([1.0, x, y, z, y * y + z * z, -x * y, x * x + z * z, -x * z, -y * z,
                                            x * x + y * y])


def identify_payload(arm: Arm, data: PeriodSamples, link: str, point, max_condition: float = MAX_CONDITION
                     ) -> Identification:
    """The URDF's links taken as they are, a payload of unknown mass at a known point of `link`, and each joint's
    armature, damping and friction: a small least squares (masses and parameters >= 0) in which all of these are
    identifiable, unlike a link's own mass (identify). IdentificationError as identify."""
    n = arm.dof
    joint, per_kilogram = point_mass_parameters(arm, link, point)
    prior = parameters(arm)
    weighted, target = _fitted_rows(arm, data)
    links = LINK_SIZE * n
    target = target - weighted[:, :links] @ prior[:links]
    columns = np.column_stack([weighted[:, links:], weighted[:, LINK_SIZE * joint:LINK_SIZE * (joint + 1)]
                               @ per_kilogram])
    if len(data) < MIN_SAMPLES_PER_PARAMETER * columns.shape[1]:
        raise IdentificationError(f'{len(data)} sampling periods are too few for the {columns.shape[1]} parameters: '
                                  f'record at least {MIN_SAMPLES_PER_PARAMETER * columns.shape[1]}')
    excited = np.linalg.norm(columns, axis=0) > BASE_TOLERANCE * np.max(np.linalg.norm(columns, axis=0))
    names = [*parameter_names(arm)[links:], f'payload on {link}']
    if not excited.all():
        raise IdentificationError(f'the data does not excite {[name for name, e in zip(names, excited) if not e]}: '
                                  'record an excitation motion (ddarm motion --excite) that moves every joint')
    condition = float(np.linalg.cond(columns / np.linalg.norm(columns, axis=0)))
    if not condition <= max_condition:
        raise IdentificationError(f'the data excites the parameters poorly: condition number {condition:.4g}, above '
                                  f'{max_condition:g}; record an excitation motion (ddarm motion --excite)')
    free, *_ = np.linalg.lstsq(columns, target, rcond=None)
    residual = target - columns @ free
    variance = float(residual @ residual) / max(len(target) - columns.shape[1], 1)
    std = np.sqrt(np.diag(variance * np.linalg.inv(columns.T @ columns)))
    import scipy.optimize  # see period_samples: 0.3 s that every ddarm command waited for

    bounded = scipy.optimize.lsq_linear(columns, target, bounds=(0.0, np.inf)).x
    estimate = prior.copy()
    estimate[links:] = bounded[:-1]
    estimate[LINK_SIZE * joint:LINK_SIZE * (joint + 1)] += bounded[-1] * per_kilogram
    unbounded = prior.copy()
    unbounded[links:] = free[:-1]
    unbounded[LINK_SIZE * joint:LINK_SIZE * (joint + 1)] += free[-1] * per_kilogram
    problems = [f'{name} {value:.6g} < 0' for name, value in zip(names, free) if value < 0]
    return Identification(
        joint_names=tuple(arm.joint_names), names=tuple(parameter_names(arm)), prior=prior, estimate=estimate,
        base=np.arange(links, len(prior)), base_estimate=free[:-1], base_std=std[:-1], condition_number=condition,
        samples=len(data), fit_residual=relative_residual(arm, estimate, data),
        base_residual=relative_residual(arm, unbounded, data), least_squares_problems=tuple(problems),
        payload=Payload(link, tuple(float(x) for x in point), float(bounded[-1]), float(std[-1])))


def _consistent_fit(arm: Arm, weighted: np.ndarray, target: np.ndarray, prior: np.ndarray,
                    start: np.ndarray) -> np.ndarray:
    """The physically consistent φ that best fits the data, pulled toward `prior` where the data is silent."""
    n = arm.dof
    links = LINK_SIZE * n
    scale = np.maximum(np.abs(prior), 1e-3 * max(1.0, float(np.max(np.abs(prior)))))
    # ‖W φ − t‖² = ‖R φ − Qᵀ t‖² + a constant (W = Q R): the same fit on p rows instead of one per sample and joint.
    orthogonal, weighted = np.linalg.qr(weighted)
    target = orthogonal.T @ target
    # The pull acts in the directions the data does not see alone (W's null space, in parameters scaled by the
    # URDF's): it fixes them without moving what the data says.
    _, singular, directions = np.linalg.svd(weighted * scale)
    unseen = directions[singular <= BASE_TOLERANCE * singular[0]]
    pull = np.sqrt(PRIOR_WEIGHT)

    def phi(x):
        return np.concatenate([*(_link_from_theta(x[LINK_SIZE * i:LINK_SIZE * (i + 1)]) for i in range(n)),
                               x[links:]])

    def residuals(x):
        value = phi(x)
        return np.concatenate([weighted @ value - target, pull * unseen @ ((value - prior) / scale)])

    def jacobian(x):
        derivative = np.zeros((len(prior), len(x)))
        for i in range(n):
            block = slice(LINK_SIZE * i, LINK_SIZE * (i + 1))
            theta, base = x[block], _link_from_theta(x[block])
            for k in range(LINK_SIZE):
                step = 1e-7 * max(1.0, abs(theta[k]))
                moved = theta.copy()
                moved[k] += step
                derivative[block, LINK_SIZE * i + k] = (_link_from_theta(moved) - base) / step
        derivative[links:, links:] = np.eye(len(x) - links)
        return np.vstack([weighted @ derivative, pull * unseen @ (derivative / scale[:, None])])

    # From the least-squares solution made consistent (its links' pseudo-inertias projected onto the positive
    # definite ones, the joint parameters onto >= 0): near the data's optimum, so few iterations move it back.
    floors = [1e-6 * max(float(np.max(np.abs(pseudo_inertia(prior[LINK_SIZE * i:LINK_SIZE * (i + 1)])))), 1e-6)
              for i in range(n)]
    initial = np.concatenate([*(_theta_from_link(start[LINK_SIZE * i:LINK_SIZE * (i + 1)], floors[i])
                                for i in range(n)), np.maximum(start[links:], 0.0)])
    lower = np.concatenate([np.full(links, -np.inf), np.zeros(len(prior) - links)])
    import scipy.optimize  # see period_samples

    fit = scipy.optimize.least_squares(residuals, initial, jac=jacobian, bounds=(lower, np.inf), max_nfev=100)
    return phi(fit.x)


def link_inertia(phi: np.ndarray, joint: int) -> pin.Inertia:
    """The composite body that joint `joint` (0-based) moves, as a pin.Inertia in its joint's frame."""
    return pin.Inertia.FromDynamicParameters(phi[LINK_SIZE * joint:LINK_SIZE * (joint + 1)])


def joint_parameters(phi: np.ndarray, dof: int) -> dict[str, np.ndarray]:
    """Armature, damping and friction per joint."""
    offset = LINK_SIZE * dof
    return {name: phi[offset + k * dof:offset + (k + 1) * dof] for k, name in enumerate(JOINT_PARAMETERS)}


def identified_urdf(arm: Arm, phi: np.ndarray, header: str) -> str:
    """The arm's URDF carrying φ: each controlled joint's composite body as its child link's <inertial> (the other
    links it moves, fixed to it or beyond a locked joint, left without one: their inertia is in the composite),
    its <dynamics damping friction> and its <ddarm:armature>. `header` goes first, as a comment."""
    description = read_urdf(arm.urdf_path)
    root = ElementTree.fromstring(description.text)
    root.set(f'xmlns:{ARMATURE_ELEMENT.split(":")[0]}', ARMATURE_NAMESPACE)
    links = {element.get('name'): element for element in root.findall('link')}
    joints = {element.get('name'): element for element in root.findall('joint')}
    model = arm.model
    parameters_of = joint_parameters(phi, arm.dof)
    for index, name in enumerate(arm.joint_names):
        child = description.joints[name].child
        carried = [frame.name for frame in model.frames
                   if frame.type == pin.FrameType.BODY and frame.parentJoint == index + 1]
        for link in carried:
            for inertial in links[link].findall('inertial'):
                links[link].remove(inertial)
        links[child].append(_inertial_element(link_inertia(phi, index)))
        joint = joints[name]
        for tag in ('dynamics', ARMATURE_ELEMENT):
            for element in joint.findall(tag):
                joint.remove(element)
        ElementTree.SubElement(joint, 'dynamics', damping=repr(float(parameters_of['damping'][index])),
                               friction=repr(float(parameters_of['friction'][index])))
        ElementTree.SubElement(joint, ARMATURE_ELEMENT, value=repr(float(parameters_of['armature'][index])))
    ElementTree.indent(root, space='  ')
    comment = header.replace('--', '- -')  # an XML comment may not hold two hyphens in a row
    return f'<?xml version="1.0"?>\n<!--\n{comment}\n-->\n{ElementTree.tostring(root, encoding="unicode")}\n'


def _inertial_element(inertia: pin.Inertia) -> ElementTree.Element:
    element = ElementTree.Element('inertial')
    ElementTree.SubElement(element, 'origin', xyz=' '.join(repr(float(x)) for x in inertia.lever), rpy='0 0 0')
    ElementTree.SubElement(element, 'mass', value=repr(float(inertia.mass)))
    moments = inertia.inertia
    ElementTree.SubElement(element, 'inertia', **{key: repr(float(moments[i, j])) for key, (i, j) in (
        ('ixx', (0, 0)), ('ixy', (0, 1)), ('ixz', (0, 2)), ('iyy', (1, 1)), ('iyz', (1, 2)), ('izz', (2, 2)))})
    return element
