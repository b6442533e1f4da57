"""The reproduction's report: REPORT.md beside the paper's figures, and its PNG figures, from results.json and its bags.

Pure (no ROS): `write_report` reads the results dict that ddarm.paper.experiments writes to
results.json and, for the tracking figure, two of the bags it names (paths relative to the
output folder). Figures are drawn on the Agg canvas directly, so no pyplot state is touched.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

from ddarm.control.laws import CONTROLLERS
from ddarm.errors import DdarmError
from ddarm.recording.bags import BagEpisode, read_episode_bag

CONTROLLER_NAMES = {'pd_gravity': 'PD + gravity', 'computed_torque': 'computed torque'}
COLOURS = {'pd_gravity': 'tab:blue', 'computed_torque': 'tab:red'}
JOINT_ROLES = ('base', 'shoulder', 'elbow')
# The Table 4 case whose episodes the tracking figure shows: trajectory, T (s), Δ (s).
TRACKING_CASE = (1, 1.0, 0.01)
# The paper's claim about sampling: ω = 15 stays stable at 100 Hz and above.
PAPER_OMEGA = 15.0
DPI = 120

TOP_KEYS = ('command', 'quick', 'started', 'wall_time_s', 'settings', 'gains', 'table2', 'table3', 'table4',
            'section2', 'claims', 'reconstruction')
ROW_KEYS = {
    'gains': ('name', 'controller', 'index', 'trajectory', 'T', 'period', 'delay', 'kp', 'kv', 'search'),
    'table2': ('controller', 'tau', 'limited', 'gains', 'I1', 'I2', 'I', 'diverged', 'max_abs_torque',
               'torque_limit', 'within_limits', 'bag', 'paper'),
    'table4': ('controller', 'trajectory', 'T', 'period', 'delay', 'gains', 'kp', 'kv', 'I', 'I1', 'I2', 'bag',
               'paper'),
    'claims': ('claim', 'reproduced', 'evidence'),
}
ROW_KEYS['table3'] = ROW_KEYS['table2']
SEARCH_KEYS = ('episodes', 'wall_time_s', 'episodes_per_s', 'in_process_index', 'start_index', 'methods')
SECTION2_KEYS = {
    'omega_rules': ('controller', 'omega', 'kp', 'kv', 'I1', 'I2', 'I', 'bag'),
    'omega_procedure': ('controller', 'case', 'max_error_deg', 'omega_min', 'omega', 'kp', 'kv', 'I1', 'I2', 'I',
                        'bag'),
    'stability': ('period', 'omega_max_stable', 'omega_15_stable', 'I1_at_omega_15', 'bag'),
}
PAPER_TABLE4_KEYS = ('I', 'I1', 'I2')
# The paper's index names, and the field of a row that holds each.
INDEX_KEYS = {'2.5': 'I1', '3.2': 'I'}


class ReportError(DdarmError, ValueError):
    """A results dict the report cannot be made from, or an output that exists already; the text says which."""


# Checking the results -----------------------------------------------------------------------

def _require(mapping, keys, where: str) -> None:
    if not isinstance(mapping, dict):
        raise ReportError(f'{where} must be an object, got {type(mapping).__name__}')
    for key in keys:
        if key not in mapping:
            raise ReportError(f'results: missing key {where}.{key}' if where != 'results'
                              else f'results: missing key {key!r}')


def _rows(container: dict, key: str, where: str) -> list:
    rows = container[key]
    if not isinstance(rows, list):
        raise ReportError(f'{where}.{key} must be a list, got {type(rows).__name__}')
    return rows


def check_results(results: dict) -> None:
    """Refuse (ReportError, a ValueError naming the key) a results dict without what the report reads."""
    _require(results, TOP_KEYS, 'results')
    for part, keys in ROW_KEYS.items():
        for i, row in enumerate(_rows(results, part, 'results')):
            _require(row, keys, f'{part}[{i}]')
    for i, row in enumerate(results['gains']):
        _require(row['search'], SEARCH_KEYS, f'gains[{i}].search')
    for i, row in enumerate(results['table4']):
        if row['paper'] is not None:
            _require(row['paper'], PAPER_TABLE4_KEYS, f'table4[{i}].paper')
    _require(results['section2'], SECTION2_KEYS, 'section2')
    for part, keys in SECTION2_KEYS.items():
        for i, row in enumerate(_rows(results['section2'], part, 'section2')):
            _require(row, keys, f'section2.{part}[{i}]')
    if not isinstance(results['reconstruction'], list):
        raise ReportError('results.reconstruction must be a list of strings')
    controller_rows = [(part, results[part]) for part in ('gains', 'table2', 'table3', 'table4')]
    controller_rows += [(f'section2.{part}', results['section2'][part]) for part in ('omega_rules', 'omega_procedure')]
    for part, rows in controller_rows:
        for i, row in enumerate(rows):
            if row['controller'] not in CONTROLLERS:
                raise ReportError(f"{part}[{i}].controller must be one of {CONTROLLERS}, got {row['controller']!r}")
    for i, row in enumerate(results['gains']):
        if row['index'] not in INDEX_KEYS:
            raise ReportError(f"gains[{i}].index must be one of {sorted(INDEX_KEYS)}, got {row['index']!r}")
    names = {row['name'] for row in results['gains']}
    for part in ('table2', 'table3', 'table4'):
        for i, row in enumerate(results[part]):
            if row['gains'] not in names:
                raise ReportError(f'{part}[{i}].gains names {row["gains"]!r}, which is not in results.gains')
    for controller in CONTROLLERS:
        tracking_row(results, controller)


def _same_case(row: dict, trajectory: int, duration: float, period: float) -> bool:
    return (row['trajectory'] == trajectory and math.isclose(row['T'], duration)
            and math.isclose(row['period'], period))


def tracking_row(results: dict, controller: str) -> dict:
    """The Table 4 row of `controller` at TRACKING_CASE (trajectory 1, T = 1 s, Δ = 0.01 s)."""
    for row in results['table4']:
        if row['controller'] == controller and _same_case(row, *TRACKING_CASE):
            return row
    trajectory, duration, period = TRACKING_CASE
    raise ReportError(f'table4: no row for {controller}, trajectory {trajectory}, T = {duration} s, '
                      f'period {period} s (the tracking figure needs it)')


# Text -------------------------------------------------------------------------------------

def number(value, digits: int = 3) -> str:
    """`digits` significant digits in fixed notation (exponent only beyond 1e6 or below 1e-4); '—' for None."""
    if value is None:
        return '—'
    value = float(value)
    if math.isnan(value):
        return 'NaN'
    if math.isinf(value):
        return '∞' if value > 0 else '-∞'
    if value == 0:
        return '0'
    # The magnitude after rounding, so that 0.09996 prints as 0.100, not 0.1000.
    magnitude = math.floor(math.log10(abs(float(f'{value:.{digits - 1}e}'))))
    if magnitude >= 6 or magnitude < -4:
        return f'{value:.{digits - 1}e}'
    return f'{value:.{max(0, digits - 1 - magnitude)}f}'


def paper_number(value) -> str:
    """The paper's figure as printed there (its own digits); '—' where it gives none."""
    return '—' if value is None else f'{float(value):g}'


