"""The report's Markdown tables, ours beside the paper's, and how their numbers are written."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ddarm.control.laws import CONTROLLERS
from ddarm.paper.schema import Results
from ddarm.paper.settings import PaperSettings
from ddarm.reporting.text import markdown_text

CONTROLLER_NAMES = {'pd_gravity': 'PD + gravity', 'computed_torque': 'computed torque'}


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


def case_text(trajectory: int, duration: float, period: float) -> str:
    return f'trajectory {trajectory}, T = {duration:g} s, Δ = {period:g} s'


def sentence(text: str) -> str:
    """`text` opening a sentence: only its first letter raised (str.capitalize would lower 'T' and 'Δ')."""
    return text[:1].upper() + text[1:]


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table; a '|' inside a cell is escaped so that it cannot split the cell."""
    def line(cells):
        return '| ' + ' | '.join(str(text).replace('|', '\\|').replace('\n', ' ') for text in cells) + ' |'

    return '\n'.join([line(header), '|' + '---|' * len(header), *(line(row) for row in rows)])


class Cells:
    """Our numbers as table cells, each a link to the bag it was scored from (a missing bag is flagged)."""

    def __init__(self, out: Path) -> None:
        self.out = out

    def link(self, text: str, bag: str | None) -> str:
        if bag is None:
            return text
        if not (self.out / bag / 'metadata.yaml').is_file():
            return f'{text} (**bag `{bag}` missing**)'
        return f'[{text}]({bag})'

    def index(self, row, key: str, digits: int = 3) -> str:
        """The index `key` of `row` linked to row's bag; a diverged episode says so beside its (partial) figure."""
        text = self.link(number(getattr(row, key), digits), row.bag)
        return f'{text} **diverged**' if row.diverged else text


def _peak_ratio(row) -> float:
    """max_i max_j |P_i| / limit_i: 1 or more means the paper's torque limit was reached."""
    return float(np.max(np.asarray(row.max_abs_torque, float) / np.asarray(row.torque_limit, float)))


def _tau_key(row) -> float:
    """τ as a table key: 0.1 * 3 and 0.3 are one row."""
    return round(float(row.tau), 9)


def table4_cases(results: Results) -> list[tuple]:
    """Table 4's cases (trajectory, T, Δ) in the order they first appear."""
    cases = []
    for row in results.table4:
        case = (row.trajectory, row.duration, row.period)
        if case not in cases:
            cases.append(case)
    return cases


def _limit_cell(reached: bool, ratio: float) -> str:
    return f'**yes** ({number(ratio)}×)' if reached else f'no ({number(ratio)}×)'


def _by_tau(rows: list, *keys) -> dict:
    return {(*(getattr(row, key) for key in keys), _tau_key(row)): row for row in rows}


def _taus(rows: list) -> list:
    return sorted({_tau_key(row) for row in rows})


def _gain_lines(results: Results, rows: list) -> str:
    used = sorted({row.gains for row in rows}, key=lambda name: (results.gain_set(name).controller, name))
    lines = []
    for name in used:
        gains = results.gain_set(name)
        lines.append(f'- {CONTROLLER_NAMES[gains.controller]} (`{name}`, delay d = {gains.delay}): '
                     f'k_p = {vector(gains.kp)}, k_v = {vector(gains.kv)}')
    return '\n'.join(lines)


def table2(results: Results, cells: Cells, settings: PaperSettings) -> str:
    rows = _by_tau(results.table2, 'controller', 'limited')
    header = ['τ s']
    for controller in CONTROLLERS:
        name = CONTROLLER_NAMES[controller]
        header += [f'{name} unlimited', 'paper', f'{name} limited', 'paper', 'limit reached (peak |P|/limit)']
    body = []
    for tau in _taus(results.table2):
        line = [f'{tau:.2f}']
        for controller in CONTROLLERS:
            pair = [rows.get((controller, limited, tau)) for limited in (False, True)]
            for row in pair:
                line += ['not run', '—'] if row is None else [cells.index(row, 'I1'), paper_number(row.paper)]
            present = [row for row in pair if row is not None]
            line.append(_limit_cell(any(not row.within_limits for row in present), _peak_ratio(present[0]))
                        if present else '—')
        body.append(line)
    case = sentence(case_text(settings.case.trajectory, settings.case.duration, settings.case.period))
    return f"""## Table 2: index (2.5) against the initial disturbance τ, gains optimised for (2.5)

{case}; q̇(0) = -q̇^d(τ) (3.1). "limited": |P_i| ≤ 2 max |P_i^nom| enforced by
the plant. "limit reached" is whether the applied torques reached that limit, with the unlimited episode's
peak |P_i| / limit_i (the largest over the joints; the limited episode is the same until it first reaches
the limit). The paper leaves its limited column blank for small τ. Each figure of ours links to its bag.

{markdown_table(header, body)}

Gains:
{_gain_lines(results, results.table2)}
"""


