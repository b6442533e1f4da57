"""`ddarm campaign`: the file read strictly (every refusal before any search, naming the key or job), the product
expanded in order, the searches the same in turn, on the process pool and as Ray tasks on a local cluster, every
summary number from a bag, and a failed job reported as failed."""

import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from ddarm.cli.main import main
from ddarm.interrupts import Interrupted
from ddarm.recording.bags import score_bag
from ddarm.tuning.campaign import CampaignError, load_campaign, parse_campaign, search_jobs
from ddarm.tuning.jobs import run_jobs

ROOT = Path(__file__).resolve().parents[1]
Z1 = ROOT / 'config' / 'arms' / 'z1'
# Two small searches on T = 0.5 s: what every run of the tiny campaign computes.
TINY = """
index: I
method: cma
budget: 200
omegas: [12, 15]
motions:
  - {name: t1, trajectory: 1, duration: 0.5}
controllers: [computed_torque, pd_gravity]
"""
# The fields of a job's record that a search and its bag decide: equal wherever the search ran.
RESULT_FIELDS = ('name', 'status', 'kp', 'kv', 'search_index', 'in_process', 'I1', 'I2', 'I', 'bag_index', 'bag')


def write(folder: Path, text: str, name: str = 'campaign.yaml') -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(text))
    return path


def test_the_example_campaign_parses_and_expands():
    campaign = load_campaign(ROOT / 'config' / 'campaigns' / 'example.yaml')
    assert [job.name for job in campaign.jobs] == [
        f'paper.t1.{law}.{scenario}' for law in ('pd_gravity', 'computed_torque')
        for scenario in ('nominal', 'payload', 'push')] + ['z1-computed-torque']
    payload, push, z1 = campaign.jobs[1], campaign.jobs[2], campaign.jobs[-1]
    assert payload.template.mass_scale == (1.0, 1.0, 1.5) and payload.template.external_torque is None
    assert push.template.external_torque == (0.0, 20.0, 5.0) and push.template.tau == 0.05
    assert z1.template.urdf == str(Z1 / 'z1.urdf') and z1.template.motion == str(Z1 / 'z1-motion.yaml')
    assert z1.budget == 1000 and z1.template.torque_limit == 'urdf' and payload.budget == 1500
    # The one warning is a fact of the Z1's URDF: its wrist's <dynamics> damping and friction stop it within a period.
    (warning,) = campaign.warnings
    assert warning.startswith("z1-computed-torque: joint 'joint6'") and 'within one sampling period' in warning


def test_the_old_keys_laws_and_law_are_read_as_controllers_and_controller_with_a_notice(tmp_path):
    from ddarm.deprecation import DeprecatedName

    old = 'index: I\nlaws: [pd_gravity]\njobs: [{name: listed, law: computed_torque}]\n'
    new = 'index: I\ncontrollers: [pd_gravity]\njobs: [{name: listed, controller: computed_torque}]\n'
    with pytest.warns(DeprecatedName) as notices:
        campaign = parse_campaign(old, tmp_path / 'old.yaml')
    assert sorted(str(notice.message).split(': ')[-1] for notice in notices) == [
        "'law' is deprecated, read as 'controller' (give 'controller' instead)",
        "'laws' is deprecated, read as 'controllers' (give 'controllers' instead)"]
    assert campaign.jobs == parse_campaign(new, tmp_path / 'new.yaml').jobs
    assert [job.controller for job in campaign.jobs] == ['pd_gravity', 'computed_torque']
    with pytest.raises(CampaignError, match=r'controllers given twice, as controllers .* deprecated name laws'):
        parse_campaign('index: I\nlaws: [pd_gravity]\ncontrollers: [computed_torque]\n', tmp_path / 'both.yaml')