def vector(values, digits: int = 4) -> str:
    return '—' if values is None else '(' + ', '.join(number(v, digits) for v in values) + ')'


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table; a '|' inside a cell is escaped so that it cannot split the cell."""
    def line(cells):
        return '| ' + ' | '.join(str(text).replace('|', '\\|').replace('\n', ' ') for text in cells) + ' |'

    return '\n'.join([line(header), '|' + '---|' * len(header), *(line(row) for row in rows)])


class _Cells:
    """Our numbers as table cells, each a link to the bag it was scored from (a missing bag is flagged)."""

    def __init__(self, out: Path) -> None:
        self.out = out

    def link(self, text: str, bag: str | None) -> str:
        if bag is None:
            return text
        if not (self.out / bag / 'metadata.yaml').is_file():
            return f'{text} (**bag `{bag}` missing**)'
        return f'[{text}]({bag})'

    def index(self, row: dict, key: str, digits: int = 3) -> str:
        """row[key] linked to row's bag; a diverged episode says so beside its (partial) figure."""
        text = self.link(number(row[key], digits), row['bag'])
        return f'{text} **diverged**' if row.get('diverged') else text


def _peak_ratio(row: dict) -> float:
    """max_i max_j |P_i| / limit_i: 1 or more means the paper's torque limit was reached."""
    return float(np.max(np.asarray(row['max_abs_torque'], float) / np.asarray(row['torque_limit'], float)))


def _limit_cell(reached: bool, ratio: float) -> str:
    return f'**yes** ({number(ratio)}×)' if reached else f'no ({number(ratio)}×)'


def _case(row: dict) -> str:
    return f"trajectory {row['trajectory']}, T = {row['T']:g} s, Δ = {row['period']:g} s"


def _by_key(rows: list, *keys) -> dict:
    return {tuple(row[key] for key in keys): row for row in rows}


def _tau(row: dict) -> float:
    """τ as a table key: 0.1 * 3 and 0.3 are one row."""
    return round(float(row['tau']), 9)


