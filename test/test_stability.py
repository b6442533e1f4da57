"""`ddarm stability` and ddarm.control.stability: the exact boundary ωΔ* of the sampled loop, checked against the
closed form for d = 0, the delayed transition matrix built here, the coupled arm's matrix and simulated episodes."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from ddarm.cli.main import main
from ddarm.control.gains import largest_stable_omega
from ddarm.control.stability import (MAX_LOOP_STATES, StabilityError, boundary_omega, boundary_omega_delta,
                                     growing_modes, modal_boundary_omega_delta, modal_gains, sampled_loop_transition)
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import (EpisodeSpec, episode_motion, gains_from_omega, loop_stability_warnings, model_arm,
                                 plant_arm)

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


@pytest.mark.parametrize('arguments', [['--delay', '100', '--zeta', '1e-6', '1e6'],
                                       ['--delay', '0', '100', '--zeta', '1e-6', '1', '--period', '1e-6']])
def test_the_tables_columns_stay_apart_whatever_the_numbers_width(capsys, arguments):
    assert main(['stability', *arguments]) == 0
    rows = capsys.readouterr().out.splitlines()[1:]
    zetas = arguments[arguments.index('--zeta') + 1:][:2]
    assert [float(cell.split('=')[1]) for cell in rows[0].split('  ') if cell.strip()] == [float(z) for z in zetas]
    for row in rows[1:]:
        # The row's label, then one whitespace-separated number (and its ω in parentheses) per ζ.
        cells = [cell for cell in row.split('  ') if cell.strip()]
        assert len(cells) == 1 + len(zetas) and all(float(cell.split()[0]) > 0 for cell in cells[1:]), row


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


def random_arm(rng, joints: int) -> np.ndarray:
    """A mass matrix with large off-diagonal inertia, as a coupled arm has."""
    factor = rng.normal(size=(joints, joints))
    return factor @ factor.T + 0.1 * np.eye(joints)


@pytest.mark.parametrize('delay', [0, 1, 2, 5])
def test_the_coupled_loop_is_the_delayed_transition_without_gravity(delay):
    rng = np.random.default_rng(delay)
    mass, zero = random_arm(rng, 3), np.zeros((3, 3))
    kp, kv = np.diag(rng.uniform(50, 500, 3)), np.diag(rng.uniform(5, 50, 3))
    ours = sampled_loop_transition(mass, zero, zero, kp, kv, 0.01, delay)
    assert ours.shape == (3 * (delay + 2),) * 2
    reference = delayed_transition(0.01, delay, np.linalg.solve(mass, np.hstack([kp, kv])))
    # The same loop: each root of ours is one of the reference's, whose extra states only add roots at 0.
    for root in np.linalg.eigvals(ours):
        if abs(root) > 1e-3:
            assert np.linalg.svd(reference - root * np.eye(len(reference)), compute_uv=False)[-1] < 1e-9
    assert growing_modes(ours, 3)[0] == pytest.approx(spectral_radius(reference), rel=1e-9)


@pytest.mark.parametrize('delay', [0, 1, 3])
def test_the_coupled_loop_steps_as_the_plant_with_gravity_and_friction_does(delay):
    """M ẍ + S x + B ẋ = u held over each period, u_n = -(F_p x + F_v ẋ)(t_{n-d}), integrated by solve_ivp."""
    from scipy.integrate import solve_ivp

    rng = np.random.default_rng(10 + delay)
    joints, period = 3, 0.01
    mass = random_arm(rng, joints)
    stiffness, damping = rng.normal(size=(joints, joints)) * 20, np.diag(rng.uniform(0, 3, joints))
    position_feedback, velocity_feedback = rng.normal(size=(joints, joints)) * 50, rng.normal(size=(joints, joints))
    transition = sampled_loop_transition(mass, stiffness, damping, position_feedback, velocity_feedback, period,
                                         delay)
    start = rng.normal(size=2 * joints)
    states = [start]
    feedback = np.hstack([position_feedback, velocity_feedback])
    history = [feedback @ start] * (delay + 1)  # y_n for the samples before 0: as the state starts them
    for n in range(12):
        held = -history[-1 - delay]
        x = solve_ivp(lambda t, z: np.concatenate([z[joints:], np.linalg.solve(
            mass, held - stiffness @ z[:joints] - damping @ z[joints:])]), (0, period), states[-1],
            rtol=1e-12, atol=1e-14).y[:, -1]
        states.append(x)
        history.append(feedback @ x)
    state = np.concatenate([start] + [feedback @ start] * delay)
    for n in range(12):
        state = transition @ state
        np.testing.assert_allclose(state[:2 * joints], states[n + 1], rtol=1e-8, atol=1e-10)


def test_a_loop_too_large_to_solve_is_refused_before_any_matrix():
    joints = MAX_LOOP_STATES // 10
    with pytest.raises(StabilityError, match=f'more than {MAX_LOOP_STATES}'):
        sampled_loop_transition(np.eye(joints), np.zeros((joints, joints)), np.zeros((joints, joints)),
                                np.eye(joints), np.eye(joints), 0.01, 9)


ROOT = Path(__file__).resolve().parents[1]
PANDA = dict(urdf='config/arms/panda/panda.urdf', motion='config/arms/panda/panda-motion.yaml')


def omega_rule_spec(controller: str, omega: float, delay: int, **arm) -> EpisodeSpec:
    arm = {key: str(ROOT / value) for key, value in arm.items()}
    spec = EpisodeSpec(controller=controller, kp=(1.0,), kv=(1.0,), delay=delay, **arm)
    kp, kv = gains_from_omega(spec, omega)
    return EpisodeSpec(controller=controller, kp=kp, kv=kv, delay=delay, **arm)


def test_pd_gravity_on_the_panda_at_omega_15_is_warned_naming_its_coupled_joints():
    """docs/your-arm.md: PD + gravity on the Panda at ω = 15, Δ = 0.01 s, d = 0 is unstable (its modal boundary near 3)."""
    warnings = loop_stability_warnings(omega_rule_spec('pd_gravity', 15.0, 0, **PANDA))
    assert len(warnings) == 1 and 'stability boundary' in warnings[0] and 'at the goal q_f' in warnings[0]
    named = warnings[0].split('move mostly ')[1].split(', whose')[0].split(', ')
    assert named and set(named) <= {f'panda_joint{i}' for i in range(1, 8)} and 'panda_joint1' in named


def test_the_papers_gains_on_the_papers_arm_are_not_warned():
    assert loop_stability_warnings(omega_rule_spec('pd_gravity', 10.0, 0)) == []
    assert loop_stability_warnings(omega_rule_spec('computed_torque', 15.0, 1)) == []


@pytest.mark.parametrize('delay', [0, 1, 2])
def test_computed_torque_is_warned_just_beyond_the_exact_boundary(delay):
    """An exact model: n double integrators, up to ∂G/∂q held against the plant's own."""
    boundary = boundary_omega(0.01, delay, 1.0)
    assert loop_stability_warnings(omega_rule_spec('computed_torque', 0.99 * boundary, delay)) == []
    warnings = loop_stability_warnings(omega_rule_spec('computed_torque', 1.01 * boundary, delay))
    assert len(warnings) == 1 and 'joint' in warnings[0]