def table3(results: Results, cells: Cells, settings: PaperSettings) -> str:
    rows = _by_tau(results.table3, 'controller')
    header = ['τ s']
    for controller in CONTROLLERS:
        header += [CONTROLLER_NAMES[controller], 'paper', 'within limits (peak |P|/limit)']
    body = []
    for tau in _taus(results.table3):
        line = [f'{tau:.2f}']
        for controller in CONTROLLERS:
            row = rows.get((controller, tau))
            if row is None:
                line += ['not run', '—', '—']
                continue
            ratio = _peak_ratio(row)
            within = f'yes ({number(ratio)}×)' if row.within_limits else f'**no** ({number(ratio)}×)'
            line += [cells.index(row, 'I1'), paper_number(row.paper), within]
        body.append(line)
    case = sentence(case_text(settings.case.trajectory, settings.case.duration, settings.case.period))
    return f"""## Table 3: index (2.5) against τ, gains optimised for (3.2)

{case}, torque unlimited. The paper: "the driving torques do not exceed their
limiting values in any of the cases considered"; "within limits" checks that against 2 max |P_i^nom|.

{markdown_table(header, body)}

Gains:
{_gain_lines(results, results.table3)}
"""


def table4(results: Results, cells: Cells) -> str:
    header = ['case', 'controller', 'd', 'I', 'paper', 'I1', 'paper', 'I2', 'paper', 'k_p', 'k_v']
    cases = table4_cases(results)
    body = []
    # As the paper: the two controllers of a case side by side.
    for row in sorted(results.table4, key=lambda row: (cases.index((row.trajectory, row.duration, row.period)),
                                                       CONTROLLERS.index(row.controller))):
        paper = [paper_number(None if row.paper is None else getattr(row.paper, key)) for key in ('I', 'I1', 'I2')]
        body.append([case_text(row.trajectory, row.duration, row.period), CONTROLLER_NAMES[row.controller],
                     str(row.delay), cells.index(row, 'I'), paper[0], cells.index(row, 'I1'), paper[1],
                     cells.index(row, 'I2'), paper[2], vector(row.kp), vector(row.kv)])
    return f"""## Table 4: minimal (3.2), I = I1 + I2

Gains optimised for (3.2) in each case, e(0) = 0, ė(0) = 0, torque unlimited. Each figure of ours links
to its bag.

{markdown_table(header, body)}
"""


def _undisturbed_row(results: Results, name: str):
    """The tables' episode with gains `name` and no disturbance (τ = 0, torque unlimited), if any."""
    rows = [row for row in results.table4 if row.gains == name]
    rows += [row for part in (results.table2, results.table3) for row in part
             if row.gains == name and _tau_key(row) == 0 and not row.limited]
    return rows[0] if rows else None


