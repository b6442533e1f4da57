"""Every citation of the fault list or of the model specification resolves to a file in this repository.

The project's earlier fault list and specification live outside the repository; docs/faults.md and
docs/model-specification.md restate them under the same numbers. Code, tests, configuration and documentation cite
those pages (`docs/faults.md N`, `docs/model-specification.md §N` or `spec §N`), never the outside files, and every
number cited is an item or a section heading of the page it names.
"""

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FAULTS_PAGE = 'docs/faults.md'
SPEC_PAGE = 'docs/model-specification.md'
SUFFIXES = ('.py', '.md', '.yaml', '.txt')

# The outside files' names, written as patterns so that this file does not name them itself.
OUTSIDE_NAME = re.compile(r'\b(?:shared/spec/)?(?:FAULTS|MODEL)\.md\b')
# A name in quotes is data, not a citation: a test asserting that an output never names the outside file.
QUOTED_NAME = re.compile(r'''(['"])(?:FAULTS|MODEL)\.md\1''')
# The outside file by its path, as the two pages that restate them name their origin.
OUTSIDE_PATH = re.compile(r'^shared/spec/')
# Files that may name the outside files, and how.
MAY_NAME_THE_OUTSIDE_FILES = {
    # Its first paragraph names its origin by path; the rest cites nothing outside.
    FAULTS_PAGE: 'by path',
    # In it the outside name stands for the earlier specification (its first paragraph says so): its Differences
    # notes and §15 say where the code departs from that file, so they must name it.
    SPEC_PAGE: 'anyhow',
}
# Files whose citations are not updated yet (another change is under way in them): their lines are skipped here,
# and test_files_still_to_update_are_named names them. Remove a file once its citations point inside the repository.
STILL_TO_UPDATE: dict[str, str] = {}

NUMBER_RANGE = r'\d+(?:\s*[-–]\s*\d+)?'
FAULTS_CITATION = re.compile(rf'docs/faults\.md\s+({NUMBER_RANGE}(?:\s*,\s*{NUMBER_RANGE})*)')
SECTION = r'§\d+(?:\.\d+)?(?:\s*[-–]\s*§?\d+(?:\.\d+)?)?'
SPEC_NAME = r'(?:(?<![\w-])[Ss]pec|docs/model-specification\.md)'
SPEC_CITATION = re.compile(rf'{SPEC_NAME}\s*\(?\s*({SECTION}(?:\s*,\s*{SECTION})*)')
FAULT_ITEM = re.compile(r'^(\d+)\. ', re.MULTILINE)
SECTION_HEADING = re.compile(r'^#{2,} (\d+(?:\.\d+)?)\.?\s', re.MULTILINE)


def tracked_files() -> list[str]:
    """The repository's source and documentation files: tracked, or new and not ignored."""
    listed = subprocess.run(['git', 'ls-files', '--cached', '--others', '--exclude-standard'], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout.splitlines()
    return sorted({name for name in listed if name.endswith(SUFFIXES) and (ROOT / name).is_file()})


def checked_texts() -> dict[str, str]:
    return {name: (ROOT / name).read_text(encoding='utf-8') for name in tracked_files() if name not in STILL_TO_UPDATE}


def numbers(cited: str) -> list[int]:
    """'1-11, 13' -> 1 … 11, 13."""
    found = []
    for part in re.split(r'\s*,\s*', cited.strip()):
        ends = [int(end) for end in re.split(r'\s*[-–]\s*', part)]
        found.extend(range(ends[0], ends[-1] + 1))
    return found


def sections(cited: str) -> list[str]:
    """'§4-§10' -> 4 … 10; '§6.1' -> 6.1; '§5, §8' -> 5, 8."""
    found = []
    for part in re.split(r'\s*,\s*', cited.strip()):
        ends = [end.strip().lstrip('§') for end in re.split(r'[-–]', part)]
        if len(ends) == 2 and ends[0].isdigit() and ends[1].isdigit():
            found.extend(str(n) for n in range(int(ends[0]), int(ends[1]) + 1))
        else:
            found.extend(ends)
    return found


def line_of(text: str, offset: int) -> int:
    return text.count('\n', 0, offset) + 1


def test_the_pages_cited_are_in_the_repository():
    files = tracked_files()
    assert FAULTS_PAGE in files and SPEC_PAGE in files


def test_no_file_cites_the_outside_fault_list_or_specification():
    stale = []
    for name, text in checked_texts().items():
        allowed = MAY_NAME_THE_OUTSIDE_FILES.get(name)
        quoted = {match.start() + 1 for match in QUOTED_NAME.finditer(text)}
        for match in OUTSIDE_NAME.finditer(text):
            if match.start() in quoted or allowed == 'anyhow':
                continue
            if allowed == 'by path' and OUTSIDE_PATH.match(match.group()):
                continue
            stale.append(f'{name}:{line_of(text, match.start())}: {match.group()}')
    assert not stale, ('cite docs/faults.md N or docs/model-specification.md §N instead:\n' + '\n'.join(stale))


def test_the_fault_list_keeps_its_numbering():
    items = [int(n) for n in FAULT_ITEM.findall((ROOT / FAULTS_PAGE).read_text(encoding='utf-8'))]
    assert items == list(range(1, 26)), items


def test_every_fault_cited_is_an_item_of_the_fault_list():
    items = {int(n) for n in FAULT_ITEM.findall((ROOT / FAULTS_PAGE).read_text(encoding='utf-8'))}
    missing, cited = [], 0
    for name, text in checked_texts().items():
        for match in FAULTS_CITATION.finditer(text):
            for n in numbers(match.group(1)):
                cited += 1
                if n not in items:
                    missing.append(f'{name}:{line_of(text, match.start())}: {FAULTS_PAGE} {n}')
    assert cited > 0, 'no citation of the fault list found: is the pattern still right?'
    assert not missing, 'no such item in docs/faults.md:\n' + '\n'.join(missing)


def test_every_section_cited_is_a_heading_of_the_specification():
    headings = set(SECTION_HEADING.findall((ROOT / SPEC_PAGE).read_text(encoding='utf-8')))
    assert {str(n) for n in range(1, 17)} <= headings, sorted(headings)
    missing, cited = [], 0
    for name, text in checked_texts().items():
        for match in SPEC_CITATION.finditer(text):
            for section in sections(match.group(1)):
                cited += 1
                if section not in headings:
                    missing.append(f'{name}:{line_of(text, match.start())}: §{section}')
    assert cited > 0, 'no citation of the specification found: is the pattern still right?'
    assert not missing, 'no such section heading in docs/model-specification.md:\n' + '\n'.join(missing)


def test_files_still_to_update_are_named():
    # Each file listed must still exist and still cite an outside file; the message names them for whoever updates
    # them next. With none listed, there is nothing to do.
    for name, why in STILL_TO_UPDATE.items():
        text = (ROOT / name).read_text(encoding='utf-8')
        assert OUTSIDE_NAME.search(text), f'{name} cites no outside file any more: remove it from STILL_TO_UPDATE'
