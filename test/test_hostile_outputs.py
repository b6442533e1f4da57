"""Outputs made from someone else's files: every name, path and message from a URDF, a motion, a campaign file or
the command line shows in a report as the text it is (it cannot run, navigate, link, break a table or a figure);
every output refuses '..', a symlink and a missing folder before any work; a disk that fills during a campaign
is named, leaves the run marked failed and no part-written file."""

import dataclasses
import json
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
from html.parser import HTMLParser
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path

import pytest
from selenium.webdriver.support.wait import WebDriverWait

import ddarm.paper.report
import ddarm.tuning.report
from ddarm.cli.main import main
from ddarm.interrupts import Interrupted
from ddarm.paper.report import write_report
from ddarm.paper.schema import Results
from ddarm.recording.runs import RunFolder
from ddarm.reporting.html import HtmlReportError, markdown_to_html
from ddarm.reporting.text import markdown_code, markdown_paragraph, markdown_text, visible
from ddarm.tuning.campaign import Campaign, summary_table
from ddarm.tuning.report import episode_figure, write_tuning_report
from test_report import CONTROLLERS, bags, synthetic_results  # noqa: F401 (bags: the recorded-episode fixture)
from test_report_html import browser, draw_png  # noqa: F401 (browser: the headless Chromium fixture)

ROOT = Path(__file__).resolve().parents[1]
# Names a URDF, a motion file or a campaign may hold: markup, a line break, Markdown, a bidirectional override.
SCRIPT = '<script>document.title = "ran"</script>'
NEWLINE = 'two\nlines | and a cell'
MARKDOWN = '*bold* _em_ [link](javascript:alert(1)) `code` $x$ ~~gone~~ &amp; \\'
BIDI = '\u202e0.1 = I'


def refresh_to(port: int) -> str:
    return f'<meta http-equiv="refresh" content="0;url=http://127.0.0.1:{port}/x">'


class Tags(HTMLParser):
    """Every start tag of a page, with its attributes."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def assert_no_markup_from_files(page: Path) -> None:
    """The page's own markup only: the CSP meta and no other, no script, no event handler, no javascript: link."""
    tags = Tags(page.read_text()).tags
    assert [attrs for tag, attrs in tags if tag == 'meta' and 'http-equiv' in attrs] == [
        {'http-equiv': 'Content-Security-Policy',
         'content': "default-src 'none'; img-src data:; style-src 'unsafe-inline'"}]
    assert not [tag for tag, _ in tags if tag in ('script', 'iframe', 'object', 'embed', 'base', 'form')]
    assert not [attrs for _, attrs in tags if any(name.startswith('on') for name in attrs)]
    assert not [attrs for _, attrs in tags if any('javascript:' in (value or '') for value in attrs.values())]


class HTMLText(HTMLParser):
    """The text of a fragment of HTML, its character references resolved."""

    def __init__(self, fragment: str) -> None:
        super().__init__(convert_charrefs=True)
        self.parts: list[str] = []
        self.feed(fragment)
        self.close()
        self.text = ''.join(self.parts)

    def handle_data(self, data):
        self.parts.append(data)


def table_lines(markdown: str, heading: str) -> list[str]:
    """The table lines under `heading` in a Markdown text, up to the next blank line after the table."""
    lines = markdown.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith('|') and i > lines.index(heading))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith('|')), len(lines))
    return lines[start:end]


