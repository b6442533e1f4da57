"""The exact stability boundary of the sampled loop: zero-order hold, a d-sample delay, the ω rule with damping ζ.

Per mode, a double integrator ë = u with u(t) = -(k_p e + k_v ė)(t_{n-d}) held over [t_n, t_{n+1}). With
x = (e, ė), the exact discretisation is x_{n+1} = A x_n - b k x_{n-d}, A = [[1, Δ], [0, 1]], b = (Δ²/2, Δ)ᵀ,
k = (k_p, k_v), and det(z^d (z I - A) + b k) = z^d p(z): under k_p = ω², k_v = 2ζω and with w = ωΔ,

    p(z) = z^d (z - 1)² + (w²/2)(z + 1) + 2ζw (z - 1),

of degree d + 2 (the other d roots of the 2(d + 1) state's transition matrix are at z = 0). For small w > 0
every root is inside the unit circle (the double root at 1 moves to 1 + w(-ζ ± √(ζ² - 1)), the d at 0 to
|z| ~ (2ζw)^{1/d}), so the boundary ωΔ* is the smallest w > 0 at which a root reaches |z| = 1.

On z = e^{iθ}, θ = π - s, p e^{-iθ/2} = w² sin(s/2) + 4iζw cos(s/2) - 4 cos²(s/2) e^{i(d + 1/2)θ}: real w
solves its imaginary part, w(s) = (-1)^d cos(s/2) cos((d + 1/2) s) / ζ, and its real part then holds where

    g(s) = cos²((d + 1/2) s) - 4ζ² (-1)^d D_d(s) = 0,   D_d(s) = sin((d + 1/2) s) / sin(s/2) = 1 + 2 Σ_{k ≤ d} cos ks,

or at s = 0 (z = -1, for any w: the real part vanishes there), where w = (-1)^d / ζ, positive for even d. g is
a Chebyshev series of degree 2d + 1 in cos s, so its critical points split [0, π] into pieces on which g is
monotone: each sign change there holds one root, found by brentq. A pair of roots of p that only touches the
circle (g has a double root; only at isolated ζ) leaves the loop stable on both sides and is no boundary.
"""

from __future__ import annotations

import numpy as np
from numpy.polynomial import chebyshev

from ddarm.errors import DdarmError

# scipy.linalg and scipy.optimize are imported where they are used: every node process imports this module (through
# ddarm.episodes.spec) and never calls them, and importing them added 0.26 s to each node's start.


# The damping ratios whose boundary keeps its printed digits: below, the crossing near z = -1 lies closer to θ = π
# than brentq resolves in θ (ωΔ* ≈ 4ζ for d = 0); far above, ζ² overflows.
ZETA_RANGE = (1e-6, 1e6)


# The linearised coupled loop's state count above which its eigenvalues are not computed: a dense eigensolve of this
# size takes a few seconds; an arm of hundreds of joints under a long delay would take many minutes.
MAX_LOOP_STATES = 2000
# |z| above which a root of the linearised loop counts as growing: eigenvalues are computed to about 1e-12 here.
GROWING = 1.0 + 1e-9


class StabilityError(DdarmError, ValueError):
    """A delay, damping, period or arm the stability boundary cannot be computed for."""


def _checked_delay(delay) -> int:
    if isinstance(delay, bool) or not isinstance(delay, (int, np.integer)) or delay < 0:
        raise StabilityError(f'delay must be a whole number of samples >= 0, got {delay!r}')
    return int(delay)


def _checked(delay, zeta) -> tuple[int, float]:
    delay = _checked_delay(delay)
    if not (np.isfinite(zeta) and ZETA_RANGE[0] <= zeta <= ZETA_RANGE[1]):
        raise StabilityError(f'zeta must be within [{ZETA_RANGE[0]:g}, {ZETA_RANGE[1]:g}], got {float(zeta):g}')
    return delay, float(zeta)