def _by_tau(rows: list, *keys) -> dict:
    return {(*(row[key] for key in keys), _tau(row)): row for row in rows}


def _taus(rows: list) -> list:
    return sorted({_tau(row) for row in rows})


def _gain_lines(results: dict, rows: list) -> str:
    gains = {row['name']: row for row in results['gains']}
    used = sorted({row['gains'] for row in rows}, key=lambda name: (gains[name]['controller'], name))
    return '\n'.join(f"- {CONTROLLER_NAMES[gains[name]['controller']]} "
                     f"(`{name}`, delay d = {gains[name]['delay']}): k_p = {vector(gains[name]['kp'])}, "
                     f"k_v = {vector(gains[name]['kv'])}" for name in used)


def _header(results: dict, out: Path) -> str:
    quick = ('**quick** (`--quick`: small search budgets, so the minima are looser than a full run\'s; '
             'compare a full run with the paper)' if results['quick'] else 'full')
    settings = '; '.join(f'{key} = `{json.dumps(value)}`' for key, value in results['settings'].items())
    example = next((row['bag'] for row in results['table4']), 'bags/<episode>')
    return f"""# Reproduction: the choice of feedback gains for a direct-drive manipulator (Kowalska)

- Command: `{results['command']}`
- Started {results['started']}; wall time {number(results['wall_time_s'], 4)} s; run: {quick}
- Settings: {settings}
- Every figure of ours in the tables below was scored from the bag of the episode it links to (paths
  relative to this folder), recorded as the episode ran through the ROS graph. Re-score any of them
  with `ddarm score <bag>`, e.g. `cd {out} && ddarm score {example}` (`--json` prints every field).
- "paper" columns: the paper's Tables 2-4 (MODEL.md section 10); — where the paper gives no figure.
- Indices (MODEL.md 8): I1 = (2.5) = (1/k_max) Σ_j Σ_i |e_i(jΔ)| with e in degrees; I2 the same sum of
  |P_i - P_i^nom| weighted by R_i = 10 / max_j |P_i^nom(jΔ)|; I = I1 + I2 = (3.2). PD + gravity is
  the paper's control system of Fig. 1, computed torque that of Fig. 2.
"""


def _claims(results: dict) -> str:
    lines = ['## Claims (MODEL.md section 10)', '',
             'Judged by the experiments from the numbers below; see the reconstruction notes for why '
             'absolute figures may differ from the paper\'s.', '']
    for claim in results['claims']:
        verdict = 'REPRODUCED' if claim['reproduced'] else 'NOT REPRODUCED'
        lines.append(f"- **{verdict}**: {claim['claim']}  \n  Evidence: {claim['evidence']}")
    return '\n'.join(lines) + '\n'


def _table2(results: dict, cells: _Cells) -> str:
    rows = _by_tau(results['table2'], 'controller', 'limited')
    header = ['τ s']
    for controller in CONTROLLERS:
        name = CONTROLLER_NAMES[controller]
        header += [f'{name} unlimited', 'paper', f'{name} limited', 'paper', 'limit reached (peak |P|/limit)']
    body = []
    for tau in _taus(results['table2']):
        line = [f'{tau:.2f}']
        for controller in CONTROLLERS:
            pair = [rows.get((controller, limited, tau)) for limited in (False, True)]
            for row in pair:
                line += (['not run', '—'] if row is None
                         else [cells.index(row, 'I1'), paper_number(row['paper'])])
            present = [row for row in pair if row is not None]
            line.append(_limit_cell(any(not row['within_limits'] for row in present), _peak_ratio(present[0]))
                        if present else '—')
        body.append(line)
    return f"""## Table 2: index (2.5) against the initial disturbance τ, gains optimised for (2.5)

Trajectory 1, T = 1 s, Δ = 0.01 s; q̇(0) = -q̇^d(τ) (3.1). "limited": |P_i| ≤ 2 max |P_i^nom| enforced by
the plant. "limit reached" is whether the applied torques reached that limit, with the unlimited episode's
peak |P_i| / limit_i (the largest over the joints; the limited episode is the same until it first reaches
the limit). The paper leaves its limited column blank for small τ. Each figure of ours links to its bag.

{markdown_table(header, body)}

Gains:
{_gain_lines(results, results['table2'])}
"""


