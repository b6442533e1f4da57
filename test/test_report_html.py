"""The reports as self-contained HTML pages: headless Chromium opens each offline from file:// and draws it
whole (every figure, no broken link, nothing fetched from the network); a page with a missing target is
refused before it is written.

The browser is Debian's chromium and chromium-driver, which `make test` installs; without them these tests
fail, saying so, rather than skip: a report page that no browser has opened is not known to work.
"""

import base64
import re
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import imread
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.support.wait import WebDriverWait

import ddarm.paper.report
import ddarm.tuning.report
from ddarm.paper.report import write_report
from ddarm.paper.schema import Results
from ddarm.recording.runs import RunFolder
from ddarm.reporting.html import HtmlReportError, markdown_to_html
from ddarm.tuning.report import write_tuning_report
from test_report import CONTROLLERS, synthetic_results

CHROMIUM, CHROMEDRIVER = Path('/usr/bin/chromium'), Path('/usr/bin/chromedriver')
# Headless, and nothing of Chromium's own that would reach the network or a profile outside the test's.
CHROMIUM_ARGUMENTS = ('--headless=new', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
                      '--disable-background-networking', '--disable-component-update', '--disable-sync',
                      '--window-size=1280,1000')
SYNTHETIC_TITLE = 'A synthetic report'


def draw_png(path: Path, seed: int) -> None:
    figure = Figure(figsize=(4, 3), dpi=80)
    FigureCanvasAgg(figure)
    axes = figure.subplots()
    axes.plot(np.cumsum(np.random.default_rng(seed).normal(size=50)), color='tab:red')
    axes.set_title(f'figure {seed}')
    figure.savefig(path)


@pytest.fixture(scope='module')
def browser(tmp_path_factory):
    missing = [str(path) for path in (CHROMIUM, CHROMEDRIVER) if not path.is_file()]
    if missing:
        pytest.fail(f'{" and ".join(missing)} missing: `make test` installs Debian\'s chromium and chromium-driver, '
                    'or as root: apt-get install -y --no-install-recommends chromium chromium-driver', pytrace=False)
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for argument in (*CHROMIUM_ARGUMENTS, f'--user-data-dir={tmp_path_factory.mktemp("chromium-profile")}'):
        options.add_argument(argument)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('SE_OFFLINE', 'true')  # Selenium Manager must not download a driver or a browser
        # The driver's path given to the Service is what keeps Selenium Manager from running at all.
        driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    yield driver
    driver.quit()


def assert_drawn_whole(browser, page: Path, title: str, figures: int, screenshot: Path) -> list[str]:
    """Open `page` offline and check it is all there; returns its relative links (each checked to exist)."""
    browser.get(page.as_uri())
    WebDriverWait(browser, 30).until(lambda driver: driver.execute_script('return document.readyState') == 'complete')
    assert browser.title == title
    drawn = browser.execute_script('return Array.from(document.images, image => image.complete '
                                   '&& image.naturalWidth > 0 && image.src.startsWith("data:image/"))')
    assert drawn == [True] * figures
    links = browser.execute_script('return Array.from(document.links, link => link.getAttribute("href"))')
    relative = [href for href in links if not urlsplit(href).scheme and urlsplit(href).path]
    for href in relative:
        assert (page.parent / unquote(urlsplit(href).path)).exists(), href
    fetched = browser.execute_script('return performance.getEntriesByType("resource").map(entry => entry.name)')
    assert all(name.startswith(('data:', 'file:')) for name in fetched), fetched
    assert browser.save_screenshot(str(screenshot))
    pixels = imread(screenshot)
    assert len(np.unique(pixels.reshape(-1, pixels.shape[-1]), axis=0)) > 1, f'{screenshot} is one colour'
    return relative