def test_the_product_is_every_arm_motion_law_and_scenario_in_order_then_the_listed_jobs(tmp_path):
    campaign = parse_campaign(textwrap.dedent(f"""
        index: 3.2
        budget: 300
        delay: 0
        arms: [{{name: paper}}, {{urdf: {ROOT / 'config' / 'ddarm.urdf'}}}]
        motions: [{{trajectory: 1}}, {{name: short, trajectory: 2, duration: 0.5}}]
        controllers: [pd_gravity, computed_torque]
        scenarios: [{{}}, {{name: heavy, mass_scale: 1.2, tau: 0.1}}]
        jobs:
          - {{controller: computed_torque, index: I1, seed: 3, omegas: [10],
             scenario: {{name: pz, external_torque: [0, 1, 2]}}}}
    """), tmp_path / 'product.yaml')
    names = [job.name for job in campaign.jobs]
    assert names[:4] == ['paper.trajectory-1.pd_gravity.nominal', 'paper.trajectory-1.pd_gravity.heavy',
                         'paper.trajectory-1.computed_torque.nominal', 'paper.trajectory-1.computed_torque.heavy']
    assert names[4] == 'paper.short.pd_gravity.nominal' and names[8] == 'ddarm.trajectory-1.pd_gravity.nominal'
    assert len(names) == 2 * 2 * 2 * 2 + 1 and names[-1] == 'paper.trajectory-1.computed_torque.pz'
    heavy, short, listed = campaign.jobs[1], campaign.jobs[4], campaign.jobs[-1]
    # The paper's 3.2 names I; one mass scale is every link's.
    assert heavy.index == 'I' and heavy.template.mass_scale == (1.2,) * 3 and heavy.template.tau == 0.1
    assert short.template.trajectory == 2 and short.template.duration == 0.5 and short.template.delay == 0
    assert (listed.index, listed.seed, listed.omegas, listed.budget) == ('I1', 3, (10.0,), 300)
    assert listed.template.external_torque == (0.0, 1.0, 2.0) and listed.template.delay == 0