def _table3(results: dict, cells: _Cells) -> str:
    rows = _by_tau(results['table3'], 'controller')
    header = ['τ s']
    for controller in CONTROLLERS:
        header += [CONTROLLER_NAMES[controller], 'paper', 'within limits (peak |P|/limit)']
    body = []
    for tau in _taus(results['table3']):
        line = [f'{tau:.2f}']
        for controller in CONTROLLERS:
            row = rows.get((controller, tau))
            if row is None:
                line += ['not run', '—', '—']
                continue
            ratio = _peak_ratio(row)
            within = f'yes ({number(ratio)}×)' if row['within_limits'] else f'**no** ({number(ratio)}×)'
            line += [cells.index(row, 'I1'), paper_number(row['paper']), within]
        body.append(line)
    return f"""## Table 3: index (2.5) against τ, gains optimised for (3.2)

Trajectory 1, T = 1 s, Δ = 0.01 s, torque unlimited. The paper: "the driving torques do not exceed their
limiting values in any of the cases considered"; "within limits" checks that against 2 max |P_i^nom|.

{markdown_table(header, body)}

Gains:
{_gain_lines(results, results['table3'])}
"""


def _table4_cases(results: dict) -> list:
    """Table 4's cases (trajectory, T, Δ) in the order they first appear."""
    cases = []
    for row in results['table4']:
        case = (row['trajectory'], row['T'], row['period'])
        if case not in cases:
            cases.append(case)
    return cases


def _table4(results: dict, cells: _Cells) -> str:
    header = ['case', 'controller', 'd', 'I', 'paper', 'I1', 'paper', 'I2', 'paper', 'k_p', 'k_v']
    cases = _table4_cases(results)
    body = []
    # As the paper: the two controllers of a case side by side.
    for row in sorted(results['table4'], key=lambda row: (cases.index((row['trajectory'], row['T'], row['period'])),
                                                            CONTROLLERS.index(row['controller']))):
        paper = row['paper'] or {}
        body.append([_case(row), CONTROLLER_NAMES[row['controller']], str(row['delay']),
                     cells.index(row, 'I'), paper_number(paper.get('I')),
                     cells.index(row, 'I1'), paper_number(paper.get('I1')),
                     cells.index(row, 'I2'), paper_number(paper.get('I2')),
                     vector(row['kp']), vector(row['kv'])])
    return f"""## Table 4: minimal (3.2), I = I1 + I2

Gains optimised for (3.2) in each case, e(0) = 0, ė(0) = 0, torque unlimited. Each figure of ours links
to its bag.

{markdown_table(header, body)}
"""


def _undisturbed_row(results: dict, name: str) -> dict | None:
    """The tables' episode with gains `name` and no disturbance (τ = 0, torque unlimited), if any."""
    rows = [row for row in results['table4'] if row['gains'] == name]
    rows += [row for part in ('table2', 'table3') for row in results[part]
             if row['gains'] == name and _tau(row) == 0 and not row['limited']]
    return rows[0] if rows else None


def _gains(results: dict, cells: _Cells) -> str:
    header = ['gains', 'controller', 'index', 'case', 'd', 'k_p', 'k_v', 'start → optimum (in-process)',
              'optimum from its bag', 'episodes', 'wall time s', 'episodes/s', 'methods']
    body = []
    for row in results['gains']:
        search = row['search']
        episode = _undisturbed_row(results, row['name'])
        scored = '—' if episode is None else cells.index(episode, INDEX_KEYS[row['index']])
        body.append([f"`{row['name']}`", CONTROLLER_NAMES[row['controller']],
                     f"({row['index']})", _case(row), str(row['delay']), vector(row['kp']), vector(row['kv']),
                     f"{number(search['start_index'])} → {number(search['in_process_index'])}", scored,
                     str(search['episodes']), number(search['wall_time_s']), number(search['episodes_per_s']),
                     ', '.join(search['methods'])])
    return f"""## Optimised gains

Every search ran in-process through the batch engine, from section 2's ω-rule gains ("start" is the best
start's index). Beside its optimum, the same gains' index scored from the bag of their undisturbed ROS
episode (τ = 0, torque unlimited, from Tables 2-4): the two should agree.

{markdown_table(header, body)}
"""


