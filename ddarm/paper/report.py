"""REPORT.md: the reproduction's tables beside the paper's, its claims judged, and its figures.

Pure (no ROS): `write_report` takes the Results that ddarm.paper.experiments writes to results.json
(`Results.load` of that file) and, for the tracking figure, two of the bags they name (paths relative
to the output folder). This module only assembles: the tables are drawn up by ddarm.paper.tables,
the figures by ddarm.paper.figures.
"""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path

from ddarm.control.laws import CONTROLLERS
from ddarm.errors import DdarmError
from ddarm.paper import figures, tables, typed
from ddarm.paper.schema import Results, Table4Row
from ddarm.paper.settings import Case, PaperSettings, paper_settings
from ddarm.paper.tables import case_text, number
from ddarm.recording.bags import read_episode_bag
from ddarm.recording.runs import write_new_text
from ddarm.reporting.html import markdown_to_html
from ddarm.reporting.text import markdown_code, markdown_text


class ReportError(DdarmError, ValueError):
    """A report that cannot be made from these results, or an output that exists already; the text says which."""


def tracking_row(results: Results, controller: str, case: Case) -> Table4Row:
    """The Table 4 row of `controller` at `case`, whose bag the tracking figure draws."""
    for row in results.table4:
        if (row.controller == controller and row.trajectory == case.trajectory
                and math.isclose(row.duration, case.duration) and math.isclose(row.period, case.period)):
            return row
    raise ReportError(f'table4: no row for {controller}, trajectory {case.trajectory}, T = {case.duration} s, '
                      f'period {case.period} s (the tracking figure needs it)')


def _header(results: Results, out: Path) -> str:
    quick = ('**quick** (`--quick`: small search budgets, so the minima are looser than a full run\'s; '
             'compare a full run with the paper)' if results.quick else 'full')
    settings = '; '.join(f'{markdown_text(key)} = {markdown_code(json.dumps(value))}'
                         for key, value in typed.write(results.settings).items())
    example = next((row.bag for row in results.table4), 'bags/<episode>')
    rescore = f'cd {shlex.quote(str(out))} && ddarm score {shlex.quote(example)}'
    return f"""# Reproduction: the choice of feedback gains for a direct-drive manipulator (Kowalska)

- Command: {markdown_code(results.command)}
- Started {markdown_text(results.started)}; wall time {number(results.wall_time_s, 4)} s; run: {quick}
- Settings: {settings}
- Every figure of ours in the tables below was scored from the bag of the episode it links to (paths
  relative to this folder), recorded as the episode ran through the ROS graph. Re-score any of them
  with `ddarm score <bag>`, e.g. {markdown_code(rescore)} (`--json` prints every field).
- "paper" columns: the paper's Tables 2-4 (docs/model-specification.md §10); — where the paper gives no
  figure.
- Indices (docs/model-specification.md §8): I1 = (2.5) = (1/k_max) Σ_j Σ_i |e_i(jΔ)| with e in degrees;
  I2 the same sum of |P_i - P_i^nom| weighted by R_i = 10 / max_j |P_i^nom(jΔ)|; I = I1 + I2 = (3.2).
  PD + gravity is the paper's control system of Fig. 1, computed torque that of Fig. 2.
"""


def _claims(results: Results) -> str:
    lines = ['## Claims (docs/model-specification.md §10)', '',
             'Judged by the experiments from the numbers below; see the reconstruction notes for why '
             'absolute figures may differ from the paper\'s.', '']
    for claim in results.claims:
        verdict = 'REPRODUCED' if claim.reproduced else 'NOT REPRODUCED'
        lines.append(f'- **{verdict}**: {markdown_text(claim.claim)}  \n  Evidence: {markdown_text(claim.evidence)}')
    return '\n'.join(lines) + '\n'


