"""`ddarm stability` and ddarm.control.stability: the exact boundary ωΔ* of the sampled loop, checked against the
closed form for d = 0, the delayed transition matrix built here, the coupled arm's matrix and simulated episodes."""

import json

import numpy as np
import pytest
from scipy.linalg import expm

from ddarm.cli.main import main
from ddarm.control.gains import largest_stable_omega
from ddarm.control.stability import (StabilityError, boundary_omega, boundary_omega_delta, modal_boundary_omega_delta,
                                     modal_gains)
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec, episode_motion, model_arm, plant_arm

# Just below and above the boundary: far inside the band where a crossing root's |z| - 1 changes sign.
STEP = 1e-7


def delayed_transition(period: float, delay: int, acceleration_gain: np.ndarray) -> np.ndarray:
    """The transition matrix of (x_n, …, x_{n-d}), x = (e, ė) of n joints, for ë = -F x(t_{n-d}) held over a
    period (F = M⁻¹ [K_p K_v], shape (n, 2n)): the zero-order hold by the matrix exponential of [[0, I, 0],
    [0, 0, I], [0, 0, 0]] Δ, independent of the module's algebra."""
    joints = acceleration_gain.shape[0]
    generator = np.zeros((3 * joints, 3 * joints))
    generator[:joints, joints:2 * joints] = np.eye(joints)
    generator[joints:2 * joints, 2 * joints:] = np.eye(joints)
    step = expm(generator * period)
    hold, gain = step[:2 * joints, :2 * joints], step[:2 * joints, 2 * joints:]
    size = 2 * joints * (delay + 1)
    matrix = np.zeros((size, size))
    matrix[:2 * joints, :2 * joints] = hold
    matrix[:2 * joints, size - 2 * joints:] -= gain @ acceleration_gain
    matrix[2 * joints:, :-2 * joints] = np.eye(size - 2 * joints)
    return matrix


def spectral_radius(matrix: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(matrix))))


def double_integrator_radius(omega_delta: float, delay: int, zeta: float) -> float:
    """One joint under k_p = ω², k_v = 2ζω at Δ = 1 (only ωΔ matters)."""
    return spectral_radius(delayed_transition(1.0, delay, np.array([[omega_delta**2, 2 * zeta * omega_delta]])))


def polynomial_radius(omega_delta: float, delay: int, zeta: float) -> float:
    """The largest |z| of p(z) = z^d (z - 1)² + (w²/2)(z + 1) + 2ζw (z - 1), the issue's polynomial."""
    w = omega_delta
    coefficients = np.zeros(delay + 3)
    coefficients[:3] = [1.0, -2.0, 1.0]
    coefficients[-2:] += [w**2 / 2 + 2 * zeta * w, w**2 / 2 - 2 * zeta * w]
    return float(np.max(np.abs(np.roots(coefficients))))


@pytest.mark.parametrize('zeta', [0.1, 0.3, 0.45, 0.5, 0.55, 0.7, 1.0, 1.5, 3.0])
def test_without_delay_the_boundary_is_the_closed_form(zeta):
    assert boundary_omega_delta(0, zeta) == pytest.approx(min(1 / zeta, 4 * zeta), rel=1e-12)


@pytest.mark.parametrize('delay', [0, 1, 2, 3, 4, 7])
@pytest.mark.parametrize('zeta', [0.05, 0.2, 0.3, 0.45, 0.5, 0.6, 0.7, 1.0, 1.3, 2.0, 5.0])
def test_the_loop_is_stable_below_the_boundary_and_not_above_it(delay, zeta):
    boundary = boundary_omega_delta(delay, zeta)
    # Everywhere below, not only just below: the boundary is the first crossing, not any crossing.
    below = boundary * np.linspace(0.01, 1 - STEP, 60)
    assert max(double_integrator_radius(w, delay, zeta) for w in below) < 1
    assert polynomial_radius(boundary * (1 - STEP), delay, zeta) < 1
    assert polynomial_radius(boundary * (1 + STEP), delay, zeta) > 1
    assert double_integrator_radius(boundary * (1 + STEP), delay, zeta) > 1