def _section2(results: dict, cells: _Cells) -> str:
    section2 = results['section2']
    rules = [[CONTROLLER_NAMES[row['controller']], number(row['omega']),
              vector(row['kp']), vector(row['kv']), cells.index(row, 'I1'), cells.index(row, 'I2'),
              cells.index(row, 'I')] for row in section2['omega_rules']]
    procedure = []
    for row in section2['omega_procedure']:
        chosen = (number(row['omega']) if row['omega'] is not None
                  else 'none: even ω_min breaks the torque conditions')
        indices = ([cells.index(row, key) for key in ('I1', 'I2', 'I')] if row['omega'] is not None
                   else ['—'] * 3)
        procedure.append([CONTROLLER_NAMES[row['controller']], row['case'],
                          number(row['max_error_deg']), number(row['omega_min']), chosen, vector(row['kp']),
                          vector(row['kv']), *indices])
    stability = []
    for row in sorted(section2['stability'], key=lambda row: row['period']):
        stable = 'yes' if row['omega_15_stable'] else '**no**'
        episode = cells.link(number(row['I1_at_omega_15']), row['bag'])
        if row.get('diverged_at_omega_15'):  # a key experiments.py adds beyond the schema's
            episode += ' **diverged**'
        stability.append([f"{row['period']:g}", f"{1 / row['period']:g}", number(row['omega_max_stable']),
                          stable, episode])
    return f"""## Section 2: gains from simplified models

### ω-rule gains

Critically damped rules (MODEL.md 6): PD + gravity k_p = m_ii ω², k_v = 2 m_ii ω (m_ii at q_f);
computed torque k_p = ω², k_v = 2ω. Trajectory 1, T = 1 s, Δ = 0.01 s, the paper's delays.

{markdown_table(['controller', 'ω rad/s', 'k_p', 'k_v', 'I1 (2.5)', 'I2', 'I (3.2)'], rules)}

### The ω procedure

The smallest ω whose steady-state errors are within the permitted error, then ω raised while the
torques stay within their limits and do not grow excessively over the nominal ones.

{markdown_table(['controller', 'case', 'permitted error °', 'ω_min', 'chosen ω', 'k_p', 'k_v', 'I1', 'I2', 'I'],
                procedure)}

### Stability of computed torque (delay d = 1) against the sampling period

The paper: at 100 Hz and above, computed torque stays stable at ω = {PAPER_OMEGA:g}. The largest stable ω
for each Δ, and the episode at ω = {PAPER_OMEGA:g} (trajectory 1, T = 1 s).

{markdown_table(['Δ s', 'sampling Hz', 'largest stable ω rad/s', f'ω = {PAPER_OMEGA:g} stable',
                 f'I1 at ω = {PAPER_OMEGA:g}'], stability)}
"""


def _reconstruction(results: dict) -> str:
    notes = '\n'.join(f'- {note}' for note in results['reconstruction'])
    return f"""## Reconstruction notes

The paper's figures with the arm's dimensions (Fig. 3) and trajectory 1's initial configuration (Fig. 4)
are lost. Our geometry (joint 2 on the base axis, link lengths) and trajectory 1's start are
reconstructions, fixed in MODEL.md (its **[fixed here]** choices), as is the sign of the initial velocity
disturbance. The inertia matrix, gravity torques, nominal torques, torque limits and the weights R_i all
follow from those choices, so our absolute figures may differ from the paper's; what a faithful
implementation must reproduce are the orderings and the trends (which controller is better, how each
index grows with τ, what the torque limits do). Choices that may explain differences:

{notes}
"""


def _figures_section() -> str:
    return """## Figures

![Tracking error and torque per joint](figures/tracking.png)

Tracking error e = q^d - q and applied torque (held over each sample period) per joint, both controllers
at their Table 4 optimum for trajectory 1, T = 1 s, Δ = 0.01 s; dashed: the nominal torque P^nom.

![Index (2.5) against τ](figures/index_vs_tau.png)

Index (2.5) against the initial disturbance τ: Table 2 (unlimited, limited) and Table 3. Lines: ours;
hollow markers: the paper's figures.

![Table 4](figures/table4.png)

Table 4 as bars: I1 (lower part) and I2 (upper part) stacked to I, ours beside the paper's.

![Stability boundary](figures/stability.png)

The largest stable ω of computed torque (delay 1) against the sampling period Δ, with ω = 15 marked.
"""


# Figures -----------------------------------------------------------------------------------

def _new_figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height), dpi=DPI)
    FigureCanvasAgg(figure)
    return figure


