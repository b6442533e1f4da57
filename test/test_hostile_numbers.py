"""Numbers from someone else (a period, a duration, a motion file's duration, the ω procedure's steps) are refused
by name before any work, JSON never holds a number JSON cannot, and a procedure that finds nothing says so with a
non-zero exit."""

import json
from pathlib import Path

import numpy as np
import pytest

from ddarm.cli.main import main
from ddarm.episodes.spec import MAX_DURATION, PERIOD_RANGE, EpisodeError, EpisodeSpec
from ddarm.tuning import procedures

ROOT = Path(__file__).resolve().parents[1]
PANDA = ROOT / 'config' / 'arms' / 'panda'


def strict_json(text: str):
    """JSON as the standard has it: Infinity and NaN are no numbers of it."""
    def refuse(constant):
        raise AssertionError(f'{constant} in the JSON')
    return json.loads(text, parse_constant=refuse)


def refused_by_the_parser(capsys, arguments: list[str], option: str) -> str:
    """Exit 2 on one line naming the option: argparse's refusal, or the episode's (which names the quantity)."""
    try:
        code = main(arguments)
    except SystemExit as stop:
        code = stop.code
    captured = capsys.readouterr()
    quantity = {'--period': 'period', '--duration': 'duration', '--tau': 'tau'}[option]
    assert code == 2 and 'Traceback' not in captured.err, captured.err
    assert len(captured.err.strip().splitlines()) == 1 and quantity in captured.err, captured.err
    assert captured.out == ''
    return captured.err


@pytest.mark.parametrize('period', ['1e-320', '5e-324', '1e-7', '0', '1e300', 'inf'])
@pytest.mark.parametrize('command', [
    ['stability'], ['stability', '--json'], ['stability', '--controller', 'pd_gravity', '--json'],
    ['episode', '--controller', 'computed_torque', '--omega', '15'],
    ['omega', '--controller', 'computed_torque', '--max-error', '0.5', '--disturbance', '0', '10', '0'],
    ['tune', '--controller', 'pd_gravity', '--index', 'I'],
])
def test_a_period_outside_its_range_is_refused_by_name(capsys, tmp_path, command, period):
    extra = ['--runs', str(tmp_path)] if command[0] in ('omega', 'tune') else []
    err = refused_by_the_parser(capsys, [*command, '--period', period, *extra], '--period')
    assert ('not a finite number' if period == 'inf' and command[0] != 'stability' else f'{PERIOD_RANGE[0]:g}') in err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize('duration', ['1e308', '1e-320', str(2 * MAX_DURATION)])
def test_a_duration_outside_its_range_is_refused_by_name(capsys, duration):
    refused_by_the_parser(capsys, ['episode', '--controller', 'computed_torque', '--omega', '15',
                                   '--duration', duration], '--duration')


@pytest.mark.parametrize('fields', [
    {'period': 1e-320}, {'period': 5e-324}, {'period': 1e-7}, {'period': float('inf')}, {'period': 1e300},
    {'duration': 1e308}, {'duration': float('nan')}, {'duration': 2 * MAX_DURATION},
    {'duration': 1.0, 'period': PERIOD_RANGE[0] / 2},
])
def test_an_episode_spec_refuses_a_period_or_duration_by_name(fields):
    name = 'period' if 'period' in fields and not PERIOD_RANGE[0] <= fields['period'] <= PERIOD_RANGE[1] \
        else 'duration'
    with pytest.raises(EpisodeError, match=name):
        EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, **fields)


def test_more_samples_than_the_bound_are_refused_naming_both_values():
    with pytest.raises(EpisodeError, match=r'the duration 100.0 s at the period 1e-05 s is more than 1000000 samples'):
        EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, duration=100.0, period=1e-5)


