"""docs/results.md lists what the commands write: its tables cannot drift from the JSON and run folders unnoticed.

Each command runs once, small, in a temporary folder (config/ linked in). The test compares the top-level keys it
prints, the entries of its run folder and the keys of its summary.json with the page's tables. A key whose meaning
starts with "Only" is conditional: each run below names the conditional keys it must produce, and the others must be
absent. results.json of `ddarm reproduce` is not run: its keys are the fields schema.py declares.
"""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / 'docs' / 'results.md'
DDARM = Path(sys.executable).with_name('ddarm')
UR5 = ['--urdf', 'config/arms/ur5/ur5.urdf', '--motion', 'config/arms/ur5/ur5-motion.yaml']
LAW = 'computed_torque'

RUN = 'The run folder'
EPISODE, SCORE, BENCH = '`ddarm episode --json`', '`ddarm score --json`', '`ddarm bench --json`'
TUNE, VALIDATE, OMEGA = '`ddarm tune`', '`ddarm validate`', '`ddarm omega`'
REPRODUCE = '`ddarm reproduce`: results.json'
STABILITY, PARETO, IDENTIFY = '`ddarm stability --json`', '`ddarm pareto --json`', '`ddarm identify --json`'
CAMPAIGN, TRANSFER = '`ddarm campaign`', '`ddarm transfer`'
JSON, FOLDER, SUMMARY = '`--json`', 'Run folder', 'summary.json'

# Conditional rows this test does not produce (each costs a minute or more), named so that a new one is noticed.
NOT_RUN = {(BENCH, ''): {'ros'}, (TRANSFER, FOLDER): {'identified-sample-<k>.urdf'}}

_ROW = re.compile(r'^\| `([^`]+)` \|')


def page_tables(text: str | None = None) -> dict[tuple[str, str], dict[str, bool]]:
    """{(## heading, ### heading or ''): {key or file: conditional}} of every table row whose first cell is in
    backticks; conditional when its last cell (the meaning) starts with "Only"."""
    tables: dict[tuple[str, str], dict[str, bool]] = {}
    section = subsection = ''
    for line in (PAGE.read_text() if text is None else text).splitlines():
        if line.startswith('## '):
            section, subsection = line[3:].strip(), ''
        elif line.startswith('### '):
            subsection = line[4:].strip()
        elif match := _ROW.match(line):
            cells = re.split(r'(?<!\\)\|', line.strip().strip('|'))
            rows = tables.setdefault((section, subsection), {})
            assert match.group(1) not in rows, f'{match.group(1)} listed twice under {section} / {subsection}'
            rows[match.group(1)] = cells[-1].strip().startswith('Only')
    return tables


TABLES = page_tables()
# Every conditional row a run below produces, by table: checked against the page at the end.
_PRODUCED: dict[tuple[str, str], set[str]] = {}


def table(section: str, subsection: str = '') -> dict[str, bool]:
    assert (section, subsection) in TABLES, f'docs/results.md has no table under {section} / {subsection}'
    return {key.replace('<controller>', LAW): optional for key, optional in TABLES[section, subsection].items()}


def expected(section: str, subsection: str = '', produced: set[str] = frozenset(), base: set[str] = frozenset()
             ) -> set[str]:
    """The keys the page says this run writes: the table's unconditional keys, the conditional ones it produced, and
    `base` (the common keys of a run folder)."""
    rows = table(section, subsection)
    unknown = set(produced) - {key for key, optional in rows.items() if optional}
    assert not unknown, f'{sorted(unknown)} are not conditional rows under {section} / {subsection}'
    _PRODUCED.setdefault((section, subsection), set()).update(produced)
    return {key for key, optional in rows.items() if not optional} | set(produced) | set(base)


def same(written, listed: set[str], what: str) -> None:
    written = set(written)
    assert written == listed, (f'{what}: written but not in docs/results.md: {sorted(written - listed)}; '
                               f'in docs/results.md but not written: {sorted(listed - written)}')


def run(folder: Path, *arguments: str, code: int = 0) -> str:
    done = subprocess.run([str(DDARM), *arguments], cwd=folder, capture_output=True, text=True, timeout=600)
    assert done.returncode == code, f'ddarm {" ".join(arguments)}: exit {done.returncode}\n{done.stderr}'
    return done.stdout


def run_json(folder: Path, *arguments: str, code: int = 0) -> dict:
    return json.loads(run(folder, *arguments, '--json', code=code))


def entries(folder: Path) -> set[str]:
    return {path.name + ('/' if path.is_dir() else '') for path in folder.iterdir()}


def summary_keys(folder: Path) -> dict:
    return json.loads((folder / 'summary.json').read_text())