def _episode_series(bag: BagEpisode) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_n, e_n in degrees, interval edges, applied torque) over the samples the bag holds before any divergence."""
    k_max = len(bag.reference_times) - 1
    samples = []
    for n in range(k_max + 1):
        if n not in bag.states or bag.states[n][0] is None:
            break
        samples.append(n)
    times = bag.reference_times[samples]
    errors = np.degrees(bag.q_ref[samples] - np.array([bag.states[n][0] for n in samples]))
    applied = [n for n in samples if n + 1 in bag.states and bag.states[n + 1][2] is not None]
    period = float(bag.episode['spec']['period'])
    torque = np.array([bag.states[n + 1][2] for n in applied]).reshape(len(applied), len(bag.joints))
    if not applied:
        return times, errors, np.empty(0), torque
    # A step plot draws a value over [edge_i, edge_i+1): the last held interval needs its end too.
    edges = np.append(bag.reference_times[applied], (applied[-1] + 1) * period)
    return times, errors, edges, np.vstack([torque, torque[-1:]])


def _plain_log_ticks(axis) -> None:
    """Ticks of a log axis at 1, 2, 5 × 10^k printed as plain numbers: the defaults print 3×10⁻¹ and collide."""
    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FormatStrFormatter('%g'))
    axis.set_minor_formatter(NullFormatter())


def _joint_label(j: int) -> str:
    return f'joint {j + 1} ({JOINT_ROLES[j]})' if j < len(JOINT_ROLES) else f'joint {j + 1}'


def tracking_figure(path: Path, episodes: dict) -> None:
    """Error and applied torque per joint over time, for each controller's (row, bag) in `episodes`."""
    joints = len(next(iter(episodes.values()))[1].joints)
    figure = _new_figure(11, 2.6 * joints + 1.0)
    axes = figure.subplots(joints, 2, sharex=True, squeeze=False)
    for controller, (row, bag) in episodes.items():
        times, errors, edges, torque = _episode_series(bag)
        diverged = len(times) < len(bag.reference_times)
        label = (f"{CONTROLLER_NAMES[controller]} (delay d = {row['delay']}): I1 = {number(row['I1'])}, "
                 f"I2 = {number(row['I2'])}" + (f' (DIVERGED at t = {times[-1]:g} s)' if diverged else ''))
        for j in range(joints):
            axes[j, 0].plot(times, errors[:, j], color=COLOURS[controller], label=label)
            axes[j, 1].step(edges, torque[:, j], where='post', color=COLOURS[controller])
    nominal = next(iter(episodes.values()))[1]  # one trajectory, so one nominal torque for both
    for j in range(joints):
        axes[j, 1].plot(nominal.reference_times, nominal.nominal[:, j], 'k--', linewidth=1.2)
        axes[j, 0].axhline(0.0, color='0.6', linewidth=0.8)
        axes[j, 0].set_ylabel(f'{_joint_label(j)}\nerror (deg)')
        axes[j, 1].set_ylabel('torque (N m)')
        for axis in axes[j]:
            axis.grid(True, alpha=0.3)
    axes[0, 0].set_title('tracking error $e = q^d - q$')
    axes[0, 1].set_title('applied torque $P$ (held over each sampling period)')
    axes[-1, 0].set_xlabel('time t (s)')
    axes[-1, 1].set_xlabel('time t (s)')
    handles, labels = axes[0, 0].get_legend_handles_labels()
    handles.append(Line2D([], [], color='k', linestyle='--'))
    labels.append('nominal torque $P^{nom}$ (open loop, no feedback)')
    trajectory, duration, period = TRACKING_CASE
    figure.suptitle(f'Table 4 optima of (3.2): trajectory {trajectory}, T = {duration:g} s, Δ = {period:g} s')
    figure.legend(handles, labels, loc='upper center', ncol=2, bbox_to_anchor=(0.5, 0.965), frameon=False)
    figure.tight_layout(rect=(0, 0, 1, 0.92))
    figure.savefig(path)


def _index_series(axis, rows: list) -> dict:
    """Draw one panel's rows; returns the legend entries it drew, by label."""
    drawn = {}
    for controller in CONTROLLERS:
        ours = sorted((row for row in rows if row['controller'] == controller), key=lambda row: row['tau'])
        if not ours:
            continue
        colour, name = COLOURS[controller], CONTROLLER_NAMES[controller]
        values = np.array([np.nan if row['diverged'] else row['I1'] for row in ours], dtype=float)
        drawn[f'{name}, ours'], = axis.plot([row['tau'] for row in ours], values, '-o', color=colour, markersize=4)
        paper = [(row['tau'], row['paper']) for row in ours if row['paper'] is not None]
        if paper:
            drawn[f'{name}, paper'], = axis.plot(*zip(*paper), 'o', markersize=8, markerfacecolor='none',
                                                 markeredgecolor=colour, markeredgewidth=1.5)
        over = [row for row in ours if not row['within_limits'] and not row['diverged']]
        if over:
            drawn['torque reached the limit 2 max $|P^{nom}|$'], = axis.plot(
                [row['tau'] for row in over], [row['I1'] for row in over], 's', markersize=9,
                markerfacecolor='none', markeredgecolor='k', markeredgewidth=0.8)
    return drawn