def gains(results: Results, cells: Cells) -> str:
    header = ['gains', 'controller', 'index', 'case', 'd', 'k_p', 'k_v', 'start → optimum (in-process)',
              'optimum from its bag', 'episodes', 'wall time s', 'episodes/s', 'runs within 1 %', 'certificate',
              'each run\'s best']
    body = []
    for row in results.gains:
        search = row.search
        episode = _undisturbed_row(results, row.name)
        scored = '—' if episode is None else cells.index(episode, row.index)
        body.append([f'`{row.name}`', CONTROLLER_NAMES[row.controller], row.index,
                     case_text(row.trajectory, row.duration, row.period), str(row.delay), vector(row.kp),
                     vector(row.kv),
                     f'{number(search.start_index)} → {number(search.in_process_index)}', scored,
                     str(search.episodes), number(search.wall_time_s), number(search.episodes_per_s),
                     f'{search.restarts_within_1_percent} of {len(search.restarts)}', certificate_cell(search),
                     ', '.join('diverged' if restart.index is None else number(restart.index)
                               for restart in search.restarts)])
    return f"""## Optimised gains

Every search ran in-process through the batch engine: `ddarm tune`'s global search, a portfolio of independent
runs (Nelder-Mead from section 2's ω-rule gains of both laws, differential evolutions and wide CMA-ES runs, each
polished by local CMA-ES runs). "start" is the best ω-rule start's index; "runs within 1 %" counts the runs whose
own best came within 1 % of the optimum: several independent runs finding the same basin make a better one
unlikely, one alone says the landscape has basins the others missed. "certificate" is the search's verdict on
them (docs/tuning.md, "The certificate"): *converged* once enough runs of both kinds agree within 0.5 %, otherwise
*not converged* with what was missing, the search having spent its budget. Beside its optimum, the
same gains' index scored from the bag of their undisturbed ROS episode (τ = 0, torque unlimited, from Tables
2-4): the two should agree.

{markdown_table(header, body)}
"""


def certificate_cell(search) -> str:
    """A search's verdict in a table cell: converged, or the certificate's line on why not."""
    return 'converged' if search.converged else f'**{markdown_text(search.certainty)}**'


def section2(results: Results, cells: Cells, settings: PaperSettings) -> str:
    rules = [[CONTROLLER_NAMES[row.controller], number(row.omega), vector(row.kp), vector(row.kv),
              cells.index(row, 'I1'), cells.index(row, 'I2'), cells.index(row, 'I')]
             for row in results.section2.omega_rules]
    procedure = []
    for row in results.section2.omega_procedure:
        ran = row.omega is not None
        chosen = number(row.omega) if ran else 'none: even ω_min breaks the torque conditions'
        indices = [cells.index(row, key) for key in ('I1', 'I2', 'I')] if ran else ['—'] * 3
        procedure.append([CONTROLLER_NAMES[row.controller], row.case, number(row.max_error_deg),
                          number(row.omega_min), chosen, vector(row.kp), vector(row.kv), *indices])
    stability = []
    for row in sorted(results.section2.stability, key=lambda row: row.period):
        stable = 'yes' if row.omega_15_stable else '**no**'
        episode = cells.link(number(row.I1_at_omega_15), row.bag)
        if row.diverged_at_omega_15:
            episode += ' **diverged**'
        stability.append([f'{row.period:g}', f'{1 / row.period:g}', number(row.omega_max_stable), stable, episode])
    case, omega, hertz = settings.case, settings.stability.omega, 1 / settings.stability.claimed_period
    case_line = case_text(case.trajectory, case.duration, case.period)
    return f"""## Section 2: gains from simplified models

### ω-rule gains

Critically damped rules (docs/model-specification.md §6): PD + gravity k_p = m_ii ω², k_v = 2 m_ii ω
(m_ii at q_f); computed torque k_p = ω², k_v = 2ω. {sentence(case_line)}, the paper's delays.

{markdown_table(['controller', 'ω rad/s', 'k_p', 'k_v', 'I1 (2.5)', 'I2', 'I (3.2)'], rules)}

### The ω procedure

The smallest ω whose steady-state errors are within the permitted error, then ω raised while the
torques stay within their limits and do not grow excessively over the nominal ones.

{markdown_table(['controller', 'case', 'permitted error °', 'ω_min', 'chosen ω', 'k_p', 'k_v', 'I1', 'I2', 'I'],
                procedure)}

### Stability of computed torque (delay d = {settings.delays['computed_torque']}) against the sampling period

The paper: at {hertz:g} Hz and above, computed torque stays stable at ω = {omega:g}. The largest stable ω
for each Δ, and the episode at ω = {omega:g} (trajectory {case.trajectory}, T = {case.duration:g} s).

{markdown_table(['Δ s', 'sampling Hz', 'largest stable ω rad/s', f'ω = {omega:g} stable', f'I1 at ω = {omega:g}'],
                stability)}
"""