@pytest.fixture(scope='module')
def work(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp('results-doc')
    (folder / 'config').symlink_to(ROOT / 'config')
    return folder


def common_files() -> set[str]:
    return expected(RUN, 'Files')


def common_summary() -> set[str]:
    return expected(RUN, SUMMARY, {'finished'})


def test_the_common_summary_keys_are_what_a_run_folder_writes(tmp_path):
    from ddarm.recording.runs import RunFolder

    folder = RunFolder('complete', tmp_path, command='ddarm test')
    folder.finish('complete')
    same(summary_keys(folder.path), common_summary(), 'a complete run')
    same(entries(folder.path), common_files(), 'a run folder')
    with pytest.raises(RuntimeError):
        with RunFolder('failed', tmp_path, command='ddarm test'):
            raise RuntimeError('a test')
    same(summary_keys(tmp_path / 'failed'), expected(RUN, SUMMARY, {'finished', 'error'}), 'a failed run')
    folder = RunFolder('log', tmp_path, command='ddarm test')
    folder._handler.failure = 'run.log: cannot write the log: a test'  # what a full disk leaves
    folder.finish('complete')
    same(summary_keys(folder.path), expected(RUN, SUMMARY, {'finished', 'log_failure'}), 'a run whose log failed')


def test_episode_json(work):
    same(run_json(work, 'episode', '--controller', LAW, '--omega', '15'), expected(EPISODE), 'ddarm episode --json')
    same(run_json(work, 'episode', '--controller', LAW, '--omega', '10', *UR5, '--mjcf', 'config/arms/ur5/ur5.urdf'),
         expected(EPISODE, '', {'robot'}), 'ddarm episode --mjcf --json')


def test_episode_through_the_graph_and_score_json(work):
    printed = run_json(work, 'episode', '--controller', LAW, '--omega', '15', '--limited', '--ros', '--bag', 'bag')
    same(printed, expected(EPISODE, '', {'saturated_joints', 'plant_report'}), 'ddarm episode --limited --ros --json')
    lines = run(work, 'score', 'bag', '--json').splitlines()
    assert len(lines) == 1
    same(json.loads(lines[0]), expected(SCORE, '', {'saturated_joints'}), 'ddarm score --json')


@pytest.fixture(scope='module')
def tuned(work) -> tuple[dict, Path]:
    """A robust tuning on the UR5 (its YAML, at work/gains.yaml, is validated below)."""
    printed = run_json(work, 'tune', '--controller', LAW, '--index', 'I', *UR5, '--budget', '200',
                       '--robust-tau', '0', '0.05', '--runs', 'runs', '--run', 'tune', '--out', 'gains.yaml')
    return printed, work / 'runs' / 'tune'


def test_tune(tuned):
    printed, folder = tuned
    assert printed['agree']
    same(printed, expected(TUNE, JSON, {'robust', 'certificate'}), 'ddarm tune --json')
    same(entries(folder), expected(TUNE, FOLDER, {f'{LAW}.yaml'}, common_files()), 'the tune run folder')
    summary = summary_keys(folder)
    same(summary, expected(TUNE, SUMMARY, base=common_summary()), 'the tune summary.json')
    same(summary['tune'], set(printed) - {'run'}, "the tune summary.json's tune (the --json object without run)")


def test_validate(work, tuned):
    printed = run_json(work, 'validate', '--gains', 'gains.yaml', '--mjcf', 'config/arms/ur5/ur5.urdf', '--ros',
                       '--runs', 'runs', '--run', 'validate')
    folder = work / 'runs' / 'validate'
    same(printed, expected(VALIDATE, JSON), 'ddarm validate --json')
    same(entries(folder), expected(VALIDATE, FOLDER, {'bags/'}, common_files()), 'the validate run folder')
    same(summary_keys(folder), expected(VALIDATE, SUMMARY, base=common_summary()), 'the validate summary.json')


def test_omega(work):
    printed = run_json(work, 'omega', '--controller', LAW, '--max-error', '0.5', '--disturbance', '0', '10', '0',
                       '--runs', 'runs', '--run', 'omega')
    folder = work / 'runs' / 'omega'
    same(printed, expected(OMEGA, JSON, {'gains_files'}), 'ddarm omega --json')
    same(entries(folder), expected(OMEGA, FOLDER, {f'{LAW}.yaml'}, common_files()), 'the omega run folder')
    summary = summary_keys(folder)
    same(summary, expected(OMEGA, SUMMARY, base=common_summary()), 'the omega summary.json')
    same(summary['omega'], set(printed) - {'run'}, "the omega summary.json's omega (the --json object without run)")


def test_bench_json(work):
    same(run_json(work, 'bench', '--episodes', '200', '--scalar-episodes', '5'), expected(BENCH), 'ddarm bench --json')


def test_stability_json(work):
    same(run_json(work, 'stability'), expected(STABILITY), 'ddarm stability --json')
    same(run_json(work, 'stability', '--controller', 'pd_gravity', '--delay', '0', '--period', '0.01'),
         expected(STABILITY, '', {'period', 'joint_names', 'modes'}), 'ddarm stability --controller pd_gravity --json')


def test_pareto_json(work):
    same(run_json(work, 'pareto', '--controller', LAW, '--budget', '200', '--tune-budget', '200', '--points', '5'),
         expected(PARETO), 'ddarm pareto --json')


def two_link_robot(work: Path) -> None:
    """test_identify.py's two-link robot (robot.xml) and its nominal URDF (nominal.urdf)."""
    from test_identify import ROBOT_MJCF
    from two_link import URDF

    (work / 'robot.xml').write_text(ROBOT_MJCF)
    (work / 'nominal.urdf').write_text(URDF)


def test_identify_json(work):
    """On two small excitation bags of test_identify.py's two-link robot (one fitted, one held out)."""
    from test_identify import excitation

    two_link_robot(work)
    for name, phase in (('fit', 0.0), ('check', 0.7)):
        excitation(work / f'{name}.yaml', 6.0, phase)
        run(work, 'episode', '--controller', LAW, '--omega', '15', '--urdf', 'nominal.urdf', '--motion',
            f'{name}.yaml', '--mjcf', 'robot.xml', '--ros', '--bag', name, '--json')
    printed = run_json(work, 'identify', 'fit', '--validate', 'check', '--urdf', 'nominal.urdf', '--out',
                       'identified.urdf')
    same(printed, expected(IDENTIFY), 'ddarm identify --json')


def test_campaign(work):
    (work / 'campaign.yaml').write_text(f'index: I\nbudget: 200\narms:\n  - name: paper\nmotions:\n'
                                        f'  - {{name: t1, trajectory: 1}}\ncontrollers: [{LAW}]\nscenarios:\n'
                                        f'  - name: nominal\n')
    (work / 'runs').mkdir(exist_ok=True)
    printed = run_json(work, 'campaign', 'campaign.yaml', '--out', 'runs/campaign', '--jobs', '1')
    folder = work / 'runs' / 'campaign'
    produced = {'SUMMARY.md', 'index-per-job.png'}
    same(entries(folder), expected(CAMPAIGN, FOLDER, produced, common_files()), 'the campaign run folder')
    summary = summary_keys(folder)
    same(summary, expected(CAMPAIGN, SUMMARY, {'table', 'plot'}, common_summary()), 'the campaign summary.json')
    assert printed == summary, 'ddarm campaign --json prints summary.json'


def test_transfer(work):
    """On test_identify.py's two-link robot, with small budgets and a short excitation."""
    from test_identify import excitation

    two_link_robot(work)
    excitation(work / 'transfer-motion.yaml', 6.0, 0.0)
    (work / 'runs').mkdir(exist_ok=True)
    printed = run_json(work, 'transfer', '--controller', LAW, '--urdf', 'nominal.urdf', '--motion',
                       'transfer-motion.yaml', '--mjcf', 'robot.xml', '--budget', '100', '--excite-duration', '3',
                       '--runs', 'runs', '--run', 'transfer')
    folder = work / 'runs' / 'transfer'
    same(printed, expected(TRANSFER, JSON), 'ddarm transfer --json')
    same(entries(folder), expected(TRANSFER, FOLDER, base=common_files()), 'the transfer run folder')
    summary = summary_keys(folder)
    same(summary, expected(TRANSFER, SUMMARY, base=common_summary()), 'the transfer summary.json')


def test_reproduce_results_json_keys_are_the_schema():
    from ddarm.paper.schema import Results

    rows = table(REPRODUCE)
    assert not any(rows.values()), 'results.json has no conditional keys: every field is written'
    same({field.name for field in dataclasses.fields(Results)}, set(rows), 'results.json (ddarm/paper/schema.py)')


def test_every_conditional_row_is_produced_by_a_run_or_named_as_not_run(request):
    """Last in the file: the runs above have recorded the conditional rows they produced. Only when every test of
    the file was collected (not with -k); a table whose run failed before checking it is left out."""
    module = sys.modules[__name__]
    collected = {item.name for item in request.session.items if item.module is module}
    if collected != {name for name in dir(module) if name.startswith('test_')}:
        pytest.skip('not every test of the file is run')
    for heading, rows in TABLES.items():
        if heading not in _PRODUCED:
            continue
        conditional = {key.replace('<controller>', LAW) for key, optional in rows.items() if optional}
        left = conditional - _PRODUCED.get(heading, set()) - NOT_RUN.get(heading, set())
        assert not left, f'{heading}: conditional rows no test run produces: {sorted(left)}'


def test_the_page_parser_reads_the_conditions():
    rows = page_tables('## A\n\n| key | type | meaning |\n|---|---|---|\n| `x` | array | the \\| e \\| |\n'
                       '| `y` | object | Only with --z: w |\n')
    assert rows == {('A', ''): {'x': False, 'y': True}}
