"""Fail fast and say what is wrong (issue: trust): refusals that come before any search, episode or bag,
name the option, path or node, and exit 2 without a traceback."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ddarm.cli.main import main
from process_helpers import DDARM

ROOT = Path(__file__).resolve().parents[1]


def test_omega_with_kv_is_refused(capsys):
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--kv', '1', '1', '1']) == 2
    assert '--kv goes with --kp' in capsys.readouterr().err


@pytest.mark.parametrize('command', [
    ['tune', '--controller', 'computed_torque', '--index', '2.5', '--budget', '100000'],
    ['omega', '--controller', 'computed_torque', '--max-error', '0.5', '--disturbance', '0', '20', '5'],
])
def test_an_existing_out_file_is_refused_before_any_work(capsys, tmp_path, command):
    existing = tmp_path / 'gains.yaml'
    existing.write_text('kept: true\n')
    assert main([*command, '--runs', str(tmp_path / 'runs'), '--out', str(existing)]) == 2
    err = capsys.readouterr().err
    assert f'{existing} exists already' in err and 'searching' not in err
    assert existing.read_text() == 'kept: true\n' and not (tmp_path / 'runs').exists()


def test_an_existing_run_folder_is_refused_before_any_work(capsys, tmp_path):
    (tmp_path / 'runs' / 'taken').mkdir(parents=True)
    assert main(['tune', '--controller', 'computed_torque', '--index', '2.5', '--budget', '100000',
                 '--runs', str(tmp_path / 'runs'), '--run', 'taken']) == 2
    assert 'taken exists already' in capsys.readouterr().err


def test_an_existing_bag_is_refused_before_any_node_starts(capsys, tmp_path):
    (tmp_path / 'bag').mkdir()
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--ros',
                 '--bag', str(tmp_path / 'bag')]) == 2
    assert 'exists already' in capsys.readouterr().err


def test_bad_gains_are_refused_before_the_graph_starts(capsys):
    assert main(['episode', '--controller', 'computed_torque', '--kp', '1', '2', '--kv', '1', '2', '--ros']) == 2
    assert 'kp needs 3' in capsys.readouterr().err


@pytest.mark.parametrize('arguments, problem', [
    (['-p', 'kp:=[1.0,2.0]', '-p', 'kv:=[1.0,2.0,3.0]'], 'kp needs 3'),
    (['-p', 'kp:=[1.0,2.0,3.0]', '-p', 'kv:=[1.0,2.0,3.0]', '-p', 'storage:=zip'], 'storage must be one of'),
    (['-p', 'kp:=[1.0,2.0,3.0]', '-p', 'kv:=[1.0,2.0,3.0]', '-p', "torque_limits:=['max']"], 'torque_limit'),
])
def test_the_tuner_refuses_a_bad_sweep_at_start(tmp_path, arguments, problem):
    done = subprocess.run([str(DDARM), 'tuner', '--ros-args', *arguments, '-p', f'output_root:={tmp_path}'],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert problem in done.stderr and 'Traceback' not in done.stderr, done.stderr
    assert not any(tmp_path.iterdir()), 'a refused sweep leaves no run folder'


def test_the_tuner_refuses_a_parameter_file_that_configures_no_tuner(tmp_path):
    parameters = tmp_path / 'tuner.yaml'
    parameters.write_text('tunr:\n  ros__parameters:\n    kp: [1.0, 2.0, 3.0]\n')
    done = subprocess.run([sys.executable, '-m', 'ddarm_tuner.node', '--ros-args', '--params-file', str(parameters)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert str(parameters) in done.stderr and 'tunr' in done.stderr and 'Traceback' not in done.stderr


def test_a_bag_on_a_full_disk_is_a_named_refusal_not_a_traceback(tmp_path):
    """RLIMIT_FSIZE makes writes past a size fail as a full disk does (EFBIG rather than ENOSPC)."""
    script = ('import resource, signal, sys\n'
              'signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n'
              'resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))\n'
              'from ddarm.cli.main import main\n'
              'sys.exit(main(sys.argv[1:]))\n')
    bag = tmp_path / 'bag'
    done = subprocess.run([sys.executable, '-c', script, 'episode', '--controller', 'computed_torque', '--omega',
                           '15', '--ros', '--storage', 'sqlite3', '--bag', str(bag)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert f'{bag}: cannot write the bag' in done.stderr and 'Traceback' not in done.stderr, done.stderr


def test_output_locations_that_cannot_be_written_are_refused_before_any_work(capsys, tmp_path):
    a_file = tmp_path / 'a_file'
    a_file.write_text('')
    tune = ['tune', '--controller', 'computed_torque', '--index', '2.5', '--budget', '100000']
    assert main([*tune, '--runs', str(a_file)]) == 2
    assert f'{a_file} is not a folder' in capsys.readouterr().err
    assert main([*tune, '--runs', str(tmp_path / 'runs'), '--out', str(tmp_path / 'missing' / 'gains.yaml')]) == 2
    assert 'does not exist' in capsys.readouterr().err
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--ros',
                 '--bag', str(a_file / 'bag')]) == 2
    assert f'{a_file} is a file, not a folder' in capsys.readouterr().err
    assert not (tmp_path / 'runs').exists()


def test_the_tuner_refuses_an_output_root_that_is_a_file(tmp_path):
    a_file = tmp_path / 'a_file'
    a_file.write_text('')
    done = subprocess.run([str(DDARM), 'tuner', '--ros-args', '-p', 'kp:=[1.0,2.0,3.0]', '-p', 'kv:=[1.0,2.0,3.0]',
                           '-p', f'output_root:={a_file}'], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and 'is not a folder' in done.stderr and 'Traceback' not in done.stderr, done.stderr


def test_a_bug_is_not_dressed_as_a_refusal(monkeypatch):
    """Only ddarm's named errors (DdarmError) and the system's refusals of paths become exit 2: a bug keeps
    its traceback."""
    import ddarm.cli.episode as cli

    def broken(spec):
        raise ValueError('a bug')

    monkeypatch.setattr(cli, 'run_episode', broken)
    with pytest.raises(ValueError, match='a bug'):
        main(['episode', '--controller', 'computed_torque', '--omega', '15'])


@pytest.mark.parametrize('arguments, problem', [
    (['--max-error', '1', '1'], '--max-error needs one value or 3 values'),
    (['--max-error', '1', '--disturbance', '1', '1'], '--disturbance needs 3 values'),
    (['--max-error', '1', '--mass-error', '0.1'], '--mass-error needs 3 values'),
    (['--max-error', '1'], 'the steady-state errors are zero at every ω'),
])
def test_omega_refuses_what_it_cannot_compute(capsys, tmp_path, arguments, problem):
    extra = [] if '--disturbance' in arguments or '--mass-error' in arguments or arguments == ['--max-error', '1'] \
        else ['--disturbance', '0', '20', '5']
    assert main(['omega', '--controller', 'pd_gravity', *arguments, *extra, '--runs', str(tmp_path)]) == 2
    assert problem in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_a_gains_file_that_is_not_text_is_refused(tmp_path):
    gains = tmp_path / 'gains.yaml'
    gains.write_bytes(b'\xff\xfe\x00binary')
    done = subprocess.run([str(DDARM), 'tuner', '--ros-args', '-p', f'gains_file:={gains}',
                           '-p', f'output_root:={tmp_path / "runs"}'], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and str(gains) in done.stderr and 'Traceback' not in done.stderr, done.stderr


@pytest.mark.parametrize('jobs, message', [('0', '0 is not in [1, 64]'), ('65', '65 is not in [1, 64]'),
                                           ('two', "'two' is not a whole number")])
def test_a_bad_jobs_count_is_refused_before_any_search(capsys, tmp_path, jobs, message):
    with pytest.raises(SystemExit) as stopped:
        main(['reproduce', '--quick', '--jobs', jobs, '--out', str(tmp_path / 'paper')])
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert '--jobs' in err and message in err and 'searching' not in err
    assert not (tmp_path / 'paper').exists()


NOT_UTF8 = 'is not UTF-8 text, and ROS 2 (node parameters, parameter files, bags) takes only UTF-8'


@pytest.mark.parametrize('command', [
    ['tune', '--controller', 'pd_gravity', '--index', 'I', '--urdf', 'arm\udcff.urdf'],
    ['episode', '--controller', 'computed_torque', '--omega', '15', '--ros', '--bag', 'bag\udcff'],
    ['episode', '--controller', 'computed_torque', '--omega', '15', '--realtime', '--urdf', 'arm\udcff.urdf'],
    ['controller', 'computed_torque', '--ros-args', '--params-file', 'gains\udcff.yaml'],
])
def test_a_non_utf8_argument_of_a_command_that_starts_ros_is_refused_first_naming_it(tmp_path, command):
    # A file name with a byte that is not UTF-8, as a shell hands it over (Python keeps it as a lone surrogate).
    (tmp_path / 'arm\udcff.urdf').write_bytes((ROOT / 'config' / 'ddarm.urdf').read_bytes())
    done = subprocess.run([os.fsencode(DDARM), *map(os.fsencode, command), b'--runs', os.fsencode(tmp_path / 'runs')]
                          if command[0] == 'tune' else [os.fsencode(DDARM), *map(os.fsencode, command)],
                          cwd=tmp_path, capture_output=True, timeout=60)
    err = done.stderr.decode('utf-8', 'backslashreplace')
    assert done.returncode == 2 and 'Traceback' not in err, err
    assert err.startswith(f'ddarm {command[0]}: the argument ') and NOT_UTF8 in err and '\\xff' in err
    assert sorted(path.name for path in tmp_path.iterdir()) == ['arm\udcff.urdf'], 'nothing made, nothing searched'


@pytest.mark.parametrize('start', [[os.fsencode(ROOT / 'scripts' / 'computed_torque')],
                                   [b'-m', b'ddarm_control.node', b'pd_gravity'],
                                   [os.fsencode(ROOT / 'scripts' / 'plant')]])
def test_a_node_started_with_a_non_utf8_argument_refuses_naming_it(start):
    done = subprocess.run([os.fsencode(sys.executable), *start, b'--ros-args', b'-r', b'__node:=node\xff'],
                          capture_output=True, timeout=60)
    out = done.stdout.decode('utf-8', 'backslashreplace')
    assert done.returncode == 2 and 'Traceback' not in out + done.stderr.decode(errors='replace'), out
    assert 'refused to start: the argument __node:=node\\xff ' + NOT_UTF8 in out


def test_an_in_process_episode_takes_a_non_utf8_file_name(tmp_path):
    (tmp_path / 'arm\udcff.urdf').write_bytes((ROOT / 'config' / 'ddarm.urdf').read_bytes())
    done = subprocess.run([os.fsencode(DDARM), b'episode', b'--controller', b'computed_torque', b'--omega', b'15',
                           b'--urdf', b'arm\xff.urdf'], cwd=tmp_path, capture_output=True, timeout=60)
    assert done.returncode == 0 and b'I1 (2.5)' in done.stdout, done.stderr


def test_a_refusal_naming_a_name_of_megabytes_shows_its_ends_only(tmp_path, capsys):
    name = 'j' * 2_000_000 + 'END'
    urdf = tmp_path / 'arm.urdf'
    urdf.write_text((ROOT / 'config' / 'ddarm.urdf').read_text().replace('name="joint2"', f'name="{name}"'))
    assert main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf)]) == 2
    err = capsys.readouterr().err
    assert len(err) < 1000 and err.startswith(f'ddarm episode: URDF {urdf}: give a motion file'), err
    assert f"'{'j' * 199}…<1999706 characters>…{'j' * 95}END', 'joint3']" in err  # the word is 'j…END',


def test_a_node_refusal_naming_a_name_of_megabytes_shows_its_ends_only(tmp_path):
    parameters = tmp_path / 'gains.yaml'
    parameters.write_text('computed_torque:\n  ros__parameters:\n    kp: [1.0, 2.0, 3.0]\n    kv: [1.0, 2.0, 3.0]\n'
                          f"    motion: {'m' * 100_000}.yaml\n")
    done = subprocess.run([sys.executable, str(ROOT / 'scripts' / 'computed_torque'), '--ros-args', '--params-file',
                           str(parameters)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and 'refused to start' in done.stdout and 'characters>…' in done.stdout
    assert len(done.stdout) < 2000, done.stdout[:3000]


# Environments ROS 2 cannot start in, each with the words of its refusal: rcl's own were a traceback (RCLError) or Fast
# DDS's coloured log line, and ROS_DOMAIN_ID=-1 was taken (rcl's strtoul made it domain 0).
NO_LOG_FOLDER = 'ROS 2 finds no folder for its log files: ROS_LOG_DIR, ROS_HOME and HOME are all unset or empty'
BAD_ROS_ENVIRONMENTS = {
    'no HOME': ({'HOME': None}, NO_LOG_FOLDER),
    'empty HOME': ({'HOME': ''}, NO_LOG_FOLDER),
    'domain abc': ({'ROS_DOMAIN_ID': 'abc'}, "ROS_DOMAIN_ID is 'abc', and ROS 2 takes a whole number from 0 to 232"),
    'domain 233': ({'ROS_DOMAIN_ID': '233'}, "ROS_DOMAIN_ID is '233', and ROS 2 takes a whole number from 0 to 232"),
    'domain 300': ({'ROS_DOMAIN_ID': '300'}, "ROS_DOMAIN_ID is '300', and ROS 2 takes a whole number from 0 to 232"),
    'domain huge': ({'ROS_DOMAIN_ID': '99999999999'}, "ROS_DOMAIN_ID is '99999999999', and ROS 2 takes a whole"),
    'domain -1': ({'ROS_DOMAIN_ID': '-1'}, "ROS_DOMAIN_ID is '-1', and ROS 2 takes a whole number from 0 to 232"),
    'log folder a file': ({'ROS_LOG_DIR': '{tmp}/logs'}, "ROS_LOG_DIR is '{tmp}/logs', and that is not a folder"),
    'ROS_HOME a file': ({'ROS_HOME': '{tmp}/logs'},
                        "ROS_HOME is '{tmp}/logs', so ROS 2 writes its log files in {tmp}/logs/log, and that "
                        '({tmp}/logs) is not a folder'),
    'log folder unwritable': ({'ROS_LOG_DIR': '{tmp}/locked/ros'},
                              "ROS_LOG_DIR is '{tmp}/locked/ros', and that folder ({tmp}/locked, where it would be "
                              'made) cannot be written'),
}


def _bad_ros_environment(tmp_path: Path, case: str) -> tuple[dict, list[str], str, list[str]]:
    """The environment of `case` (HOME a folder not yet made unless the case sets it, so a log folder rcl made would
    show), the command prefix that keeps a root test from writing where the user could not, the refusal's words,
    and the names in tmp_path before the command."""
    changes, words = BAD_ROS_ENVIRONMENTS[case]
    (tmp_path / 'logs').write_text('a file, not a folder\n')
    (tmp_path / 'locked').mkdir(mode=0o555)
    prefix = []
    if 'unwritable' in case and os.geteuid() == 0:  # root writes anywhere: run without its capabilities
        if shutil.which('setpriv') is None:
            pytest.skip('running as root, and no setpriv to drop the capabilities that write anywhere')
        prefix = ['setpriv', '--inh-caps=-all', '--bounding-set=-all']
    environment = {key: value for key, value in os.environ.items() if key not in ('ROS_LOG_DIR', 'ROS_HOME')}
    environment['HOME'] = str(tmp_path / 'home')
    for key, value in changes.items():
        if value is None:
            environment.pop(key, None)
        else:
            environment[key] = value.format(tmp=tmp_path)
    return environment, prefix, words.format(tmp=tmp_path), sorted(path.name for path in tmp_path.iterdir())


EPISODE = ['episode', '--controller', 'computed_torque', '--omega', '15', '--duration', '0.2', '--ros']
TUNE = ['tune', '--controller', 'pd_gravity', '--index', 'I', '--budget', '5', '--runs', 'runs']


@pytest.mark.parametrize('command, case', [
    pytest.param(command, case, id=f'{command[0]}-{case}') for command, case in
    [(EPISODE, case) for case in BAD_ROS_ENVIRONMENTS]
    + [(TUNE, case) for case in ('no HOME', 'domain -1', 'log folder unwritable')]])  # tune: refused before its search
def test_a_command_that_starts_ros_refuses_an_environment_ros_cannot_start_in_first(tmp_path, command, case):
    environment, prefix, words, before = _bad_ros_environment(tmp_path, case)
    done = subprocess.run([*prefix, str(DDARM), *command], cwd=tmp_path, env=environment, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and 'Traceback' not in done.stderr + done.stdout, done.stderr
    assert done.stderr.startswith(f'ddarm {command[0]}: {words}') and done.stderr.count('\n') == 1, done.stderr
    assert done.stdout == '', 'nothing searched, no episode run'
    assert sorted(path.name for path in tmp_path.iterdir()) == before, 'nothing made: no log folder, no run'


@pytest.mark.parametrize('case', BAD_ROS_ENVIRONMENTS)
@pytest.mark.parametrize('script', ['computed_torque', 'plant'])
def test_a_node_refuses_an_environment_ros_cannot_start_in(tmp_path, case, script):
    environment, prefix, words, before = _bad_ros_environment(tmp_path, case)
    done = subprocess.run([*prefix, sys.executable, str(ROOT / 'scripts' / script)], cwd=tmp_path, env=environment,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and 'Traceback' not in done.stderr + done.stdout, done.stdout + done.stderr
    assert done.stdout.startswith(f'{script}: refused to start: {words}') and done.stdout.count('\n') == 1, done.stdout
    assert done.stderr == '' and sorted(path.name for path in tmp_path.iterdir()) == before


@pytest.mark.parametrize('domain_id', [None, '', '0', '232'])
def test_ros_takes_a_domain_id_unset_empty_or_in_its_range(tmp_path, domain_id):
    from ddarm.ros.executable import ros_environment_problem

    environment = {'HOME': str(tmp_path)} | ({} if domain_id is None else {'ROS_DOMAIN_ID': domain_id})
    assert ros_environment_problem([], environment) is None


def test_ros_finds_its_log_folder_as_rcl_does(tmp_path):
    from ddarm.ros.executable import ros_environment_problem

    (tmp_path / 'file').write_text('')
    assert ros_environment_problem([], {'ROS_HOME': str(tmp_path / 'ros')}) is None  # no HOME needed
    assert ros_environment_problem([], {'ROS_LOG_DIR': str(tmp_path / 'a' / 'b'), 'HOME': '/'}) is None
    assert ros_environment_problem([], {'ROS_LOG_DIR': '', 'ROS_HOME': '', 'HOME': str(tmp_path)}) is None
    assert ros_environment_problem([], {'ROS_LOG_DIR': '~/logs', 'HOME': str(tmp_path)}) is None
    assert "ROS_LOG_DIR is '~/logs', and ROS 2 reads its ~ from HOME" in ros_environment_problem(
        [], {'ROS_LOG_DIR': '~/logs', 'ROS_HOME': str(tmp_path)})
    assert 'is not a folder' in ros_environment_problem([], {'HOME': str(tmp_path / 'file')})
    # rcl writes no log file with --disable-external-lib-logs among the ROS arguments (the last of it and --enable-).
    assert ros_environment_problem(['node', '--ros-args', '--disable-external-lib-logs'], {}) is None
    assert ros_environment_problem(['node', '--ros-args', '--disable-external-lib-logs', '--enable-external-lib-logs'],
                                   {}) is not None
    assert ros_environment_problem(['node', '--disable-external-lib-logs'], {}) is not None  # not a ROS argument
    assert sorted(path.name for path in tmp_path.iterdir()) == ['file'], 'nothing made'


def test_a_ros_episode_runs_with_an_explicit_domain_id_and_its_log_folder_from_ros_home(tmp_path):
    environment = {key: value for key, value in os.environ.items() if key not in ('HOME', 'ROS_LOG_DIR')}
    environment['ROS_HOME'] = str(tmp_path / 'ros')
    assert environment['ROS_DOMAIN_ID'].isdigit()  # the test process's own (conftest.py), explicit
    done = subprocess.run([str(DDARM), 'episode', '--controller', 'computed_torque', '--omega', '15', '--ros',
                           '--duration', '0.05'], cwd=tmp_path, env=environment, capture_output=True, text=True,
                          timeout=180)
    assert done.returncode == 0 and 'I1 (2.5)' in done.stdout, done.stderr
    assert any((tmp_path / 'ros' / 'log').iterdir()), 'rcl wrote its log files under ROS_HOME'


def test_bench_refuses_a_negative_seed_before_any_episode():
    done = subprocess.run([str(DDARM), 'bench', '--episodes', '20', '--scalar-episodes', '2', '--seed', '-1'],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and 'Traceback' not in done.stderr and done.stdout == '', done.stderr
    assert done.stderr == ('ddarm bench: error: argument --seed: -1 is not 0 or more (a NumPy seed) '
                           '(see ddarm bench --help)\n')


@pytest.mark.parametrize('arguments, option, problem', [
    (['tune', '--controller', 'computed_torque', '--index', 'I', '--seed', '-1'], '--seed', '-1 is not 0 or more'),
    (['pareto', '--controller', 'computed_torque', '--seed', '-1'], '--seed', '-1 is not 0 or more'),
    (['episode', '--controller', 'computed_torque', '--omega', '15', '--ros', '--bag', ''], '--bag', 'an empty path'),
    (['episode', '--controller', 'computed_torque', '--omega', '15', '--ros', '--bag', 'a\nb'], '--bag',
     'control character U+000A'),
])
def test_a_seed_or_bag_no_run_takes_is_refused_when_parsed(capsys, tmp_path, arguments, option, problem):
    with pytest.raises(SystemExit) as refused:
        main([*arguments, *(['--runs', str(tmp_path)] if arguments[0] == 'tune' else [])])
    err = capsys.readouterr().err
    assert refused.value.code == 2 and f'error: argument {option}: ' in err and problem in err, err
    assert not any(tmp_path.iterdir())
