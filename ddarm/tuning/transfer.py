"""`ddarm transfer`'s judgement and page: do gains tuned on an identified URDF predict the robot, and by how much
did identification improve its tracking. No ROS and no engine here: the caller runs the episodes and hands over
their indices."""

from __future__ import annotations

from pathlib import Path

from ddarm.episodes.indices import INDICES
from ddarm.episodes.result import Episodes
from ddarm.physics.regressor import JOINT_PARAMETERS
from ddarm.recording.runs import RunFolder
from ddarm.reporting.html import markdown_to_html
from ddarm.reporting.text import markdown_code, markdown_text

PAGE_NAME, HTML_NAME = 'transfer.md', 'transfer.html'
PHASES = ('nominal', 'retuned')
SIDES = ('predicted', 'measured')


def side_record(result: Episodes) -> dict:
    """One side of a validation as the summary holds it: I1, I2, I (over the scored samples) and whether it
    diverged."""
    return {**result.indices(), 'diverged': bool(result.diverged[0])}


def _robust_words(retuned: dict, index: str) -> str:
    """How the retuned gains were tuned over the identification's samples, if they were."""
    if not retuned.get('samples'):
        return ''
    worst = retuned['predicted_worst']
    return (f", robustly (worst case) over it and {len(retuned['samples'])} samples of its parameters: predicted "
            f"worst {index} {'diverged' if worst is None else f'{worst:.6g}'}, measured "
            f"{retuned['measured'][index]:.6g}")


def verdict(retuned: dict, index: str, tolerance: float) -> tuple[bool, str]:
    """Whether the retuned gains' prediction is the robot: neither side diverged and |measured − predicted| /
    measured of `index` is at most `tolerance`. The reason names the figure that failed."""
    for side in SIDES:
        if retuned[side]['diverged']:
            return False, f'does not transfer: the {side} episode of the retuned gains diverged'
    measured, predicted = retuned['measured'][index], retuned['predicted'][index]
    if not measured > 0:
        return False, f'does not transfer: the measured {index} is {measured!r}, no scale to judge the prediction by'
    error = abs(measured - predicted) / measured
    if error <= tolerance:
        return True, (f'transfers: the retuned gains\' measured {index} {measured:.6g} is within {error:.3g} '
                      f'(≤ {tolerance:g}) of the predicted {predicted:.6g}')
    return False, (f'does not transfer: the retuned gains\' measured {index} {measured:.6g} is {error:.3g} from the '
                   f'predicted {predicted:.6g} (relative to the measured), more than the tolerance {tolerance:g}')


def improvement(nominal: dict, retuned: dict) -> float | None:
    """The nominal gains' measured I1 over the retuned gains': how many times lower the robot's I1 became (None
    where either measurement diverged, whose I1 covers other samples, or the retuned I1 is 0)."""
    before, after = nominal['measured'], retuned['measured']
    if before['diverged'] or after['diverged'] or after['I1'] == 0:
        return None
    return before['I1'] / after['I1']


def improvement_sentence(ratio: float | None) -> str:
    if ratio is None:
        return 'no I1 ratio: a measurement diverged, and its I1 covers only the samples before it'
    if ratio >= 1:
        return f"measured I1 of the retuned gains is {ratio:.3g} times lower than the nominal gains'"
    return f"measured I1 of the retuned gains is {1 / ratio:.3g} times higher than the nominal gains'"


def _row(values) -> str:
    return '| ' + ' | '.join(values) + ' |'


def _cell(record: dict, index: str) -> str:
    return f'{record[index]:.6g}' + ('*' if record['diverged'] else '')


def index_rows(report: dict) -> list[list[str]]:
    """Per phase and index: predicted, measured, measured / predicted (none for a side that diverged: its indices,
    marked *, cover fewer samples)."""
    rows = []
    for phase in PHASES:
        predicted, measured = report[phase]['predicted'], report[phase]['measured']
        whole = not (predicted['diverged'] or measured['diverged'])
        for index in INDICES:
            ratio = measured[index] / predicted[index] if whole and predicted[index] != 0 else None
            rows.append([phase, index, _cell(predicted, index), _cell(measured, index),
                         '-' if ratio is None else f'{ratio:.4g}'])
    return rows