PD = 'index: I\ncontrollers: [pd_gravity]\n'  # a campaign of one controller, the rest its defaults
BAD_FILES = [
    ('controllers: [pd_gravity]\nindex: I\ncolour: red\n', "the top level: unknown key 'colour'"),
    ('index: I\njobs: [{controller: pd_gravity, arm: {urdf: nowhere.urdf}}]\n', 'jobs[0].arm.urdf:'),
    ('index: I\njobs: [{controller: pd_gravity, arm: {urdf: nowhere.urdf}}]\n', 'nowhere.urdf: no such file'),
    ('index: I\njobs: [{controller: pd_gravity, motion: {file: gone.yaml}}]\n', 'jobs[0].motion.file:'),
    ('index: I\ncontrollers: [pid]\n', "controllers[0]: must be one of pd_gravity, computed_torque, got 'pid'"),
    ('index: I\ncontrollers: [pd_gravity, pd_gravity]\n', 'controllers: a controller is given twice'),
    ('index: I4\ncontrollers: [pd_gravity]\n', "index: must be one of I1, I2, I"),
    ('controllers: [pd_gravity]\n', 'no index'),
    ('index: I\nbudget: 5\ncontrollers: [pd_gravity]\n', 'budget must be a whole number of at least'),
    ('index: I\nbudget: 2.5\ncontrollers: [pd_gravity]\n', 'budget: must be a whole number of at least 1, got 2.5'),
    ('index: I\nbudget: true\ncontrollers: [pd_gravity]\n', 'budget: must be a whole number'),
    ('index: I\nseed: -1\ncontrollers: [pd_gravity]\n', 'seed: must be a whole number of at least 0'),
    ('index: I\nmethod: simplex\ncontrollers: [pd_gravity]\n', 'method: must be one of global, nelder-mead, cma'),
    ('index: I\nomegas: []\ncontrollers: [pd_gravity]\n', 'omegas: must be a non-empty list'),
    ('index: I\nomegas: [10, -1]\ncontrollers: [pd_gravity]\n', 'omegas[1]: must be positive'),
    ('index: I\nperiod: .nan\ncontrollers: [pd_gravity]\n', 'period: must be a finite number'),
    ('index: I\ntorque_limit: lots\ncontrollers: [pd_gravity]\n', 'torque_limit: must be one of none, paper, urdf'),
    ('index: I\ntorque_limit: [1, 2]\ncontrollers: [pd_gravity]\n', 'torque_limit needs 3 values'),
    (PD + 'scenarios: [{name: a, tau: 5}]\n', 'paper.trajectory-1.pd_gravity.a'),
    (PD + 'scenarios: [{name: a, mass_scale: [1, 2]}]\n', 'paper.trajectory-1.pd_gravity.a'),
    (PD + 'scenarios: [{name: a, mass_scale: 0}]\n', 'scenarios[0].mass_scale: must be positive'),
    (PD + 'scenarios: [{name: a, external_torque: [1, 2]}]\n', 'external'),
    (PD + 'scenarios: [{tau: 0.1}]\n', 'scenarios[0]: a scenario that changes the episode '
                                                              'needs a name'),
    (PD + 'scenarios: [{name: a}, {name: a}]\n', "scenarios: the name 'a' is given 2 times"),
    (PD + 'scenarios: [{name: a/b}]\n', 'scenarios[0].name: must be a name'),
    # paper.trajectory-1.pd_gravity. and 221 characters: 251, and .mcap makes 256, one more than a file name holds.
    (PD + f"scenarios: [{{name: {'s' * 221}, tau: 0.1}}]\n",
     f"the job paper.trajectory-1.pd_gravity.{'s' * 221} (of the product): its name 'paper.trajectory-1.pd_gravity.s"),
    (f"index: I\njobs: [{{name: {'j' * 251}, controller: pd_gravity}}]\n",
     '(251 characters) names its bag\'s storage file '
                                                                   'and gains file'),
    (PD + 'scenarios: [{name: a, payload: 2}]\n', "scenarios[0]: unknown key 'payload'"),
    (PD + 'motions: [{trajectory: 1, file: x.yaml}]\n', 'motions[0]: give one of trajectory'),
    (PD + 'motions: [{trajectory: 3}]\n', 'motions[0].trajectory: must be one of (1, 2)'),
    (PD + 'motions: [{trajectory: 1, duration: 0}]\n', 'motions[0].duration: must be '
                                                                              'positive'),
    # The Z1's 6 joints and the paper's motion of 3: the product's job is named.
    (PD + f'arms: [{{urdf: {Z1 / "z1.urdf"}}}]\n', 'the job z1.trajectory-1.pd_gravity.nominal '
                                                                          '(of the product): URDF'),
    (PD + f'arms: [{{model_urdf: {Z1 / "z1.urdf"}}}]\n', 'arms[0]: model_urdf is the model'),
    ('index: I\narms: [{name: paper}]\n', 'controllers: arms, motions and scenarios make jobs only with controllers'),
    ('index: I\n', 'no jobs'),
    ('', 'empty'),
    ('index: I\njobs: [{arm: {name: paper}}]\n', 'jobs[0]: no controller'),
    ('index: I\njobs: [{controller: pd_gravity, delay: -1}]\n', 'jobs[0].delay: must be a whole number of at least 0'),
    (PD + 'jobs: [{controller: pd_gravity}]\n', "its name 'paper.trajectory-1.pd_gravity.nominal' "
                                                                 'is also that of'),
    (PD + 'index: I1\n', 'duplicate key'),
    ('index: I\ncontrollers: [pd_gravity\n', 'not a YAML file'),
    ('- index: I\n', 'the top level: must be a mapping'),
    # YAML 1.2 reads 017 as text, not as 15 (YAML 1.1) or 17.
    ('index: I\nbudget: 017\ncontrollers: [pd_gravity]\n', "budget: must be a whole number of at least 1, got '017'"),
]


@pytest.mark.parametrize('text, named', BAD_FILES)
def test_a_bad_campaign_file_is_refused_naming_the_key_or_job_before_any_search(capsys, tmp_path, text, named):
    path = write(tmp_path, text)
    assert main(['campaign', str(path), '--out', str(tmp_path / 'run')]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'ddarm campaign: {path}: ') and named in err, err
    assert 'Traceback' not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / 'run').exists()


@pytest.mark.parametrize('kind, named', [('directory', 'is a directory, not a regular file'),
                                         ('fifo', 'is a FIFO, not a regular file')])