def _mark_diverged(axis, rows: list) -> dict:
    """A cross at the top of the panel for each diverged episode: its partial index would mislead."""
    diverged = [row for row in rows if row['diverged']]
    if not diverged:
        return {}
    top = axis.get_ylim()[1]
    marks = {}
    for controller in CONTROLLERS:
        taus = [row['tau'] for row in diverged if row['controller'] == controller]
        if taus:
            marks['diverged (drawn at the top)'], = axis.plot(taus, [top] * len(taus), 'x', color=COLOURS[controller],
                                                              markersize=10, markeredgewidth=2.5, clip_on=False)
    axis.set_ylim(top=top)
    return marks


def index_vs_tau_figure(path: Path, results: dict) -> None:
    """Index (2.5) against τ: Table 2 unlimited and limited and Table 3, ours as lines, the paper's hollow."""
    panels = [('Table 2, gains for (2.5), torque unlimited', [r for r in results['table2'] if not r['limited']]),
              ('Table 2, gains for (2.5), torque limited', [r for r in results['table2'] if r['limited']]),
              ('Table 3, gains for (3.2), torque unlimited', results['table3'])]
    figure = _new_figure(14, 5.2)
    axes = figure.subplots(1, 3, sharey=True)
    legend = {}
    for axis, (title, rows) in zip(axes, panels):
        axis.set_yscale('log')
        _plain_log_ticks(axis.yaxis)
        legend.update(_index_series(axis, rows))
        axis.set_title(title, fontsize=10)
        axis.set_xlabel('initial disturbance τ (s)')
        axis.grid(True, which='both', alpha=0.3)
    for axis, (_, rows) in zip(axes, panels):  # once every panel is drawn: the shared top is final
        legend.update(_mark_diverged(axis, rows))
    axes[0].set_ylabel('index (2.5), I1 (deg)')
    # Filled column by column: each controller's ours above its paper, then the markers' meanings.
    labels = sorted(legend, key=lambda label: not label.endswith(('ours', 'paper')))
    figure.legend([legend[label] for label in labels], labels, loc='lower center', ncol=3, frameon=False)
    figure.suptitle(r'Sensitivity to the initial velocity disturbance $\dot q(0) = -\dot q^d(\tau)$: '
                    'trajectory 1, T = 1 s, Δ = 0.01 s')
    figure.tight_layout(rect=(0, 0.12, 1, 1))
    figure.savefig(path)


def table4_figure(path: Path, results: dict) -> None:
    """Table 4 as grouped bars: per case, each controller's I1 and I2 stacked, ours beside the paper's."""
    cases = _table4_cases(results)
    rows = _by_key(results['table4'], 'controller', 'trajectory', 'T', 'period')
    figure = _new_figure(13, 5.5)
    axis = figure.subplots()
    width = 0.2
    bars = [(controller, source) for controller in CONTROLLERS for source in ('ours', 'paper')]
    for c, case in enumerate(cases):
        for k, (controller, source) in enumerate(bars):
            row = rows.get((controller, *case))
            if row is None or (source == 'paper' and row['paper'] is None):
                continue
            figures = row if source == 'ours' else row['paper']
            x = c + (k - 1.5) * width
            axis.text(x, -0.01, source, ha='center', va='top', fontsize=8, transform=axis.get_xaxis_transform())
            if source == 'ours' and (row.get('diverged') or not np.isfinite([row['I1'], row['I2']]).all()):
                axis.text(x, 0, 'diverged', ha='center', va='bottom', rotation=90, color=COLOURS[controller])
                continue
            style = {'hatch': '///', 'edgecolor': 'white', 'linewidth': 0} if source == 'paper' else {}
            axis.bar(x, figures['I1'], width * 0.95, color=COLOURS[controller], **style)
            axis.bar(x, figures['I2'], width * 0.95, bottom=figures['I1'], color=COLOURS[controller], alpha=0.4,
                     **style)
            label = number(figures['I']) if source == 'ours' else paper_number(figures['I'])
            axis.text(x, max(figures['I'], figures['I1'] + figures['I2']), label, ha='center', va='bottom',
                      fontsize=8)
    axis.set_xticks(range(len(cases)),
                    [f'trajectory {t}\nT = {T:g} s, Δ = {period:g} s' for t, T, period in cases])
    axis.tick_params(axis='x', pad=16, length=0)
    axis.set_ylim(0, axis.get_ylim()[1] * 1.08)  # room for the numbers on top
    axis.set_ylabel('minimal index (3.2): I = I1 + I2')
    axis.grid(True, axis='y', alpha=0.3)
    handles = [Patch(color=COLOURS[controller], label=CONTROLLER_NAMES[controller]) for controller in CONTROLLERS]
    handles += [Patch(color='0.3', label='I1, tracking (2.5)\n(lower part)'),
                Patch(color='0.3', alpha=0.4, label='I2, torque deviation\n(upper part)'),
                Patch(facecolor='0.5', hatch='///', edgecolor='white', linewidth=0, label='the paper (hatched)')]
    axis.legend(handles=handles, loc='upper left', bbox_to_anchor=(1.01, 1), fontsize=9)
    axis.set_title('Table 4: minimal (3.2), ours beside the paper (number on top: I)')
    figure.tight_layout()
    figure.savefig(path)


