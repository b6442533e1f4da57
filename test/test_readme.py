"""The README's commands run as shown: every `sh` block, in order, in a folder of its own (config/ linked in), each
command exiting 0; the first result's output is what the README shows. A block marked as not run says why, and
may hold only the Makefile's targets (the main job and the test suite themselves, which CI runs)."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / 'README.md'
NOT_RUN = re.compile(r'<!-- not run by test/test_readme\.py: (.+?) -->')
BLOCK = re.compile(r'```(\w+)\n(.*?)```', re.S)
MAX_LINES = 250


def blocks() -> list[tuple[str, str, str | None]]:
    """(language, text, the reason it is not run or None) of each fenced block, in order."""
    text = README.read_text()
    found = []
    for match in BLOCK.finditer(text):
        before = text[:match.start()].rstrip().splitlines()
        reason = NOT_RUN.fullmatch(before[-1].strip()) if before else None
        found.append((match.group(1), match.group(2), reason.group(1) if reason else None))
    return found


def commands(text: str) -> list[list[str]]:
    """The commands of a shell block: continuation lines joined, comments dropped."""
    joined = re.sub(r'\\\n\s*', ' ', text)
    return [words for line in joined.splitlines() if (words := shlex.split(line, comments=True))]


RUN = [words for language, text, reason in blocks() if language == 'sh' and reason is None for words in commands(text)]


def test_the_readme_is_short_and_says_why_a_block_is_not_run():
    assert len(README.read_text().splitlines()) <= MAX_LINES
    targets = set(re.findall(r'^([a-z]+):', (ROOT / 'Makefile').read_text(), re.M))
    skipped = [(text, reason) for language, text, reason in blocks() if reason is not None]
    assert skipped, 'the two commands are the only block not run'
    for text, reason in skipped:
        for words in commands(text):
            assert words[0] == 'make' and words[1:] and set(words[1:]) <= targets, (words, reason)
    assert all(words[0] == 'ddarm' for words in RUN), [words for words in RUN if words[0] != 'ddarm']


@pytest.fixture(scope='module')
def folder(tmp_path_factory):
    """Where the README's commands run, one after another: config/ as in the checkout, outputs kept apart."""
    path = tmp_path_factory.mktemp('readme')
    (path / 'config').symlink_to(ROOT / 'config')
    return path


@pytest.mark.parametrize('words', RUN, ids=[' '.join(words)[:60] for words in RUN])
def test_each_readme_command_runs(folder, words):
    ddarm = str(Path(sys.executable).with_name('ddarm'))
    done = subprocess.run([ddarm, *words[1:]], cwd=folder, capture_output=True, text=True, timeout=900,
                          env={**os.environ, 'PATH': f'{Path(sys.executable).parent}{os.pathsep}{os.environ["PATH"]}'})
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    shown = next((following for (language, text, _), (following_language, following, _) in
                  zip(blocks(), blocks()[1:]) if language == 'sh' and commands(text) == [words]
                  and following_language == 'text'), None)
    if shown is not None:  # the output the README shows under it
        assert done.stdout == shown