def boundary_omega_delta(delay: int, zeta: float) -> float:
    """ωΔ*: the loop with k_p = ω², k_v = 2ζω, delay d and period Δ is stable for ωΔ < ωΔ* and not at ωΔ*.

    Dimensionless (only ωΔ enters p(z)); for d = 0 it is min(1/ζ, 4ζ). See the module's docstring.
    """
    delay, zeta = _checked(delay, zeta)
    sign = (-1) ** delay
    # g in the Chebyshev basis of y = cos s: cos² = (T_0 + T_{2d+1}) / 2, D_d = T_0 + 2 (T_1 + … + T_d).
    series = np.zeros(2 * delay + 2)
    series[0] = 0.5 - 4.0 * zeta**2 * sign
    series[1:delay + 1] = -8.0 * zeta**2 * sign
    series[-1] += 0.5
    turning = chebyshev.chebroots(chebyshev.chebder(series))
    turning = turning[np.abs(turning.imag) < 1e-9].real
    edges = np.unique(np.concatenate([[0.0, np.pi], np.arccos(np.clip(turning, -1.0, 1.0))]))
    half = delay + 0.5

    def crossing(s: float) -> float:
        dirichlet = 2 * delay + 1 if s == 0 else np.sin(half * s) / np.sin(s / 2)
        return np.cos(half * s) ** 2 - 4.0 * zeta**2 * sign * dirichlet

    from scipy.optimize import brentq

    values = [crossing(s) for s in edges]
    crossings = [1.0 / zeta] if sign > 0 else []  # z = -1
    for low, high, at_low, at_high in zip(edges[:-1], edges[1:], values[:-1], values[1:]):
        if at_low * at_high < 0:
            s = brentq(crossing, low, high, xtol=1e-15, rtol=4 * np.finfo(float).eps)
            crossings.append(sign * np.cos(s / 2) * np.cos(half * s) / zeta)
    # Not empty: as w grows, all roots of p but the one tending to -1 go to infinity.
    return float(min(w for w in crossings if w > 0))


def boundary_omega(period: float, delay: int, zeta: float) -> float:
    """ω* = ωΔ*/Δ in rad/s: the largest stable ω of the ω rule with damping ζ, sampled at `period` Δ (s)."""
    if not (np.isfinite(period) and period > 0):
        raise StabilityError(f'period must be finite and positive, got {period!r}')
    return boundary_omega_delta(delay, zeta) / period


def modal_gains(mass_matrix: np.ndarray, gain_diagonal: np.ndarray) -> np.ndarray:
    """μ_k, ascending: the eigenvalues of M⁻¹ D, D = diag(`gain_diagonal`), the modes of PD + gravity.

    PD + gravity linearised about the goal q_f with the arm's inertia M = M(q_f): M ë = -(K_p e + K_v ė),
    delayed and held, under the ω rule K_p = D ω², K_v = 2ζ D ω with D = diag(m̂_ii), the controller's model at
    q_f. M⁻¹ D is similar to the symmetric positive definite D^{1/2} M⁻¹ D^{1/2}, so the μ_k are real and
    positive and its eigenvectors decouple the loop into double integrators with k_p = μ_k ω², k_v = 2ζμ_k ω;
    computed torque with an exact model is the case μ_k = 1.

    Gravity: the feedforward Ĝ(q^d) = G(q_f) of an exact model cancels G at the goal, and what is left,
    ∂G/∂q(q_f) (q - q_f), is left out: the boundary is that of the loop linearised about the goal with the
    arm's inertia alone, as the ω rule's analysis takes it. That term is a stiffness of the continuous plant,
    acting without hold or delay, which neither discretises with the held torque nor is diagonal in these modes.
    """
    mass_matrix = np.asarray(mass_matrix, dtype=float)
    gain_diagonal = np.asarray(gain_diagonal, dtype=float)
    if not np.all(gain_diagonal > 0):
        raise StabilityError(f'the gain diagonal m_ii must be positive, got {gain_diagonal.tolist()}')
    from scipy.linalg import eigh

    try:
        # D v = μ M v, the symmetric-definite form of M⁻¹ D v = μ v.
        return eigh(np.diag(gain_diagonal), mass_matrix, eigvals_only=True)
    except np.linalg.LinAlgError as error:
        raise StabilityError('the mass matrix M(q_f) is not positive definite') from error