def test_the_boundary_of_the_omega_rule_is_the_known_one():
    """ζ = 1: 1 for d = 0 and 0.42616 for d = 1 (spec §13's table, ω* = 42.62 at Δ = 0.01)."""
    assert largest_stable_omega(0.01, 0) == pytest.approx(100.0, rel=1e-12)
    assert largest_stable_omega(0.01, 1) == pytest.approx(42.616, rel=1e-4)
    for delay in (0, 1, 2):
        assert largest_stable_omega(0.02, delay) == boundary_omega(0.02, delay, 1.0)
        assert boundary_omega(0.02, delay, 1.0) == pytest.approx(boundary_omega_delta(delay, 1.0) / 0.02)


def test_a_long_delay_is_exact_too():
    for delay, zeta in ((20, 1.0), (35, 0.4)):
        boundary = boundary_omega_delta(delay, zeta)
        assert polynomial_radius(boundary * (1 - 1e-6), delay, zeta) < 1 < polynomial_radius(boundary * (1 + 1e-6),
                                                                                            delay, zeta)


@pytest.mark.parametrize('arguments, name', [
    ((-1, 1.0), 'delay'), ((1.5, 1.0), 'delay'), ((True, 1.0), 'delay'),
    ((1, 0.0), 'zeta'), ((1, -0.5), 'zeta'), ((1, np.nan), 'zeta'), ((1, np.inf), 'zeta'),
])
def test_a_bad_delay_or_damping_is_refused_by_name(arguments, name):
    with pytest.raises(StabilityError, match=name):
        boundary_omega_delta(*arguments)


@pytest.mark.parametrize('period', [0.0, -0.01, np.inf])
def test_a_bad_period_is_refused(period):
    with pytest.raises(StabilityError, match='period'):
        boundary_omega(period, 1, 1.0)


def paper_arm_at_the_goal():
    spec = EpisodeSpec(controller='pd_gravity', kp=(1.0,), kv=(1.0,))
    goal = episode_motion(spec).qf
    return plant_arm(spec).mass_matrix(goal), np.diag(model_arm(spec).mass_matrix(goal))


def first_unstable_omega(radius, low: float, high: float, points: int = 400) -> float:
    """The smallest ω on a geometric grid of [low, high] with radius(ω) ≥ 1, refined by bisection."""
    grid = np.geomspace(low, high, points)
    unstable = next(i for i, omega in enumerate(grid) if radius(omega) >= 1)
    below, above = (grid[unstable - 1], grid[unstable]) if unstable else (0.0, grid[0])
    for _ in range(60):
        middle = 0.5 * (below + above)
        below, above = (middle, above) if radius(middle) < 1 else (below, middle)
    return above


@pytest.mark.parametrize('delay', [0, 1, 2])
@pytest.mark.parametrize('zeta', [0.7, 1.0])
def test_pd_gravity_modes_give_the_coupled_arms_boundary(delay, zeta):
    mass, diagonal = paper_arm_at_the_goal()
    gains = modal_gains(mass, diagonal)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(np.linalg.solve(mass, np.diag(diagonal))).real), gains)
    period = 0.01

    def radius(omega):
        stiffness, damping = diagonal * omega**2, 2 * zeta * diagonal * omega
        return spectral_radius(delayed_transition(
            period, delay, np.linalg.solve(mass, np.hstack([np.diag(stiffness), np.diag(damping)]))))

    coupled = first_unstable_omega(radius, 0.01 / period, 10 / period)
    assert modal_boundary_omega_delta(gains, delay, zeta) / period == pytest.approx(coupled, rel=1e-7)
    # The per-joint model, which drops M's coupling, promises more than the arm keeps.
    assert coupled < boundary_omega(period, delay, zeta)


def test_computed_torque_is_the_unit_mode():
    assert modal_boundary_omega_delta(np.ones(3), 1, 0.7) == boundary_omega_delta(1, 0.7)


def growth(delay: int, zeta: float, factor: float) -> tuple[bool, float]:
    """(diverged, late / middle |e|) of computed torque with the exact model at `factor` ω*, a τ start error."""
    period = 0.01
    omega = factor * boundary_omega(period, delay, zeta)
    spec = EpisodeSpec(controller='computed_torque', kp=(omega**2,) * 3, kv=(2 * zeta * omega,) * 3, delay=delay,
                       period=period, duration=2.0, tau=0.1)
    result = run_episode(spec)
    errors = np.abs(result.scored('errors'))
    middle, late = len(errors) // 2, len(errors) - 20
    return bool(result.diverged[0]), float(errors[late:].max() / errors[middle - 10:middle + 10].max())