def _reconstruction(results: Results) -> str:
    notes = '\n'.join(f'- {markdown_text(note)}' for note in results.reconstruction)
    return f"""## Reconstruction notes

The paper's figures with the arm's dimensions (Fig. 3) and trajectory 1's initial configuration (Fig. 4)
are lost. Our geometry (joint 2 on the base axis, link lengths) and trajectory 1's start are
reconstructions, fixed in docs/model-specification.md (§1, §4), as is the sign of the initial velocity
disturbance (§7). The inertia matrix, gravity torques, nominal torques, torque limits and the weights R_i all
follow from those choices, so our absolute figures may differ from the paper's; what a faithful
implementation must reproduce are the orderings and the trends (which controller is better, how each
index grows with τ, what the torque limits do). Choices that may explain differences:

{notes}
"""


def _figures_section(settings: PaperSettings) -> str:
    case = settings.tracking_case
    tracking = case_text(case.trajectory, case.duration, case.period)
    delay, omega = settings.delays['computed_torque'], settings.stability.omega
    return f"""## Figures

![Tracking error and torque per joint](figures/tracking.png)

Tracking error e = q^d - q and applied torque (held over each sample period) per joint, both controllers
at their Table 4 optimum for {tracking}; dashed: the nominal torque P^nom.

![Index (2.5) against τ](figures/index_vs_tau.png)

Index (2.5) against the initial disturbance τ: Table 2 (unlimited, limited) and Table 3. Lines: ours;
hollow markers: the paper's figures.

![Table 4](figures/table4.png)

Table 4 as bars: I1 (lower part) and I2 (upper part) stacked to I, ours beside the paper's.

![Stability map](figures/stability.png)

The stability map of computed torque with an exact model: the boundary ωΔ* against the damping ratio ζ for
d = {', '.join(str(d) for d in sorted({*settings.beyond.stability_map.delays, delay}))} (the region below each
curve is stable), the paper's operating point (ζ = 1, ω = {omega:g} rad/s at
its claimed Δ, delay {delay}) as a point, and the recorded episodes at ω = {omega:g} for each Δ at their own ωΔ,
marked by how they ended.
"""


def write_report(out: Path, results: Results) -> list[Path]:
    """Write REPORT.md and figures/*.png into `out` from `results` and the bags it names (relative to `out`).

    Args:
        out: the output folder holding the results' bags; it must exist, and hold neither REPORT.md
            nor figures/ yet.
        results: the reproduction's results (`Results.from_json` of a results.json).

    Returns REPORT.md, then the figures; report.html, REPORT.md as one self-contained page (figures embedded),
    is written beside them.

    Raises:
        ReportError (a ValueError): the tracking figure's Table 4 rows are missing, or an output exists
            already.
        BagError: a bag the tracking figure reads is missing or unusable.
    """
    out = Path(out)
    settings = paper_settings()
    tracking = {controller: tracking_row(results, controller, settings.tracking_case) for controller in CONTROLLERS}
    report, folder = out / 'REPORT.md', out / 'figures'
    for path in (report, folder):
        if path.exists():
            raise ReportError(f'{path} exists already, not overwriting')
    episodes = {controller: (row, read_episode_bag(out / row.bag)) for controller, row in tracking.items()}
    folder.mkdir()
    drawn = {'tracking.png': lambda path: figures.tracking_figure(path, episodes, settings.tracking_case),
             'index_vs_tau.png': lambda path: figures.index_vs_tau_figure(path, results, settings),
             'table4.png': lambda path: figures.table4_figure(path, results),
             'stability.png': lambda path: figures.stability_figure(path, results, settings)}
    if results.pareto is not None:
        drawn['pareto.png'] = lambda path: figures.pareto_figure(path, results, settings)
    written = []
    for name, draw in drawn.items():
        draw(folder / name)
        written.append(folder / name)
    cells = tables.Cells(out)
    sections = [_header(results, out), _claims(results), tables.table2(results, cells, settings),
                tables.table3(results, cells, settings), tables.table4(results, cells), tables.gains(results, cells),
                tables.section2(results, cells, settings), tables.beyond(results, cells, settings),
                _reconstruction(results), _figures_section(settings)]
    write_new_text(report, '\n'.join(sections))
    markdown_to_html(report, out / 'report.html')
    return [report, *written]