def modal_boundary_omega_delta(gains: np.ndarray, delay: int, zeta: float) -> float:
    """ωΔ* of the loop whose modes have k_p = μ_k ω², k_v = 2ζμ_k ω (`gains` = μ_k, see modal_gains).

    Mode k is p(z) with w' = √μ_k w and ζ' = ζ√μ_k, so ωΔ* = min_k boundary_omega_delta(d, ζ√μ_k) / √μ_k.
    """
    gains = np.asarray(gains, dtype=float)
    if not np.all(gains > 0):
        raise StabilityError(f'the modal gains μ_k must be positive, got {gains.tolist()}')
    delay, zeta = _checked(delay, zeta)
    roots = np.unique(np.sqrt(gains))
    low, high = ZETA_RANGE[0] / roots[0], ZETA_RANGE[1] / roots[-1]
    if not low <= zeta <= high:
        root = roots[0] if zeta < low else roots[-1]
        raise StabilityError(f'zeta {zeta:g} gives the mode of μ_k = {root**2:.6g} the damping ζ√μ_k = '
                             f'{zeta * root:.6g}, outside the [{ZETA_RANGE[0]:g}, {ZETA_RANGE[1]:g}] the boundary '
                             f'is computed within: this loop takes zeta within [{low * (1 + 1e-5):.6g}, '
                             f'{high * (1 - 1e-5):.6g}]')  # rounded inward: each bound printed is taken
    return float(min(boundary_omega_delta(delay, zeta * root) / root for root in roots))


def sampled_loop_transition(mass_matrix: np.ndarray, stiffness: np.ndarray, damping: np.ndarray,
                            position_feedback: np.ndarray, velocity_feedback: np.ndarray, period: float,
                            delay: int) -> np.ndarray:
    """The transition matrix of a sampled loop linearised about a rest point, coupled through M.

    The plant M ẍ + S x + B ẋ = u (`stiffness` S = ∂G/∂q, `damping` B), u held over [t_n, t_{n+1}) at
    u_n = -y_{n-d}, y = F_p x + F_v ẋ (the law's feedback, linearised). Its exact zero-order-hold discretisation
    z_{n+1} = Φ z_n + Γ u_n, z = (x, ẋ), from the exponential of [[A, B_u], [0, 0]] Δ, and the delayed feedback as
    the state (z_n, y_{n-1}, …, y_{n-d}): n (d + 2) numbers. Without S and B, and with F = [K_p K_v], these are
    the modes of modal_gains; with them, the loop as the plant has it at that point.
    """
    mass_matrix = np.asarray(mass_matrix, dtype=float)
    n = mass_matrix.shape[0]
    delay = _checked_delay(delay)
    if not (np.isfinite(period) and period > 0):
        raise StabilityError(f'period must be finite and positive, got {period!r}')
    if n * (delay + 2) > MAX_LOOP_STATES:
        raise StabilityError(f'the linearised loop of {n} joints with a delay of {delay} samples has '
                             f'{n * (delay + 2)} states, more than {MAX_LOOP_STATES}')
    try:
        inverse = np.linalg.inv(mass_matrix)
    except np.linalg.LinAlgError as error:
        raise StabilityError('the mass matrix M(q) is singular') from error
    generator = np.zeros((3 * n, 3 * n))
    generator[:n, n:2 * n] = np.eye(n)
    generator[n:2 * n, :n] = -inverse @ stiffness
    generator[n:2 * n, n:2 * n] = -inverse @ damping
    generator[n:2 * n, 2 * n:] = inverse
    from scipy.linalg import expm

    step = expm(generator * period)
    hold, response = step[:2 * n, :2 * n], step[:2 * n, 2 * n:]
    feedback = np.hstack([position_feedback, velocity_feedback])
    if not (np.isfinite(step).all() and np.isfinite(feedback).all()):
        raise StabilityError('the linearised loop is not finite: its gains, friction or arm are too large for '
                             'floating point')
    if delay == 0:
        return hold - response @ feedback
    size = n * (delay + 2)
    matrix = np.zeros((size, size))
    matrix[:2 * n, :2 * n] = hold
    matrix[:2 * n, size - n:] = -response
    matrix[2 * n:3 * n, :2 * n] = feedback
    matrix[3 * n:, 2 * n:size - n] = np.eye(n * (delay - 1))
    return matrix


def growing_modes(transition: np.ndarray, joints: int) -> tuple[float, np.ndarray]:
    """(spectral radius, share): the largest |z| of `transition` (sampled_loop_transition's), and per joint the
    largest |x_i| / max_j |x_j| over the eigenvectors whose |z| exceeds 1 (all 0 when none does): which joints the
    growing modes move."""
    try:
        values, vectors = np.linalg.eig(transition)
    except np.linalg.LinAlgError as error:
        raise StabilityError(f'the modes of the linearised loop were not found ({error})') from error
    magnitudes = np.abs(values)
    share = np.zeros(joints)
    for k in np.flatnonzero(magnitudes > GROWING):
        positions = np.abs(vectors[:joints, k])
        if positions.max() > 0:
            share = np.maximum(share, positions / positions.max())
    return float(magnitudes.max()), share