def test_a_urdf_or_motion_that_is_no_regular_file_is_refused_saying_what_it_is(capsys, tmp_path, kind, named):
    target = tmp_path / 'arm.urdf'
    target.mkdir() if kind == 'directory' else os.mkfifo(target)  # a FIFO is refused from its status, never opened
    for field, key in (('arm: {urdf: arm.urdf}', 'arm.urdf'),
                       (f'arm: {{urdf: {Z1 / "z1.urdf"}, model_urdf: arm.urdf}}', 'arm.model_urdf'),
                       ('motion: {file: arm.urdf}', 'motion.file')):
        path = write(tmp_path, f'index: I\njobs: [{{controller: pd_gravity, {field}}}]\n')
        assert main(['campaign', str(path), '--out', str(tmp_path / 'run')]) == 2
        err = capsys.readouterr().err
        assert err.strip() == f'ddarm campaign: {path}: jobs[0].{key}: {target} {named}', err


def test_a_missing_file_an_existing_run_folder_and_an_unreachable_cluster_are_refused(capsys, tmp_path):
    assert main(['campaign', str(tmp_path / 'none.yaml'), '--out', str(tmp_path / 'run')]) == 2
    assert 'none.yaml: cannot read the campaign file' in capsys.readouterr().err
    path = write(tmp_path, TINY)
    (tmp_path / 'taken').mkdir()
    assert main(['campaign', str(path), '--out', str(tmp_path / 'taken')]) == 2
    assert 'exists already' in capsys.readouterr().err
    with socket.socket() as unused:  # a port nothing listens on
        unused.bind(('127.0.0.1', 0))
        port = unused.getsockname()[1]
    assert main(['campaign', str(path), '--out', str(tmp_path / 'run'), '--ray', f'127.0.0.1:{port}']) == 2
    assert f'--ray 127.0.0.1:{port}: no Ray cluster answers there' in capsys.readouterr().err
    assert main(['campaign', str(path), '--out', str(tmp_path / 'run'), '--ray', 'somewhere']) == 2
    assert 'give the cluster\'s address as host:port' in capsys.readouterr().err
    assert not (tmp_path / 'run').exists()


def test_without_ray_installed_ray_is_refused_saying_how_to_install_it(capsys, tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, 'find_spec', lambda name, *rest: None if name == 'ray' else real(name, *rest))
    assert main(['campaign', str(write(tmp_path, TINY)), '--out', str(tmp_path / 'run'), '--ray', '127.0.0.1:1']) == 2
    assert "--ray needs Ray, which is not installed: pip install 'ddarm[ray]'" in capsys.readouterr().err
    assert not (tmp_path / 'run').exists()


@pytest.fixture(scope='module')
def ray_cluster():
    """A Ray cluster of 2 CPUs on this machine, listening on 127.0.0.1 only, its workers importing this checkout;
    ended through its process group (our processes only, never `ray stop`, which ends every Ray process of the
    user) however the tests end. Its address, host:port."""
    if importlib.util.find_spec('ray') is None:  # not imported here: ddarm imports it once it knows the address
        pytest.skip('Ray is not installed (pip install .[ray])')
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        port = probe.getsockname()[1]
    folder = Path(tempfile.mkdtemp(prefix='ddarm-ray-'))  # short: Ray's socket paths must fit in 107 characters
    environment = {key: value for key, value in os.environ.items() if key != 'RAY_ADDRESS'}
    # Ray replaces 127.0.0.1 with the machine's outward address, and listens on every interface, unless this is 0.
    environment.update(RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER='0', PYTHONUNBUFFERED='1',
                       PYTHONPATH=os.pathsep.join([str(ROOT), *filter(None, [os.environ.get('PYTHONPATH')])]))
    log = folder / 'head.log'
    with open(log, 'w') as output:
        head = subprocess.Popen(
            [str(Path(sys.executable).with_name('ray')), 'start', '--head', '--block', '--node-ip-address=127.0.0.1',
             f'--port={port}', '--num-cpus=2', '--include-dashboard=false', '--disable-usage-stats',
             f'--temp-dir={folder}'], env=environment, stdout=output, stderr=subprocess.STDOUT,
            start_new_session=True)
    try:
        deadline = time.monotonic() + 120.0
        # `ray start --block` says so once the head's processes are up, then waits.
        while 'Ray runtime started' not in log.read_text():
            if head.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f'ray start did not start (exit code {head.poll()}):\n{log.read_text()}')
            time.sleep(0.2)
        yield f'127.0.0.1:{port}'
    finally:
        for stop, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):  # some of its processes outlive a SIGTERM
            try:
                os.killpg(head.pid, stop)
            except ProcessLookupError:
                break  # the whole group is gone
            deadline = time.monotonic() + wait
            while time.monotonic() < deadline and _group_alive(head.pid):
                head.poll()
                time.sleep(0.2)
        head.wait()
        shutil.rmtree(folder, ignore_errors=True)