@pytest.mark.parametrize('duration', ['1e308', '1.0e+300', str(2 * MAX_DURATION)])
def test_a_motion_files_duration_beyond_the_bound_is_refused_naming_the_file(capsys, tmp_path, duration):
    text = (PANDA / 'panda-motion.yaml').read_text()
    motion = tmp_path / 'long.yaml'
    motion.write_text(text.replace('duration: 1.0', f'duration: {duration}'))
    assert f'duration: {duration}' in motion.read_text()
    assert main(['episode', '--controller', 'pd_gravity', '--omega', '15', '--urdf', str(PANDA / 'panda.urdf'),
                 '--motion', str(motion)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and f'motion {motion}: its duration ' in err and f'{MAX_DURATION:g}' in err


def test_waypoint_velocities_beyond_any_torque_are_not_blamed_on_a_still_joint(capsys, tmp_path):
    motion = tmp_path / 'fast.yaml'
    motion.write_text('joint_names: [joint1, joint2, joint3]\n'
                      'points:\n'
                      '  - positions: [0.0, 0.5, -0.5]\n'
                      '    velocities: [1.0e308, 0.0, 0.0]\n'
                      '    time_from_start: 0.5\n'
                      '  - positions: [0.2, 0.6, -0.4]\n'
                      '    time_from_start: 1.0\n'
                      'start: [0.0, 0.4, -0.6]\n')
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--motion', str(motion)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'neither moves' not in err and 'joint1' in err and 'finite' in err


@pytest.mark.parametrize('period', [PERIOD_RANGE[0], 2.0, PERIOD_RANGE[1]])
def test_an_episode_runs_at_every_period_of_its_range(capsys, period):
    # The plant refused Δ > 1 s that the command line and the spec accept.
    duration = max(20 * period, 1e-3)
    assert main(['episode', '--controller', 'pd_gravity', '--omega', '0.05', '--period', repr(period),
                 '--duration', repr(duration), '--json']) == 0
    report = strict_json(capsys.readouterr().out)
    assert report['spec']['period'] == period and report['samples_scored'] > 0


def test_the_stability_json_is_strict_at_the_smallest_period(capsys):
    assert main(['stability', '--period', f'{PERIOD_RANGE[0]!r}', '--json']) == 0
    report = strict_json(capsys.readouterr().out)
    assert all(np.isfinite(entry['omega']) for entry in report['boundaries'])


def omega_arguments(tmp_path, *extra):
    return ['omega', '--controller', 'computed_torque', '--max-error', '0.5', '--disturbance', '0', '10', '0',
            '--runs', str(tmp_path / 'runs'), '--run', 'procedure', *extra]


@pytest.mark.parametrize('json_flag', [[], ['--json']])
def test_an_omega_procedure_that_finds_no_omega_exits_non_zero_and_says_so(capsys, tmp_path, json_flag):
    (tmp_path / 'runs').mkdir()
    out = tmp_path / 'gains.yaml'
    code = main(omega_arguments(tmp_path, '--torque-factor', '0.01', '--out', str(out), *json_flag))
    captured = capsys.readouterr()
    assert code != 0
    assert 'no ω' in captured.err and f'{out} not written' in captured.err
    assert not out.exists()
    summary = json.loads((tmp_path / 'runs' / 'procedure' / 'summary.json').read_text())
    assert summary['omega']['omega'] is None and summary['status'] != 'complete'
    if json_flag:
        assert strict_json(captured.out)['omega'] is None


@pytest.mark.parametrize('extra', [['--max-error', '1e-300'], ['--omega-max', '1']])
def test_an_omega_min_above_omega_max_is_refused_before_any_episode(capsys, tmp_path, extra):
    (tmp_path / 'runs').mkdir()
    assert main([*omega_arguments(tmp_path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'omega max' in err and 'ω_min' in err
    assert not any((tmp_path / 'runs').iterdir())


def test_the_raising_step_runs_a_bounded_number_of_episodes_whatever_the_step(monkeypatch):
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, external_torque=(0.0, 10.0, 0.0))
    permitted = np.radians(0.5)
    error_unit, gain_scale = procedures.steady_state_error_per_unit_gain(spec)
    omega_min = procedures.smallest_omega(error_unit, gain_scale, np.full(3, permitted))
    episodes = []
    simulate = procedures.run_episode

    def counted(episode_spec):
        episodes.append(episode_spec.kp)
        assert len(episodes) <= 3, 'the raising step does not end'
        return simulate(episode_spec)

    monkeypatch.setattr(procedures, 'run_episode', counted)
    # A step below the last bit of ω: adding it leaves ω where it was.
    choice = procedures.omega_procedure(spec, permitted, torque_factor=100.0, omega_step=1e-300, omega_max=omega_min)
    assert len(episodes) == 1 and choice.omega == pytest.approx(omega_min, rel=1e-15)


def test_the_raising_step_takes_each_omega_as_a_product_of_the_step(monkeypatch):
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * 3, kv=(1.0,) * 3, external_torque=(0.0, 0.01, 0.0))
    choice = procedures.omega_procedure(spec, np.radians(90.0), torque_factor=1e9, omega_step=0.1, omega_max=3.0)
    assert [step.omega for step in choice.steps] == [0.1 + k * 0.1 for k in range(30)]


def test_a_damping_whose_mode_leaves_the_computed_range_is_refused_with_the_range_this_loop_takes(capsys):
    # PD + gravity's modes have the damping ζ√μ_k: ζ = 1e-6 was refused quoting 7.3e-07, a number never given.
    assert main(['stability', '--controller', 'pd_gravity', '--zeta', '1e-6']) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'zeta 1e-06 gives the mode of μ_k' in err
    low = err.split('this loop takes zeta within [')[1].split(',')[0]
    assert main(['stability', '--controller', 'pd_gravity', '--zeta', low, '--json']) == 0
    report = strict_json(capsys.readouterr().out)
    assert all(entry['omega_delta'] > 0 for entry in report['boundaries'])


@pytest.mark.parametrize('last, problem', [('1e-320', 'must be within'), ('1.0005', 'not a whole number'),
                                           ('1e18', "time_from_start 1e+18 s is more than 10000 s")])
def test_a_waypoint_motion_whose_last_time_no_episode_takes_is_refused_naming_the_file_and_field(capsys, tmp_path,
                                                                                                 last, problem):
    motion = tmp_path / 'motion.yaml'
    motion.write_text('joint_names: [joint1, joint2, joint3]\nstart: [0.0, 0.0, 0.0]\npoints:\n'
                      f'  - {{positions: [0.1, 0.1, 0.1], time_from_start: {last}}}\n')
    assert main(['episode', '--controller', 'pd_gravity', '--omega', '10', '--motion', str(motion)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and f"motion {motion}: the last point's time_from_start" in err and problem in err


def test_a_run_summary_never_holds_a_number_json_cannot(tmp_path):
    from ddarm.recording.runs import RunFolder
    from ddarm.strict_json import OutputError

    with RunFolder('strict', root=tmp_path) as run:
        run.record('best', {'I': 0.25})
        with pytest.raises(OutputError, match=r'best\.I = inf'):
            run.record('best', {'I': float('inf')})
        assert strict_json((run.path / 'summary.json').read_text())['best'] == {'I': 0.25}
        run.finish('complete')  # the refused value is not the run's: the run still ends with its summary
    summary = strict_json((run.path / 'summary.json').read_text())
    assert summary['best'] == {'I': 0.25} and summary['status'] == 'complete'


def test_a_negative_number_float_cannot_read_is_refused_by_its_argument_not_taken_for_an_option(capsys):
    err = refused_by_the_parser(capsys, ['episode', '--controller', 'pd_gravity', '--omega', '10', '--duration',
                                         '-0x1p3'], '--duration')
    assert "'-0x1p3'" in err and 'expected one' not in err


@pytest.mark.parametrize('value', ['-1e-3', '-1E+2', '-.5e1', '-inf', '-1_0'])
def test_a_negative_number_in_exponent_form_is_a_value_not_an_option(capsys, value):
    # argparse took -1e-3 for an option: 'expected one argument', not the quantity's own refusal.
    err = refused_by_the_parser(capsys, ['episode', '--controller', 'pd_gravity', '--omega', '10', '--tau', value],
                                '--tau')
    assert ('not a finite number' if value == '-inf' else 'tau must be') in err and 'expected one' not in err


@pytest.mark.parametrize('arguments', [
    ['--kp', '1e308', '1', '1', '--kv', '10', '10', '10'],
    ['--omega', '10', '--viscous-friction', '1e150', '0', '0'],
])
def test_gains_or_friction_beyond_floating_point_run_and_say_the_stability_was_not_checked(capsys, arguments):
    assert main(['episode', '--controller', 'computed_torque', *arguments, '--json']) == 0
    captured = capsys.readouterr()
    result = strict_json(captured.out)
    assert result['diverged'] and 'Traceback' not in captured.err and 'RuntimeWarning' not in captured.err
    assert ('the stability of the gains was not checked: the linearised loop is not finite: its gains, friction or '
            'arm are too large for floating point') in result['warnings']


@pytest.mark.parametrize('max_error, shown', [(['1e308'], '1e+308 deg'), (['-1'], '-1 deg'), (['1', '5730', '1'], '5730 deg')])
def test_a_permitted_error_beyond_the_plants_bound_is_refused_in_the_users_units(capsys, tmp_path, max_error, shown):
    code = main(['omega', '--controller', 'computed_torque', '--duration', '0.2', '--disturbance', '5', '5', '5',
                 '--max-error', *max_error, '--runs', str(tmp_path)])
    captured = capsys.readouterr()
    joint = 'joint2' if len(max_error) == 3 else 'joint1'
    assert code == 2 and captured.err == (f'ddarm omega: --max-error for {joint}: {shown}, not within (0, 5729.58] '
                                          "deg (the plant's bound on a position, beyond which an episode counts as "
                                          'diverged)\n')
    assert not any(tmp_path.iterdir())