def beyond(results: Results, cells: Cells, settings: PaperSettings) -> str:
    """What ddarm adds to the paper: the I1–I2 front, the robust gains against the nominal optimum, the map."""
    parts = ['## Beyond the paper\n']
    front = results.pareto
    if front is not None:
        least = min(front.front, key=lambda point: point.I1 + point.I2)
        ends = [('least I1 end', front.front[0]), ('least I', least), ('least I2 end', front.front[-1])]
        rows = [[name, number(point.I1, 4), number(point.I2, 4), number(point.I1 + point.I2, 4), vector(point.kp),
                 vector(point.kv)] for name, point in ends]
        seeds = ', '.join(f'`{name}` ({"on the front" if on else "dominated"})'
                          for name, on in zip(front.seeds, front.seeds_on_front))
        parts.append(f"""### The I1–I2 front

{CONTROLLER_NAMES[front.controller]}, {case_text(front.trajectory, front.duration, front.period)}, delay {front.delay}:
{len(front.front)} points of the {front.front_size} non-dominated episodes found in {front.episodes} episodes
({number(front.wall_time_s)} s in-process, batch engine; {front.method}; {front.searches_converged} of its
{front.searches} refining searches converged). It was seeded by {seeds}. These are in-process numbers; the
figure sets the seeds' own episodes, scored from their bags, and the paper's Table 4 point on it.

{markdown_table(['point', 'I1', 'I2', 'I', 'k_p', 'k_v'], rows)}

![The I1–I2 front](figures/pareto.png)
""")
    robust = results.robust
    if robust is not None:
        parts.append(_robust_table(robust, cells))
    if results.stability_map:
        delays = sorted({row.delay for row in results.stability_map})
        zetas = sorted({row.zeta for row in results.stability_map})
        value = {(row.delay, row.zeta): row.omega_delta for row in results.stability_map}
        period = settings.stability.claimed_period
        rows = [[f'd = {delay}', *(f'{number(value[(delay, zeta)], 5)} ({number(value[(delay, zeta)] / period, 4)} '
                                   f'rad/s)' for zeta in zetas)] for delay in delays]
        parts.append(f"""### The stability map

The exact boundary ωΔ* of the sampled loop (zero-order hold, a d-sample delay, the ω rule with damping ζ:
k_p = ω², k_v = 2ζω), from its characteristic polynomial (`ddarm stability`), with ω* = ωΔ*/Δ at
Δ = {period:g} s in brackets. The paper's computed torque runs at ω = {settings.stability.omega:g} rad/s, d =
{settings.delays['computed_torque']}, ζ = 1: ωΔ = {settings.stability.omega * period:g}.

{markdown_table(['', *(f'ζ = {zeta:g}' for zeta in zetas)], rows)}
""")
    return '\n'.join(parts)


def _robust_table(robust, cells: Cells) -> str:
    scenarios = []
    for row in robust.rows:
        key = (row.tau, row.mass_scale)
        if key not in scenarios:
            scenarios.append(key)
    by_key = {(row.tau, row.mass_scale, row.gains): row for row in robust.rows}
    body = [[f'τ = {tau:g} s, link masses × {vector(scale, 3)}', cells.index(by_key[(tau, scale, 'robust')], 'I'),
             cells.index(by_key[(tau, scale, 'nominal')], 'I')] for tau, scale in scenarios]
    for name, aggregate in (('worst', max), ('mean', lambda values: sum(values) / len(values))):
        figures = []
        for gains in ('robust', 'nominal'):
            rows = [by_key[(tau, scale, gains)] for tau, scale in scenarios]
            figures.append('diverged' if any(row.diverged for row in rows)
                           else f'**{number(aggregate([row.I for row in rows]))}**')
        body.append([f'{name} over the scenarios', *figures])
    return f"""### Robust gains

{CONTROLLER_NAMES[robust.controller]}, {case_text(robust.trajectory, robust.duration, robust.period)}: the gains that
minimise the {robust.objective} I (3.2) over the scenarios below (in-process, {robust.search.episodes} episodes in
{number(robust.search.wall_time_s)} s; {robust.search.restarts_within_1_percent} of its
{len(robust.search.restarts)} independent runs within 1 % of its optimum; its certificate:
{certificate_cell(robust.search)}), k_p = {vector(robust.kp)}, k_v =
{vector(robust.kv)}, beside the nominal optimum `{robust.nominal}` (Table 4), each run on every scenario through
the ROS graph and scored from its bag.

{markdown_table(['scenario', 'I, robust gains', 'I, nominal optimum'], body)}
"""