def _group_alive(group: int) -> bool:
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    return True


def test_the_searches_are_the_same_in_turn_on_the_pool_and_as_ray_tasks(tmp_path, ray_cluster):
    from ddarm.tuning.cluster import RayCluster

    jobs = search_jobs(parse_campaign(TINY, tmp_path / 'tiny.yaml'))
    in_turn, pooled = run_jobs(jobs, 1), run_jobs(jobs, 2)
    with RayCluster(ray_cluster) as cluster:
        on_ray = cluster.run_jobs(jobs)
    for job in jobs:
        searches = [found[job.key].tuning.search for found in (in_turn, pooled, on_ray)]
        for search in searches[1:]:  # the whole search, every episode it evaluated, bit for bit
            assert search.index == searches[0].index and search.episodes == searches[0].episodes
            for field in ('kp', 'kv', 'history_kp', 'history_kv', 'history_index'):
                np.testing.assert_array_equal(getattr(search, field), getattr(searches[0], field))


def test_a_campaign_locally_and_on_ray_gives_the_same_summary_every_number_from_a_bag(capsys, tmp_path, ray_cluster):
    path = write(tmp_path, TINY, 'tiny.yaml')
    summaries = {}
    for where, option in (('local', ['--jobs', '2']), ('ray', ['--ray', ray_cluster])):
        assert main(['campaign', str(path), '--out', str(tmp_path / where), '--json', *option]) == 0
        summaries[where] = json.loads(capsys.readouterr().out)
    local, on_ray = summaries['local']['jobs'], summaries['ray']['jobs']
    assert [record['name'] for record in local] == ['paper.t1.computed_torque.nominal', 'paper.t1.pd_gravity.nominal']
    for ours, theirs in zip(local, on_ray):
        assert {field: ours[field] for field in RESULT_FIELDS} == {field: theirs[field] for field in RESULT_FIELDS}
    run = tmp_path / 'local'
    summary = json.loads((run / 'summary.json').read_text())
    assert summary == summaries['local'] and summary['status'] == 'complete' and summary['failed'] == []
    assert (run / 'campaign.yaml').read_text() == path.read_text()
    table = (run / 'SUMMARY.md').read_text()
    for record in local:
        assert record['status'] == 'ok' and record['agree'] and record['bag_index'] == record['I']
        assert record['bag_index'] == pytest.approx(record['search_index'], rel=1e-9)
        scored = score_bag(run / record['bag'])  # every number the summary gives is the bag's
        assert {key: scored[key] for key in ('I1', 'I2', 'I')} == {key: record[key] for key in ('I1', 'I2', 'I')}
        node = yaml.safe_load((run / record['gains_file']).read_text())[record['controller']]
        gains = node['ros__parameters']['gains']
        assert [gains[name]['p'] for name in record['joint_names']] == record['kp']
        assert f"| {record['name']} | paper | t1 | {record['controller']} | nominal: " in table
        assert f"[{record['bag_index']:.6g}]({record['bag']}) | ok |" in table
    assert (run / 'index-per-job.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_a_job_that_fails_is_reported_as_failed_beside_the_others_and_the_exit_is_not_zero(capsys, tmp_path):
    path = write(tmp_path, """
        index: I
        method: cma
        budget: 60
        omegas: [15]
        torque_limit: paper
        motions: [{name: short, trajectory: 1, duration: 0.3}]
        controllers: [computed_torque]
        scenarios:
          - {name: nominal}
          - {name: crushing, external_torque: [0, 100000, 0]}   # far past the torque limit: every episode diverges
    """)
    assert main(['campaign', str(path), '--out', str(tmp_path / 'run'), '--jobs', '1']) == 1
    captured = capsys.readouterr()
    crushed = 'paper.short.computed_torque.crushing'
    assert f'1 of 2 jobs ok; failed: {crushed}' in captured.out
    summary = json.loads((tmp_path / 'run' / 'summary.json').read_text())
    assert summary['status'] == f'1 of 2 jobs failed: {crushed}' and summary['failed'] == [crushed]
    good, bad = summary['jobs']
    assert good['status'] == 'ok' and (tmp_path / 'run' / good['gains_file']).is_file()
    assert bad['status'] == 'failed' and bad['reason'].startswith('search: every gain set the search evaluated '
                                                                  'diverged')
    assert 'bag' not in bad and 'I' not in bad and 'gains_file' not in bad
    assert not (tmp_path / 'run' / 'gains' / f'{crushed}.yaml').exists()
    assert f'| {crushed} |' in (table := (tmp_path / 'run' / 'SUMMARY.md').read_text()) and '**FAILED**: search' in table
    # One CMA-ES run certifies nothing, and every output says so beside its number.
    assert good['converged'] is None and 'certificate' not in good and good['certainty'].startswith('not certified')
    assert f"{good['search_index']:.6g} (not certified) |" in table and good['certainty'] in table
    assert f"ok; WARNING: {good['certainty']}" in captured.out
    assert good['certainty'] in (tmp_path / 'run' / good['gains_file']).read_text()


def test_a_global_search_that_did_not_converge_says_so_in_every_output_of_the_campaign(capsys, tmp_path):
    path = write(tmp_path, """
        index: I1
        budget: 300
        motions: [{name: short, trajectory: 1, duration: 0.3}]
        controllers: [computed_torque]
    """)
    assert main(['campaign', str(path), '--out', str(tmp_path / 'run'), '--jobs', '1']) == 0
    printed = capsys.readouterr().out
    (record,) = json.loads((tmp_path / 'run' / 'summary.json').read_text())['jobs']
    assert record['status'] == 'ok' and record['method'] == 'global'
    assert record['converged'] is False and record['certificate']['converged'] is False
    # The certificate as `ddarm tune --json` gives it; the campaign's line without tune's --budget hint.
    assert record['certificate']['summary'] == f"{record['certainty']}; try --budget 600"
    assert record['certainty'].startswith('not converged: ')
    assert f"ok; WARNING: {record['certainty']}" in printed
    table = (tmp_path / 'run' / 'SUMMARY.md').read_text()
    assert f"{record['search_index']:.6g} (not converged) |" in table and record['certainty'] in table
    assert 'the search did not converge' in (tmp_path / 'run' / record['gains_file']).read_text()


def test_a_stopped_campaign_leaves_its_run_folder_marked_interrupted_with_the_jobs_checked(capsys, tmp_path,
                                                                                         monkeypatch):
    import ddarm.tuning.campaign as campaign

    checked = []
    real = campaign.check_job

    def stopped_after_one(*arguments, **options):
        if checked:
            raise Interrupted(signal.SIGINT)
        checked.append(real(*arguments, **options))
        return checked[-1]

    monkeypatch.setattr(campaign, 'check_job', stopped_after_one)
    assert main(['campaign', str(write(tmp_path, TINY)), '--out', str(tmp_path / 'run'), '--jobs', '1']) == 130
    summary = json.loads((tmp_path / 'run' / 'summary.json').read_text())
    # The job checked, and the one whose search finished but whose gains were not checked yet.
    assert summary['status'] == 'interrupted' and [(record['name'], record['status']) for record in summary['jobs']
                                                   ] == [('paper.t1.computed_torque.nominal', 'ok'),
                                                         ('paper.t1.pd_gravity.nominal', 'searched')]
    assert summary['failed'] == [] and summary['jobs'][1]['kp'] and 'bag' not in summary['jobs'][1]
    assert not (tmp_path / 'run' / 'SUMMARY.md').exists()