@pytest.mark.parametrize('delay, zeta', [(1, 1.0), (2, 1.0), (2, 0.7)])
def test_simulated_episodes_decay_below_the_boundary_and_grow_above_it(delay, zeta):
    diverged, ratio = growth(delay, zeta, 0.9)
    assert not diverged and ratio < 1
    diverged, ratio = growth(delay, zeta, 1.1)
    assert diverged or ratio > 1


def stability_json(capsys, *arguments):
    assert main(['stability', *arguments, '--json']) == 0
    return json.loads(capsys.readouterr().out)


def test_the_json_has_one_boundary_per_delay_and_damping(capsys):
    report = stability_json(capsys, '--delay', '0', '1', '2', '--zeta', '0.7', '1.0')
    assert set(report) == {'controller', 'boundaries'} and report['controller'] == 'computed_torque'
    assert [(entry['delay'], entry['zeta']) for entry in report['boundaries']] == [
        (d, z) for d in (0, 1, 2) for z in (0.7, 1.0)]
    for entry in report['boundaries']:
        assert set(entry) == {'delay', 'zeta', 'omega_delta'}
        assert entry['omega_delta'] == boundary_omega_delta(entry['delay'], entry['zeta'])
    with_period = stability_json(capsys, '--delay', '1', '--period', '0.02')
    assert with_period['boundaries'] == [{'delay': 1, 'zeta': 1.0, 'omega_delta': boundary_omega_delta(1, 1.0),
                                          'omega': boundary_omega_delta(1, 1.0) / 0.02}]


def test_pd_gravity_reports_its_modes(capsys):
    report = stability_json(capsys, '--controller', 'pd_gravity', '--delay', '0', '1')
    mass, diagonal = paper_arm_at_the_goal()
    assert report['joint_names'] == ['joint1', 'joint2', 'joint3']
    np.testing.assert_allclose(report['modes'], modal_gains(mass, diagonal))
    assert [entry['omega_delta'] for entry in report['boundaries']] == [
        modal_boundary_omega_delta(modal_gains(mass, diagonal), d, 1.0) for d in (0, 1)]


def test_the_table_has_a_row_per_delay(capsys):
    assert main(['stability', '--delay', '0', '1', '--zeta', '0.7', '1', '--period', '0.01']) == 0
    lines = capsys.readouterr().out.splitlines()
    assert 'ζ = 0.7' in lines[1] and 'ζ = 1' in lines[1]
    assert lines[2].split()[:3] == ['d', '=', '0'] and '1.42857 (142.9)' in lines[2] and '1 (100)' in lines[2]
    assert lines[3].split()[:3] == ['d', '=', '1'] and '0.426159 (42.62)' in lines[3]


@pytest.mark.parametrize('arguments, option', [
    (['--delay', '-1'], '--delay'), (['--delay', '1.5'], '--delay'), (['--zeta', '0'], '--zeta'),
    (['--zeta', 'nan'], '--zeta'), (['--zeta', '-1'], '--zeta'), (['--period', '0'], '--period'),
    (['--period', '-0.01'], '--period'),
])
def test_bad_options_are_refused_by_name(capsys, arguments, option):
    with pytest.raises(SystemExit) as stop:
        main(['stability', *arguments])
    assert stop.value.code == 2 and f'argument {option}' in capsys.readouterr().err


def test_an_arm_for_computed_torque_is_refused(capsys):
    assert main(['stability', '--urdf', 'arm.urdf']) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and '--urdf' in err and 'Traceback' not in err


def test_a_missing_arm_for_pd_gravity_is_one_line(capsys, tmp_path):
    assert main(['stability', '--controller', 'pd_gravity', '--urdf', str(tmp_path / 'none.urdf')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'none.urdf' in err


def test_the_stability_figure_draws_the_map(tmp_path):
    from types import SimpleNamespace

    from ddarm.paper.figures import stability_figure
    from ddarm.paper.schema import StabilityRow
    from ddarm.paper.settings import paper_settings

    settings = paper_settings()
    rows = [StabilityRow(period=period, omega_max_stable=largest_stable_omega(period, 1),
                         omega_15_stable=15 < largest_stable_omega(period, 1), I1_at_omega_15=0.1,
                         diverged_at_omega_15=15 > largest_stable_omega(period, 1), bag=f'bags/{period}')
            for period in settings.stability.periods]
    path = tmp_path / 'stability.png'
    stability_figure(path, SimpleNamespace(section2=SimpleNamespace(stability=rows)), settings)
    assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