@pytest.mark.parametrize('delay', [0, 1])
def test_pd_gravity_is_warned_where_the_episode_held_at_the_goal_grows(tmp_path, delay):
    """The paper's arm held at q_f after a waypoint move: errors grow just above the boundary the warning uses."""
    motion = tmp_path / 'hold.yaml'
    motion.write_text('joint_names: [joint1, joint2, joint3]\nstart: [0.0, 1.0471975511965976, '
                      '-2.0943951023931953]\npoints:\n  - positions: [1.5707963267948966, 0.0, 0.0]\n'
                      '    time_from_start: 1.0\n')
    mass, diagonal = paper_arm_at_the_goal()
    decoupled = modal_boundary_omega_delta(modal_gains(mass, diagonal), delay, 1.0) / 0.01
    decay = {}
    for factor in (0.8, 1.25):
        spec = dataclasses.replace(omega_rule_spec('pd_gravity', factor * decoupled, delay), motion=str(motion),
                                   duration=3.0)
        errors = np.abs(run_episode(spec).scored('errors'))
        decay[factor] = errors[300].max() / errors[100].max()
        assert bool(loop_stability_warnings(spec)) == (factor > 1)
    # Two seconds at the goal after it is reached at t = 1 s: the errors decay below the boundary, not above it.
    assert decay[0.8] < 0.1 and decay[1.25] > 1


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