@pytest.fixture
def listener():
    """An HTTP server on 127.0.0.1 that records every path asked of it: a page that navigates there shows up."""
    asked = []

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server's name)
            asked.append(self.path)
            self.send_response(200)
            self.end_headers()
            self.wfile.write(b'<title>navigated</title>')

        def log_message(self, *arguments):
            pass

    server = HTTPServer(('127.0.0.1', 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address[1], asked
    server.shutdown()
    thread.join()


def hostile_tuning_report(tmp_path: Path, joints: list[str], port: int) -> dict:
    indices = {'I1': 0.1, 'I2': 0.2, 'I': 0.3}
    return {'controller': 'computed_torque', 'index': 'I', 'method': 'cma',
            'command': f'ddarm tune --urdf "{refresh_to(port)}.urdf" --run `x`',
            'restarts': [], 'restarts_within_1_percent': None, 'evolution_generations': 0,
            'spec': {'urdf': str(tmp_path / f'{SCRIPT}.urdf'), 'model_urdf': str(tmp_path / 'a`b``c.urdf'),
                     'motion': str(tmp_path / f'{MARKDOWN}.yaml'), 'trajectory': 1, 'duration': 1.0,
                     'period': 0.01, 'delay': 1, 'tau': 0.0, 'torque_limit': None},
            'joint_names': joints, 'kp': [900.0, 800.0, 700.0, 600.0, 500.0], 'kv': [60.0, 50.0, 40.0, 30.0, 20.0],
            'episodes': 150, 'wall_time_s': 0.5, 'episodes_per_s': 300.0, 'search_index': 0.3,
            'in_process': indices, 'from_bag': indices, 'max_rel_difference': 0.0, 'agree': True,
            'bag': str(tmp_path / 'runs' / 'hostile' / 'bags' / 'best'), 'saturated_joints': [NEWLINE],
            'warnings': [f'joint {refresh_to(port)} has no limit\nsecond line'], 'gains_files': ['g`ains.yaml'],
            'converged': None, 'certainty': 'not certified: --method cma runs no independent global runs'}


def test_a_tuning_report_shows_every_name_from_a_file_as_text_and_navigates_nowhere(browser, listener, tmp_path,
                                                                                     monkeypatch):
    port, asked = listener
    monkeypatch.setattr(ddarm.tuning.report, 'episode_figure', lambda path, bag, title: draw_png(path, 5))
    joints = [refresh_to(port), SCRIPT, NEWLINE, MARKDOWN, BIDI]
    run = RunFolder('hostile', tmp_path / 'runs', 'ddarm tune')
    report = hostile_tuning_report(tmp_path, joints, port)
    try:
        write_tuning_report(run, report)
    finally:
        run.finish('complete')
    markdown, page = (run.path / 'report.md').read_text(), run.path / 'report.html'
    assert len(table_lines(markdown, '## Gains')) == 2 + len(joints)  # one line per joint, whatever its name
    assert_no_markup_from_files(page)
    browser.get(page.as_uri())
    WebDriverWait(browser, 30).until(lambda driver: driver.execute_script('return document.readyState') == 'complete')
    assert browser.current_url == page.as_uri() and asked == []
    title = browser.title
    gains = browser.execute_script(
        'const heading = Array.from(document.querySelectorAll("h2")).find(h => h.textContent === "Gains");'
        'let table = heading.nextElementSibling; while (table.tagName !== "TABLE") table = table.nextElementSibling;'
        'return Array.from(table.tBodies[0].rows, row => Array.from(row.cells, cell => cell.textContent));')
    assert gains == [[visible(name), f'{p:g}', f'{d:g}'] for name, p, d in
                     zip(joints, (900, 800, 700, 600, 500), (60, 50, 40, 30, 20))]
    text = browser.execute_script('return document.body.innerText')
    assert 'Command: ddarm tune --urdf "<meta http-equiv="refresh"' in text and '--run `x`' in text
    assert f'controller model: {tmp_path}/a`b``c.urdf' in text and f'{MARKDOWN}.yaml' in text
    assert f'WARNING: joint {refresh_to(port)} has no limit␊second line' in text
    assert f'At their torque limit in the recorded episode: {visible(NEWLINE)}.' in text
    assert title == (f"computed_torque on {Path(report['spec']['urdf']).name}, "
                     f"{Path(report['spec']['motion']).name}: I minimised")
    links = browser.execute_script('return Array.from(document.links, link => link.getAttribute("href"))')
    assert links == []


def test_a_figure_draws_names_and_titles_from_files_as_text(bags, tmp_path, monkeypatch):  # noqa: F811
    """A `$` in a joint name or a file name is not matplotlib's mathematics, which refuses `$\\foo$` outright."""
    real = ddarm.tuning.report.read_episode_bag
    joints = ['$\\foo$', 'a$b$c\n$', BIDI]
    monkeypatch.setattr(ddarm.tuning.report, 'read_episode_bag',
                        lambda path: dataclasses.replace(real(path), joints=joints))
    figure = tmp_path / 'episode.png'
    episode_figure(figure, bags / 'bags' / 'computed_torque', 'computed_torque on $\\undefined$.urdf')
    assert figure.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_the_page_shows_raw_html_as_text_and_refuses_a_script_link(tmp_path, listener):
    port, _ = listener
    report = tmp_path / 'REPORT.md'
    raw = [refresh_to(port), SCRIPT, '<img src="x" onerror="alert(1)">', '<a href="javascript:alert(1)">here</a>',
           '<iframe src="http://127.0.0.1/"></iframe>', '<base href="http://127.0.0.1/">']
    report.write_text('# Raw\n\n' + '\n\n'.join(raw) + '\n\nInline ' + ' and '.join(raw) + '.\n')
    page = markdown_to_html(report, tmp_path / 'report.html')
    assert_no_markup_from_files(page)
    assert [tag for tag, _ in Tags(page.read_text()).tags if tag not in ('html', 'head', 'meta', 'title', 'style',
                                                                         'body', 'main', 'h1', 'p')] == []
    for scheme in ('javascript:alert(1)', 'data:text/html,<script>alert(1)</script>', 'file:///etc/passwd'):
        report.write_text(f'# Links\n\n[here]({scheme})\n')
        with pytest.raises(HtmlReportError, match=f'link .*{scheme.split(":")[0]}: link'):
            markdown_to_html(report, tmp_path / 'refused.html')
        assert not (tmp_path / 'refused.html').exists()


def test_markdown_text_and_code_render_as_the_text_itself():
    import markdown

    for text in (refresh_to(1), SCRIPT, NEWLINE, MARKDOWN, BIDI, '`', '``a`', 'C:\\', '| a |', '&lt;', 'a_b_c', '_a_b_'):
        rendered = markdown.Markdown(extensions=['tables']).convert(f'{markdown_text(text)} and {markdown_code(text)}')
        assert HTMLText(rendered).text == f'{visible(text)} and {visible(text)}', (text, rendered)


@pytest.mark.parametrize('text', ['# a heading', '### three', '> a quote', '- an item', '+ an item', '* an item',
                                  '1. first', '12) twelfth', '---', '***', '___', '    indented code', '```fence',
                                  '~~~fence', '<div>', '=== x', '#no space', 'plain 1. text'])
def test_a_markdown_paragraph_opens_no_other_block(text):
    import markdown

    rendered = markdown.Markdown(extensions=['tables']).convert(f'# Title\n\n{markdown_paragraph(text)}\n')
    assert rendered.startswith('<h1>Title</h1>\n<p>') and rendered.count('<') == 4, rendered
    assert HTMLText(rendered).text == 'Title\n' + visible(text).lstrip(' '), rendered


def test_the_reproduction_report_shows_the_command_and_folder_as_text(tmp_path, monkeypatch):
    monkeypatch.setattr(ddarm.paper.report, 'read_episode_bag', lambda path: path)
    monkeypatch.setattr(ddarm.paper.report.figures, 'tracking_figure', lambda path, episodes, case: draw_png(path, 6))
    out = tmp_path / '<meta http-equiv="refresh" content="0;url=x"> `$x$` it\'s'
    for controller in CONTROLLERS:
        (out / 'bags' / controller).mkdir(parents=True)
        (out / 'bags' / controller / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    results = synthetic_results(dict.fromkeys(CONTROLLERS, {'I': 0.4, 'I1': 0.1, 'I2': 0.3}))
    results['command'] = f'ddarm reproduce --out {out} {SCRIPT} ``'
    results['started'] = NEWLINE
    write_report(out, Results.from_json(results))
    assert_no_markup_from_files(out / 'report.html')
    text = HTMLText((out / 'report.html').read_text().split('<main>')[1]).text
    assert f'Command: {results["command"]}' in text and f'Started {visible(NEWLINE)};' in text
    assert f"cd '{tmp_path}/<meta http-equiv=\"refresh\" content=\"0;url=x\"> `$x$` it'\"'\"'s' && ddarm score" in text
    for claim in results['claims']:
        assert f"{claim['claim']} Evidence: {claim['evidence']}" in ' '.join(text.split())


def test_the_campaign_summary_shows_file_names_descriptions_and_reasons_as_text(tmp_path, listener):
    port, _ = listener
    path = tmp_path / f'{SCRIPT}|{MARKDOWN}.yaml'
    campaign = Campaign(path, '', f'{refresh_to(port)}\n# not a heading\n| not | a row |', (), ())
    failed = {'name': 'paper.t1.computed_torque.nominal', 'arm': 'paper', 'motion': 't1',
              'controller': 'computed_torque', 'law': 'computed_torque',
              'scenario_text': 'nominal: τ = 0 s', 'index': 'I', 'status': 'failed',
              'reason': f'graph episode: joint {refresh_to(port)} |\n| x | y | z |'}
    ok = {**failed, 'name': 'paper.t1.pd_gravity.nominal', 'controller': 'pd_gravity', 'law': 'pd_gravity', 'status': 'ok',
          'search_index': 2.5,
          'bag_index': 2.5, 'bag': 'bags/paper.t1.pd_gravity.nominal'}
    (tmp_path / 'bags' / ok['name']).mkdir(parents=True)
    draw_png(tmp_path / 'index-per-job.png', 7)
    summary = tmp_path / 'SUMMARY.md'
    summary.write_text(summary_table(campaign, [failed, ok]))
    rows = table_lines(summary.read_text(), '')[2:]
    assert len(rows) == 2
    page = markdown_to_html(summary, tmp_path / 'summary.html')
    assert_no_markup_from_files(page)
    text = HTMLText(page.read_text().split('<main>')[1]).text
    assert f'Campaign {path.name}' in text and visible(campaign.description) in text
    assert f'FAILED: {visible(failed["reason"])}' in text
    assert page.read_text().count('<tr>') == 3


@pytest.fixture
def symlinked(tmp_path) -> Path:
    """tmp_path/link, a symlink to the empty folder tmp_path/target; and a folder tmp_path/sub to climb out of."""
    (tmp_path / 'target').mkdir()
    (tmp_path / 'link').symlink_to(tmp_path / 'target')
    (tmp_path / 'sub').mkdir()
    return tmp_path / 'target'


def test_a_motion_file_through_a_symlink_or_dotdot_is_refused_before_the_bag_is_read(capsys, tmp_path, symlinked):
    never_read = str(tmp_path / 'no-such-bag')
    for out, named in ((tmp_path / 'link' / 'motion.yaml', 'is a symlink'),
                       (tmp_path / 'sub' / '..' / 'motion.yaml', '".." is not allowed')):
        assert main(['motion', never_read, '--out', str(out)]) == 2
        err = capsys.readouterr().err
        assert named in err and 'Traceback' not in err, err
    assert not any(symlinked.iterdir()) and not (tmp_path / 'motion.yaml').exists()


def test_a_pareto_yaml_dir_through_a_symlink_or_dotdot_is_refused_before_any_search(capsys, tmp_path, symlinked):
    pareto = ['pareto', '--controller', 'computed_torque', '--budget', '10000']
    for folder, named in ((tmp_path / 'link', 'is a symlink'), (tmp_path / 'link' / 'front', 'is a symlink'),
                          (tmp_path / 'sub' / '..' / 'front', '".." is not allowed')):
        assert main([*pareto, '--yaml-dir', str(folder)]) == 2
        err = capsys.readouterr().err
        assert err.startswith('ddarm pareto: --yaml-dir ') and named in err, err
    assert not any(symlinked.iterdir()) and not (tmp_path / 'front').exists()


def test_run_folders_in_a_missing_folder_are_refused_before_any_work(capsys, tmp_path):
    missing = tmp_path / 'missing' / 'deeper'
    assert main(['tune', '--controller', 'computed_torque', '--index', 'I', '--runs', str(missing)]) == 2
    assert f'{missing}: the folder {missing.parent} does not exist' in capsys.readouterr().err
    campaign = tmp_path / 'campaign.yaml'
    campaign.write_text('index: I\ncontrollers: [computed_torque]\nbudget: 200\n')
    assert main(['campaign', str(campaign), '--out', str(missing / 'run')]) == 2
    assert f'--out {missing / "run"}: the folder {missing} does not exist' in capsys.readouterr().err
    assert not (tmp_path / 'missing').exists()


# `ddarm omega` refuses its outputs before any episode: its refusals come at once.
OMEGA = ['omega', '--controller', 'computed_torque', '--duration', '0.2', '--disturbance', '5', '5', '5',
         '--max-error', '1']


def refusal(capsys, arguments: list[str]) -> str:
    """The one line `ddarm` wrote to stderr in refusing `arguments` with exit code 2 (argparse's refusals exit)."""
    try:
        code = main(arguments)
    except SystemExit as exit:
        code = exit.code
    out, err = capsys.readouterr()
    assert code == 2 and err.count('\n') == 1 and 'Traceback' not in err, (code, out, err)
    return err


@pytest.fixture
def a_file(tmp_path, monkeypatch) -> Path:
    """tmp_path/afile, a file; the test runs in tmp_path, which is left holding nothing else."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / 'afile').write_text('x\n')
    return tmp_path / 'afile'


def assert_nothing_made(tmp_path: Path, *kept: str) -> None:
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(['afile', *kept])


def test_a_runs_folder_through_a_file_is_refused_as_through_a_file_not_as_missing(capsys, tmp_path, a_file):
    for runs in (a_file / 'x', a_file / 'x' / 'y'):
        err = refusal(capsys, [*OMEGA, '--runs', str(runs)])
        assert f'{runs}: {a_file} is a file, not a folder' in err and 'does not exist' not in err, err
    err = refusal(capsys, [*OMEGA, '--runs', str(tmp_path / 'runs'), '--out', str(a_file / 'x')])
    assert f'--out {a_file / "x"}: {a_file} is a file, not a folder' in err, err
    assert_nothing_made(tmp_path)


def test_a_campaign_or_pareto_folder_through_a_file_is_refused_as_through_a_file(capsys, tmp_path, a_file):
    campaign = tmp_path / 'campaign.yaml'
    campaign.write_text('index: I\ncontrollers: [computed_torque]\nbudget: 200\n')
    for arguments, option in ((['campaign', str(campaign)], '--out'),
                              (['pareto', '--controller', 'computed_torque', '--budget', '10000'], '--yaml-dir')):
        err = refusal(capsys, [*arguments, option, str(a_file / 'x')])
        assert option in err and f'{a_file} is a file, not a folder' in err and 'does not exist' not in err, err
    assert_nothing_made(tmp_path, 'campaign.yaml')


@pytest.mark.parametrize('option', ['--run', '--out', '--runs'])
def test_an_empty_output_option_is_refused_naming_it_not_replaced_by_the_default(capsys, tmp_path, a_file, option):
    runs = [] if option == '--runs' else ['--runs', str(tmp_path / 'runs')]
    err = refusal(capsys, [*OMEGA, *runs, option, ''])
    assert f'argument {option}: ' in err and 'empty' in err, err
    assert_nothing_made(tmp_path)


@pytest.mark.parametrize('control', ['\n', '\t', '\x1b', '\x7f'], ids=['newline', 'tab', 'ESC', 'DEL'])
def test_an_output_name_holding_a_control_character_is_refused_naming_the_option_and_the_character(
        capsys, tmp_path, a_file, control):
    name, code = f'a{control}b', f'U+{ord(control):04X}'
    shown = visible(name, pictures=False)
    assert shown == f'a<{code}>b'
    for option, value in (('--run', name), ('--out', str(tmp_path / name))):
        err = refusal(capsys, [*OMEGA, '--runs', str(tmp_path / 'runs'), option, value])
        assert f'argument {option}: the name {shown} holds the control character {code}' in err, ascii(err)
    # A new --runs folder is a name ddarm makes too; the refusal names it, as it shows every invisible character.
    err = refusal(capsys, [*OMEGA, '--runs', str(tmp_path / name)])
    assert f'{tmp_path}/{shown}: the name {shown} holds the control character {code}' in err, ascii(err)
    # So is a bag's folder.
    err = refusal(capsys, ['episode', '--controller', 'computed_torque', '--omega', '15', '--ros',
                           '--bag', str(tmp_path / name)])
    assert f'the name {shown} holds the control character {code}' in err, ascii(err)
    assert_nothing_made(tmp_path)


def test_a_control_character_in_a_folder_that_exists_is_the_users_and_not_refused(tmp_path):
    from ddarm.tuning.outputs import check_outputs

    folder = tmp_path / 'theirs\nfolder'
    folder.mkdir()
    check_outputs(str(folder / 'gains.yaml'), str(folder / 'runs'), 'run')  # ddarm makes gains.yaml, runs, run
    check_outputs(None, str(folder), None)
    assert list(folder.iterdir()) == []


# Two small searches on T = 0.5 s, as test_campaign.TINY.
TINY = """
index: I
method: cma
budget: 200
omegas: [12, 15]
motions:
  - {name: t1, trajectory: 1, duration: 0.5}
controllers: [computed_torque, pd_gravity]
"""


def test_an_interrupted_campaign_keeps_its_finished_searches_and_says_which_failed(tmp_path, monkeypatch):
    import ddarm.tuning.jobs as jobs

    real = jobs.run_jobs

    def stopped_after_the_first(searches, workers, *, on_done, **options):
        def done(job, result):
            on_done(job, result)
            raise Interrupted(signal.SIGINT)
        return real(searches, workers, on_done=done, **options)

    monkeypatch.setattr(jobs, 'run_jobs', stopped_after_the_first)
    (tmp_path / 'campaign.yaml').write_text(TINY)
    assert main(['campaign', str(tmp_path / 'campaign.yaml'), '--out', str(tmp_path / 'run'), '--jobs', '1']) == 130
    summary = json.loads((tmp_path / 'run' / 'summary.json').read_text())
    assert summary['status'] == 'interrupted' and summary['failed'] == []
    (searched,) = summary['jobs']
    assert searched['name'] == 'paper.t1.computed_torque.nominal' and searched['status'] == 'searched'
    assert len(searched['kp']) == 3 and searched['search_index'] > 0 and searched['episodes'] <= 200
    assert 'bag' not in searched and not (tmp_path / 'run' / 'gains').exists()


def in_a_full_file_system(tmp_path: Path, size: str, script: str, *arguments: str) -> subprocess.CompletedProcess:
    """Python `script` run with `arguments` in a mount namespace of its own where `tmp_path`/full is a tmpfs of
    `size` (unshare: no root needed); what it leaves there is copied to `tmp_path`/left, as the tmpfs ends with it."""
    unshare = shutil.which('unshare')
    if unshare is None:
        pytest.fail('unshare (util-linux) is missing: it gives this test a small file system to fill', pytrace=False)
    full = tmp_path / 'full'
    full.mkdir()
    shell = ('mount -t tmpfs -o size="$1" ddarm-full "$2" || exit 99; shift 2\n'
             '"$@"; code=$?\ncp -a "$0/full" "$0/left"; exit $code\n')
    return subprocess.run([unshare, '--user', '--map-root-user', '--mount', 'sh', '-c', shell, str(tmp_path),
                           size, str(full), sys.executable, '-c', script, *arguments],
                          capture_output=True, text=True, timeout=300)


def test_a_run_folder_on_a_full_disk_names_each_file_and_leaves_no_part_of_it(tmp_path):
    script = textwrap.dedent("""
        import sys
        from pathlib import Path
        from ddarm.errors import DdarmError
        from ddarm.recording.runs import RunFolder
        full = Path(sys.argv[1])
        run = RunFolder('run', full, 'test')
        filler = full / 'filler'
        with filler.open('wb', buffering=0) as file:  # every byte of the file system taken but the last few pages
            try:
                while True:
                    file.write(bytes(4096))
                    file.flush()
            except OSError:
                pass
        for attempt in (lambda: run.write_text('SUMMARY.md', 'x' * 100000),
                        lambda: run.record('jobs', ['y' * 100000])):
            try:
                attempt()
            except DdarmError as error:
                print(error)
        try:
            with run:
                raise DdarmError('the job failed')
        except DdarmError as error:
            print(error)
    """)
    done = in_a_full_file_system(tmp_path, '256k', script, str(tmp_path / 'full'))
    assert done.returncode == 0, done.stderr
    run = tmp_path / 'full' / 'run'
    assert done.stdout.splitlines() == [
        f'{run}/SUMMARY.md: cannot write it: No space left on device',
        f'{run}/summary.json: cannot write the summary: No space left on device',
        f'the job failed; and the run could not be marked failed: {run}/summary.json: cannot write the summary: '
        'No space left on device'], done.stdout
    assert 'Traceback' not in done.stderr and 'Logging error' not in done.stderr, done.stderr
    left = sorted(path.name for path in (tmp_path / 'left' / 'run').iterdir())
    assert left == ['run.log', 'summary.json']  # no SUMMARY.md in part, no summary.json.partial


def test_a_campaign_that_fills_the_disk_names_the_bag_marks_the_run_failed_and_leaves_no_part_written_file(
        tmp_path):
    """The disk fills as the job's bag is written: the campaign stops there (every later job would fail alike),
    removes the bag no scorer accepts, and so has the space to mark its summary failed."""
    (tmp_path / 'campaign.yaml').write_text(TINY)
    script = 'import sys\nfrom ddarm.cli.main import main\nsys.exit(main(sys.argv[1:]))\n'
    run = tmp_path / 'full' / 'run'
    done = in_a_full_file_system(tmp_path, '64k', script, 'campaign', str(tmp_path / 'campaign.yaml'),
                                 '--out', str(run), '--jobs', '1')
    assert done.returncode == 2, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    job = 'paper.t1.computed_torque.nominal'
    assert last.startswith(f'ddarm campaign: {run}/bags/{job}: cannot write the bag: No space left on device'), last
    assert 'Traceback' not in done.stderr and 'Logging error' not in done.stderr, done.stderr
    left = tmp_path / 'left' / 'run'
    summary = json.loads((left / 'summary.json').read_text())
    assert summary['status'] == 'failed' and 'No space left on device' in summary['error']
    assert summary['failed'] == [job] and [record['name'] for record in summary['jobs']] == [
        job, 'paper.t1.pd_gravity.nominal']
    assert [record['status'] for record in summary['jobs']] == ['failed', 'searched']
    assert not list(left.rglob('*.partial')) and not list(left.rglob('*.tmp'))
    assert not list((left / 'bags').iterdir())  # the job's bag, which no scorer would accept, is gone


TERMINAL_CONTROLS = ('\x1b', '\x07', '\x9b', '\u202e', '\r')


def assert_nothing_for_the_terminal_to_act_on(text: str) -> None:
    assert not any(control in text for control in TERMINAL_CONTROLS), ascii(text)


def test_a_path_holding_escape_sequences_is_shown_escaped_in_a_refusal(capfd, tmp_path):
    path = tmp_path / 'motion\x1b]0;PWNED\x07\x1b[2J\r.yaml'
    assert main(['episode', '--controller', 'pd_gravity', '--omega', '10', '--motion', str(path)]) == 2
    out, err = capfd.readouterr()
    assert_nothing_for_the_terminal_to_act_on(out + err)
    assert 'motion<U+001B>]0;PWNED<U+0007><U+001B>[2J<U+000D>.yaml' in err


def test_an_argument_holding_escape_sequences_is_shown_escaped_in_argparses_refusal(capfd):
    assert_refused = pytest.raises(SystemExit)
    with assert_refused:
        main(['episode', '--controller', 'pd\x1b[2J'])
    out, err = capfd.readouterr()
    assert_nothing_for_the_terminal_to_act_on(out + err)
    assert 'invalid choice' in err


def test_joint_names_holding_c1_controls_and_overrides_are_shown_escaped_in_a_printed_table(capfd, tmp_path):
    # XML forbids ESC, but not U+009B (the 8-bit CSI of many terminals) or U+202E (right-to-left override).
    names = ['a\u009b2J', 'b\u202e1.0', 'c']
    urdf = (ROOT / 'config' / 'ddarm.urdf').read_text()
    for old, new in zip(('joint1', 'joint2', 'joint3'), names):
        urdf = urdf.replace(f'"{old}"', f'"{new}"')
    (tmp_path / 'arm.urdf').write_text(urdf, encoding='utf-8')
    (tmp_path / 'motion.yaml').write_text(json.dumps({'joint_names': names, 'duration': 0.2, 'profile': 'bang_bang',
                                                      'start': [0.0] * 3, 'goal': [0.1] * 3}))
    assert main(['episode', '--controller', 'pd_gravity', '--omega', '10', '--urdf', str(tmp_path / 'arm.urdf'),
                 '--motion', str(tmp_path / 'motion.yaml')]) == 0
    out, err = capfd.readouterr()
    assert_nothing_for_the_terminal_to_act_on(out + err)
    assert 'a<U+009B>2J, b<U+202E>1.0, c' in out