@pytest.fixture
def synthetic_report(tmp_path) -> Path:
    """A report as the writers make them: a table linking a bag folder, two figures, a link to results.json."""
    (tmp_path / 'figures').mkdir()
    draw_png(tmp_path / 'figures' / 'tracking.png', 1)
    draw_png(tmp_path / 'index.png', 2)
    (tmp_path / 'bags' / 'best').mkdir(parents=True)
    (tmp_path / 'bags' / 'best' / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    (tmp_path / 'results.json').write_text('{}\n')
    report = tmp_path / 'REPORT.md'
    report.write_text(f"""# {SYNTHETIC_TITLE}

Every number is in [results.json](results.json).

| controller | ω | I |
|---|---|---|
| computed_torque | 15 | [0.3701](bags/best) |
| pd_gravity | 10 | [1.07](bags/best/metadata.yaml) |

![Tracking error](figures/tracking.png)

```sh
ddarm score bags/best
```

![Index against τ](index.png)
""")
    return report


def test_a_report_page_opens_offline_with_every_figure_drawn_and_every_link_whole(browser, synthetic_report,
                                                                                  tmp_path):
    page = markdown_to_html(synthetic_report, tmp_path / 'report.html')
    assert page == tmp_path / 'report.html'
    links = assert_drawn_whole(browser, page, SYNTHETIC_TITLE, 2, tmp_path / 'screenshot.png')
    assert links == ['results.json', 'bags/best', 'bags/best/metadata.yaml']
    text = page.read_text()
    assert '<table>' in text and '<code class="language-sh">ddarm score bags/best' in text
    assert 'http://' not in text and 'https://' not in text


def test_images_are_embedded_byte_for_byte(synthetic_report, tmp_path):
    text = markdown_to_html(synthetic_report, tmp_path / 'report.html').read_text()
    embedded = re.findall(r'<img alt="([^"]*)" src="data:image/png;base64,([^"]+)"', text)
    assert [alt for alt, _ in embedded] == ['Tracking error', 'Index against τ']
    for (_, data), path in zip(embedded, ('figures/tracking.png', 'index.png')):
        assert base64.b64decode(data) == (tmp_path / path).read_bytes()


def test_a_page_elsewhere_links_the_files_from_where_it_is(browser, synthetic_report, tmp_path):
    (tmp_path / 'pages').mkdir()
    page = markdown_to_html(synthetic_report, tmp_path / 'pages' / 'synthetic.html', title='Elsewhere')
    links = assert_drawn_whole(browser, page, 'Elsewhere', 2, tmp_path / 'screenshot.png')
    assert links == ['../results.json', '../bags/best', '../bags/best/metadata.yaml']


@pytest.mark.parametrize('markdown, named', [
    ('[the results](results.jsn)', 'link results.jsn: '),
    ('![a figure](figures/missing.png)', 'image figures/missing.png: '),
    ('![not an image](results.json)', 'results.json is not an image file'),
    ('![remote](https://example.org/figure.png)', "'https://example.org/figure.png' is not a local file"),
])
def test_a_page_with_a_missing_or_remote_target_is_refused_by_name_and_not_written(synthetic_report, tmp_path,
                                                                                    markdown, named):
    synthetic_report.write_text(synthetic_report.read_text() + f'\n{markdown}\n')
    with pytest.raises(HtmlReportError, match=re.escape(named)) as refused:
        markdown_to_html(synthetic_report, tmp_path / 'report.html')
    assert str(refused.value).startswith(f'{synthetic_report}: ')
    assert not (tmp_path / 'report.html').exists()


def test_a_missing_markdown_file_or_page_folder_is_refused_by_name(synthetic_report, tmp_path):
    with pytest.raises(HtmlReportError, match='REPORT.md: cannot read the report'):
        markdown_to_html(tmp_path / 'missing' / 'REPORT.md', tmp_path / 'report.html')
    with pytest.raises(HtmlReportError, match='report.html: cannot write the page: No such file or directory'):
        markdown_to_html(synthetic_report, tmp_path / 'missing' / 'report.html')


def test_the_reproduction_writes_report_html_beside_report_md(browser, tmp_path, monkeypatch):
    """write_report as `ddarm reproduce` calls it; the tracking figure, which reads recorded bags
    (test_report.py records them), is a stand-in drawing here, and the bags are folders with a metadata.yaml."""
    monkeypatch.setattr(ddarm.paper.report, 'read_episode_bag', lambda path: path)
    monkeypatch.setattr(ddarm.paper.report.figures, 'tracking_figure', lambda path, episodes, case: draw_png(path, 3))
    out = tmp_path / 'out'
    for controller in CONTROLLERS:
        (out / 'bags' / controller).mkdir(parents=True)
        (out / 'bags' / controller / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    scores = dict.fromkeys(CONTROLLERS, {'I': 0.4, 'I1': 0.1, 'I2': 0.3})
    write_report(out, Results.from_json(synthetic_results(scores)))
    links = assert_drawn_whole(browser, out / 'report.html',
                               'Reproduction: the choice of feedback gains for a direct-drive manipulator (Kowalska)',
                               5, tmp_path / 'screenshot.png')
    assert set(links) == {f'bags/{controller}' for controller in CONTROLLERS}


def test_a_tuning_writes_report_html_beside_report_md(browser, tmp_path, monkeypatch):
    """write_tuning_report on a finished tuning's report; its figure, drawn from the recorded bag, is a
    stand-in drawing here."""
    monkeypatch.setattr(ddarm.tuning.report, 'episode_figure', lambda path, bag, title: draw_png(path, 4))
    joints = ['joint1', 'joint2', 'joint3']
    indices = {'I1': 0.1, 'I2': 0.2, 'I': 0.3}
    report = {'controller': 'computed_torque', 'index': 'I', 'method': 'global', 'command': 'ddarm tune',
              'restarts': [{'start': 'point 1 seen (0.31)', 'popsize': 16, 'episodes': 64, 'index': 0.3,
                            'stopped_by': ['tolx']}], 'restarts_within_1_percent': 1, 'evolution_generations': 2,
              'spec': {'urdf': None, 'model_urdf': None, 'motion': None, 'trajectory': 1, 'duration': 1.0,
                       'period': 0.01, 'delay': 1, 'tau': 0.0, 'torque_limit': None},
              'joint_names': joints, 'kp': [900.0] * 3, 'kv': [60.0] * 3, 'episodes': 150, 'wall_time_s': 0.5,
              'episodes_per_s': 300.0, 'search_index': 0.3, 'in_process': indices, 'from_bag': indices,
              'max_rel_difference': 0.0, 'agree': True, 'bag': str(tmp_path / 'runs' / 'small' / 'bags' / 'best'),
              'gains_files': ['gains.yaml'], 'converged': True, 'certainty': 'converged: 3 of 4 runs within 1 %'}
    run = RunFolder('small', tmp_path / 'runs', 'ddarm tune')
    try:
        page = write_tuning_report(run, report)
    finally:
        run.finish('complete')
    assert page == run.path / 'report.md'
    assert 'wrote ' + str(run.path / 'report.html') in (run.path / 'run.log').read_text()
    assert_drawn_whole(browser, run.path / 'report.html', "computed_torque on the paper arm, the paper's "
                       'trajectory 1: I minimised', 1, tmp_path / 'screenshot.png')