def parameter_rows(identification: dict) -> list[list[str]]:
    """Per joint: the identified mass, armature, damping and friction beside the URDF's, and the torque residual on
    the held-out bag (where the joint moves)."""
    residual = identification['validation_residual']
    rows = []
    for entry in identification['joints']:
        cells = [entry['joint']]
        for parameter in ('mass', *JOINT_PARAMETERS):
            cells += [f'{entry[parameter]:.4g}', f'{entry[f"{parameter}_urdf"]:.4g}']
        cells.append(f"{residual[entry['joint']]:.3%}")
        rows.append(cells)
    return rows


PARAMETER_HEADER = ['joint', 'mass kg', '(URDF)', 'armature kg m²', '(URDF)', 'damping N m s/rad', '(URDF)',
                    'friction N m', '(URDF)', 'held-out residual']


def _doubt_words(phase: dict) -> str:
    """After a phase's gains on the page: that its search is not sure of them, if so."""
    return '' if phase['converged'] else f"; **{markdown_text(phase['certainty'])}**"


def write_transfer_page(run: RunFolder, report: dict, index: str, figures: dict[str, str], title: str) -> Path:
    """transfer.md and transfer.html: the indices before and after identification, the identified parameters beside
    the URDF's, the figures (`figures`: phase → PNG name in the run folder) and the verdict. Every text from a file
    or the command line is escaped (ddarm.reporting.text)."""
    identification = report['identification']
    lines = [f'# {markdown_text(title)}', '', f"Command: {markdown_code(run.summary['command'])}", '',
             f"**{markdown_text(report['verdict'])}**", '',
             f"- {markdown_text(improvement_sentence(report['improvement_I1']))}",
             f"- nominal gains: {markdown_code(report['nominal']['gains'])}, tuned on the URDF"
             + _doubt_words(report['nominal']),
             f"- identified URDF: {markdown_code(identification['urdf'])} (condition number "
             f"{identification['condition_number']:.4g})",
             f"- retuned gains: {markdown_code(report['retuned']['gains'])}, tuned on the identified URDF"
             + _robust_words(report['retuned'], index) + _doubt_words(report['retuned']),
             f"- bags: {', '.join(markdown_code(bag) for bag in report['bags'])}",
             f"- the verdict: |measured {index} − predicted {index}| / measured {index} of the retuned gains at most "
             f"{report['tolerance']:g}, neither side diverged",
             '', '## Predicted and measured', '',
             _row(['gains', 'index', 'predicted', 'measured', 'measured / predicted']), _row(['---'] * 5)]
    lines += [_row([markdown_text(cell) for cell in row]) for row in index_rows(report)]
    if any(report[phase][side]['diverged'] for phase in PHASES for side in SIDES):
        lines += ['', '\\* diverged: the index covers only the samples before it.']
    lines += ['', '## Identified against the URDF', '',
              f"Residual: RMS torque error over RMS torque per joint where it moves, on the bag not fitted "
              f"({markdown_code(identification['validation_residual']['bag'])}).", '',
              _row(PARAMETER_HEADER), _row(['---'] * len(PARAMETER_HEADER))]
    lines += [_row([markdown_text(cell) for cell in row]) for row in parameter_rows(identification)]
    lines += ['', '## Tracking error, predicted and measured', '']
    for phase in PHASES:
        lines += [f'### {phase} gains', '', f'![the tracking error of each joint, {phase} gains]({figures[phase]})', '']
    page = run.write_text(PAGE_NAME, '\n'.join(lines))
    run.log.info('wrote %s', markdown_to_html(page, run.path / HTML_NAME))
    return page