def stability_figure(path: Path, results: dict) -> None:
    """The largest stable ω of computed torque (delay 1) against Δ, with the paper's ω = 15 marked."""
    rows = sorted((row for row in results['section2']['stability'] if row['omega_max_stable'] is not None),
                  key=lambda row: row['period'])
    periods = [row['period'] for row in rows]
    figure = _new_figure(8, 5)
    axis = figure.subplots()
    axis.set_xscale('log')
    axis.set_yscale('log')
    axis.plot(periods, [row['omega_max_stable'] for row in rows], '-', color='0.4',
              label='largest stable ω (the boundary)')
    for stable, marker, label in ((True, 'o', f'ω = {PAPER_OMEGA:g} stable at this Δ'),
                                  (False, 'X', f'ω = {PAPER_OMEGA:g} unstable at this Δ')):
        chosen = [row for row in rows if bool(row['omega_15_stable']) == stable]
        if chosen:
            axis.plot([row['period'] for row in chosen], [row['omega_max_stable'] for row in chosen], marker,
                      color='tab:green' if stable else 'tab:red', markersize=8, label=label)
    for row in rows:
        axis.annotate(number(row['omega_max_stable']), (row['period'], row['omega_max_stable']),
                      textcoords='offset points', xytext=(6, 6), fontsize=8)
    axis.axhline(PAPER_OMEGA, color='k', linestyle='--', linewidth=1, label=f'ω = {PAPER_OMEGA:g} (the paper)')
    axis.axvline(0.01, color='0.5', linestyle=':', linewidth=1, label='Δ = 0.01 s (100 Hz)')
    # Ticks at the periods run, in plain numbers.
    axis.set_xticks(periods, [f'{period:g}' for period in periods])
    axis.xaxis.set_minor_formatter(NullFormatter())
    _plain_log_ticks(axis.yaxis)
    axis.margins(y=0.12)  # room for the value written above the highest point
    axis.set_xlabel('sampling period Δ (s)')
    axis.set_ylabel('ω (rad/s)')
    top = axis.secondary_xaxis('top', functions=(lambda x: 1 / np.maximum(x, 1e-12),
                                                 lambda x: 1 / np.maximum(x, 1e-12)))
    top.set_xticks([1 / period for period in periods], [f'{1 / period:g}' for period in periods])
    top.xaxis.set_minor_formatter(NullFormatter())
    top.set_xlabel('sampling frequency 1/Δ (Hz)')
    axis.grid(True, which='both', alpha=0.3)
    axis.legend(fontsize=9)
    axis.set_title('Computed torque, delay d = 1: stability against the sampling period', fontsize=10)
    figure.tight_layout()
    figure.savefig(path)


# The report ---------------------------------------------------------------------------------

def write_report(out: Path, results: dict) -> list[Path]:
    """Write REPORT.md and figures/*.png into `out` from `results` and the bags it names (relative to `out`).

    Args:
        out: the output folder holding results.json's bags; it must exist, and hold neither
            REPORT.md nor figures/ yet.
        results: the dict of results.json.

    Returns the files written: REPORT.md, then the figures.

    Raises:
        ReportError (a ValueError): a required key is missing (the message names it), or an output
            exists already.
        BagError: a bag the tracking figure reads is missing or unusable.
    """
    out = Path(out)
    check_results(results)
    report, figures = out / 'REPORT.md', out / 'figures'
    for path in (report, figures):
        if path.exists():
            raise ReportError(f'{path} exists already, not overwriting')
    episodes = {controller: (row, read_episode_bag(out / row['bag']))
                for controller in CONTROLLERS for row in [tracking_row(results, controller)]}
    figures.mkdir()
    drawn = {'tracking.png': lambda path: tracking_figure(path, episodes),
             'index_vs_tau.png': lambda path: index_vs_tau_figure(path, results),
             'table4.png': lambda path: table4_figure(path, results),
             'stability.png': lambda path: stability_figure(path, results)}
    written = []
    for name, draw in drawn.items():
        draw(figures / name)
        written.append(figures / name)
    cells = _Cells(out)
    sections = [_header(results, out), _claims(results), _table2(results, cells), _table3(results, cells),
                _table4(results, cells), _gains(results, cells), _section2(results, cells), _reconstruction(results),
                _figures_section()]
    report.write_text('\n'.join(sections))
    return [report, *written]
