"""The `ddarm episode` command: its JSON, its human output and its refusals."""

import contextlib
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from ddarm.cli.main import main
from ddarm.episodes.engine import run_episode
from ddarm.episodes.spec import EpisodeSpec


def run_json(capsys, *arguments):
    assert main(['episode', *arguments, '--json']) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize('controller', ['pd_gravity', 'computed_torque'])
@pytest.mark.parametrize('trajectory', ['1', '2'])
@pytest.mark.parametrize('extra', [[], ['--limited', '--tau', '0.1']])
def test_episode_json_has_the_indices_and_matches_the_core(capsys, controller, trajectory, extra):
    summary = run_json(capsys, '--controller', controller, '--trajectory', trajectory,
                       '--kp', '400', '300', '200', '--kv', '40', '30', '20', *extra)
    assert {'I1', 'I2', 'I', 'diverged', 'spec', 'command'} <= set(summary)
    assert summary['I'] == pytest.approx(summary['I1'] + summary['I2'], rel=1e-12)
    spec = EpisodeSpec(**summary['spec'])
    assert run_episode(spec).indices()['I'] == summary['I']
    assert summary['command'].startswith('ddarm episode --controller')


def test_omega_gives_the_rule_gains(capsys):
    computed = run_json(capsys, '--controller', 'computed_torque', '--omega', '15')
    assert computed['spec']['kp'] == [225.0] * 3 and computed['spec']['kv'] == [30.0] * 3
    pd = run_json(capsys, '--controller', 'pd_gravity', '--omega', '10', '--delay', '0')
    assert pd['spec']['kp'] == pytest.approx([2800, 2700, 350])
    assert pd['spec']['delay'] == 0 and computed['spec']['delay'] == 1


def test_a_diverging_episode_is_reported_not_crashed(capsys):
    summary = run_json(capsys, '--controller', 'computed_torque', '--kp', '1e6', '1e6', '1e6',
                       '--kv', '3e3', '3e3', '3e3')
    assert summary['diverged'] is True
    assert all(isinstance(summary[key], float) for key in ('I1', 'I2', 'I'))


def test_human_output_names_the_indices(capsys):
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15']) == 0
    out = capsys.readouterr().out
    assert 'I1 (2.5)' in out and 'I (3.2)' in out


@pytest.mark.parametrize('arguments, problem', [
    (['--kp', '1', '2', '--kv', '1', '2', '3'], 'kp needs 3'),
    (['--kp', '1', '2', '3'], '--kp needs --kv'),
    (['--omega', '-3'], 'omega'),
    (['--omega', '15', '--period', '0.003'], 'whole number'),
    (['--omega', '15', '--tau', '2'], 'tau'),
])
def test_bad_options_are_refused_with_the_problem_named(capsys, arguments, problem):
    assert main(['episode', '--controller', 'computed_torque', *arguments]) == 2
    assert problem in capsys.readouterr().err


def test_non_finite_numbers_are_refused_by_the_parser(capsys):
    with pytest.raises(SystemExit):
        main(['episode', '--controller', 'computed_torque', '--kp', 'nan', '1', '1', '--kv', '1', '1', '1'])
    assert 'not a finite number' in capsys.readouterr().err


def test_the_console_script_is_installed():
    executable = Path(sys.executable).with_name('ddarm')
    done = subprocess.run([str(executable), 'episode', '--controller', 'computed_torque', '--omega', '15',
                           '--json'], capture_output=True, text=True, check=True)
    assert json.loads(done.stdout)['I1'] > 0


ROOT = Path(__file__).resolve().parents[1]
PANDA = ['--urdf', str(ROOT / 'config/arms/panda/panda.urdf'),
         '--motion', str(ROOT / 'config/arms/panda/panda-motion.yaml')]


def stability_warnings(warnings: list[str]) -> list[str]:
    return [warning for warning in warnings if 'stability boundary' in warning]


def test_gains_beyond_the_coupled_loops_boundary_are_warned_naming_the_joints(capsys):
    """docs/your-arm.md: PD + gravity on the Panda at ω = 15 (Δ = 0.01 s, d = 0) is unstable, which the ω rule cannot see."""
    summary = run_json(capsys, '--controller', 'pd_gravity', '--omega', '15', '--delay', '0', *PANDA)
    [warning] = stability_warnings(summary['warnings'])
    assert 'panda_joint1' in warning and 'spectral radius' in warning
    assert main(['episode', '--controller', 'pd_gravity', '--omega', '15', '--delay', '0', *PANDA]) == 0
    assert 'WARNING: the gains lie beyond the stability boundary' in capsys.readouterr().out


def test_the_papers_gains_are_not_warned(capsys):
    for arguments in (['--controller', 'pd_gravity', '--omega', '10', '--delay', '0'],
                      ['--controller', 'computed_torque', '--omega', '15']):
        assert stability_warnings(run_json(capsys, *arguments)['warnings']) == []


def test_tune_warns_of_starts_and_tuned_gains_beyond_the_boundary(capsys, tmp_path, monkeypatch):
    import ddarm.cli.tune as tune_command
    import ddarm.tuning.outputs as outputs
    import ddarm.tuning.tune as tuning_module
    from ddarm.episodes.spec import gains_from_omega

    def searched_at(omega):
        def searched(template, *arguments, **options):
            kp, kv = gains_from_omega(template, omega)
            return tuning_module.Tuning(SimpleNamespace(kp=kp, kv=kv, index=1.0, episodes=1), (omega,), [1.0], 1.0,
                                        {})
        return searched

    monkeypatch.setattr(tune_command, 'graph_with_nodes',
                        lambda template: contextlib.nullcontext(SimpleNamespace(keep_files_in=lambda folder: None,
                                                                                close=lambda: None)))
    monkeypatch.setattr(tune_command, 'check_through_graph', lambda session, run, spec, storage: {})
    monkeypatch.setattr(outputs, 'finish_tuning', lambda run, template, best, tuning, scored, **options: {
        'agree': True, 'warnings': list(tuning.warnings)})
    tune = ['tune', '--controller', 'pd_gravity', '--delay', '0', '--index', 'I', '--runs', str(tmp_path), '--json']
    monkeypatch.setattr(tuning_module, 'tune', searched_at(15.0))
    assert main([*tune, '--omegas', '15', '--run', 'panda', *PANDA]) == 0
    captured = capsys.readouterr()
    [start] = stability_warnings(captured.err.splitlines())
    assert 'the ω-rule start gains at ω = 15 lie beyond' in start and 'panda_joint1' in start
    [tuned] = stability_warnings(json.loads(captured.out)['warnings'])
    assert tuned.startswith('the tuned gains lie beyond') and 'panda_joint1' in tuned
    monkeypatch.setattr(tuning_module, 'tune', searched_at(10.0))
    assert main([*tune, '--omegas', '10', '--run', 'paper']) == 0  # the paper's arm and gains
    captured = capsys.readouterr()
    assert stability_warnings(captured.err.splitlines()) == []
    assert stability_warnings(json.loads(captured.out)['warnings']) == []
