"""The report's four PNG figures. Drawn on the Agg canvas directly, so no pyplot state is touched."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

from ddarm.control.laws import CONTROLLERS
from ddarm.control.stability import boundary_omega_delta
from ddarm.paper.schema import Results
from ddarm.paper.settings import Case, PaperSettings
from ddarm.paper.tables import CONTROLLER_NAMES, case_text, number, paper_number, table4_cases
from ddarm.recording.bags import BagEpisode, bag_result

COLOURS = {'pd_gravity': 'tab:blue', 'computed_torque': 'tab:red'}
DPI = 120


def _new_figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height), dpi=DPI)
    FigureCanvasAgg(figure)
    return figure


def _episode_series(bag: BagEpisode) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """(t_n, e_n in degrees, interval edges, applied torque, diverged) over the bag's scored samples.

    The samples are those the scorer scores (`bag_result`): BagError for a bag missing any.
    """
    episode = bag_result(bag)
    errors, torque = episode.scored('errors'), episode.scored('torque')
    count = len(torque)
    times = episode.plan.times[:count]
    period = float(bag.episode['spec']['period'])
    # A step plot draws a value over [edge_i, edge_i+1): the last held interval needs its end too.
    edges = np.append(times, count * period)
    return times, np.degrees(errors), edges, np.vstack([torque, torque[-1:]]), bool(episode.diverged[0])


def _plain_log_ticks(axis) -> None:
    """Ticks of a log axis at 1, 2, 5 × 10^k printed as plain numbers: the defaults print 3×10⁻¹ and collide."""
    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FormatStrFormatter('%g'))
    axis.set_minor_formatter(NullFormatter())


def tracking_figure(path: Path, episodes: dict, case: Case) -> None:
    """Error and applied torque per joint over time, for each controller's (Table 4 row, bag) in `episodes`.

    Joints are labelled by the names their bags recorded, so any arm the URDF describes is drawn."""
    joints = next(iter(episodes.values()))[1].joints
    figure = _new_figure(11, 2.6 * len(joints) + 1.0)
    axes = figure.subplots(len(joints), 2, sharex=True, squeeze=False)
    for controller, (row, bag) in episodes.items():
        times, errors, edges, torque, diverged = _episode_series(bag)
        label = (f'{CONTROLLER_NAMES[controller]} (delay d = {row.delay}): I1 = {number(row.I1)}, '
                 f'I2 = {number(row.I2)}' + (f' (DIVERGED at t = {times[-1]:g} s)' if diverged else ''))
        for j in range(len(joints)):
            axes[j, 0].plot(times, errors[:, j], color=COLOURS[controller], label=label)
            axes[j, 1].step(edges, torque[:, j], where='post', color=COLOURS[controller])
    nominal = next(iter(episodes.values()))[1]  # one trajectory, so one nominal torque for both
    for j, joint in enumerate(joints):
        axes[j, 1].plot(nominal.reference_times, nominal.nominal[:, j], 'k--', linewidth=1.2)
        axes[j, 0].axhline(0.0, color='0.6', linewidth=0.8)
        axes[j, 0].set_ylabel(f'{joint}\nerror (deg)')
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
    figure.suptitle(f'Table 4 optima of (3.2): {case_text(case.trajectory, case.duration, case.period)}')
    figure.legend(handles, labels, loc='upper center', ncol=2, bbox_to_anchor=(0.5, 0.965), frameon=False)
    figure.tight_layout(rect=(0, 0, 1, 0.92))
    figure.savefig(path)


def _index_series(axis, rows: list) -> dict:
    """Draw one panel's rows; returns the legend entries it drew, by label."""
    drawn = {}
    for controller in CONTROLLERS:
        ours = sorted((row for row in rows if row.controller == controller), key=lambda row: row.tau)
        if not ours:
            continue
        colour, name = COLOURS[controller], CONTROLLER_NAMES[controller]
        values = np.array([np.nan if row.diverged else row.I1 for row in ours], dtype=float)
        drawn[f'{name}, ours'], = axis.plot([row.tau for row in ours], values, '-o', color=colour, markersize=4)
        paper = [(row.tau, row.paper) for row in ours if row.paper is not None]
        if paper:
            drawn[f'{name}, paper'], = axis.plot(*zip(*paper), 'o', markersize=8, markerfacecolor='none',
                                                 markeredgecolor=colour, markeredgewidth=1.5)
        over = [row for row in ours if not row.within_limits and not row.diverged]
        if over:
            drawn['torque reached the limit 2 max $|P^{nom}|$'], = axis.plot(
                [row.tau for row in over], [row.I1 for row in over], 's', markersize=9,
                markerfacecolor='none', markeredgecolor='k', markeredgewidth=0.8)
    return drawn


def _mark_diverged(axis, rows: list) -> dict:
    """A cross at the top of the panel for each diverged episode: its partial index would mislead."""
    diverged = [row for row in rows if row.diverged]
    if not diverged:
        return {}
    top = axis.get_ylim()[1]
    marks = {}
    for controller in CONTROLLERS:
        taus = [row.tau for row in diverged if row.controller == controller]
        if taus:
            marks['diverged (drawn at the top)'], = axis.plot(taus, [top] * len(taus), 'x', color=COLOURS[controller],
                                                              markersize=10, markeredgewidth=2.5, clip_on=False)
    axis.set_ylim(top=top)
    return marks


def index_vs_tau_figure(path: Path, results: Results, settings: PaperSettings) -> None:
    """Index (2.5) against τ: Table 2 unlimited and limited and Table 3, ours as lines, the paper's hollow."""
    panels = [('Table 2, gains for (2.5), torque unlimited', [row for row in results.table2 if not row.limited]),
              ('Table 2, gains for (2.5), torque limited', [row for row in results.table2 if row.limited]),
              ('Table 3, gains for (3.2), torque unlimited', results.table3)]
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
    case = settings.case
    figure.suptitle(r'Sensitivity to the initial velocity disturbance $\dot q(0) = -\dot q^d(\tau)$: '
                    + case_text(case.trajectory, case.duration, case.period))
    figure.tight_layout(rect=(0, 0.12, 1, 1))
    figure.savefig(path)


def table4_figure(path: Path, results: Results) -> None:
    """Table 4 as grouped bars: per case, each controller's I1 and I2 stacked, ours beside the paper's."""
    cases = table4_cases(results)
    rows = {(row.controller, row.trajectory, row.duration, row.period): row for row in results.table4}
    figure = _new_figure(13, 5.5)
    axis = figure.subplots()
    width = 0.2
    bars = [(controller, source) for controller in CONTROLLERS for source in ('ours', 'paper')]
    for c, case in enumerate(cases):
        for k, (controller, source) in enumerate(bars):
            row = rows.get((controller, *case))
            if row is None or (source == 'paper' and row.paper is None):
                continue
            figures = row if source == 'ours' else row.paper
            x = c + (k - 1.5) * width
            axis.text(x, -0.01, source, ha='center', va='top', fontsize=8, transform=axis.get_xaxis_transform())
            if source == 'ours' and (row.diverged or not np.isfinite([row.I1, row.I2]).all()):
                axis.text(x, 0, 'diverged', ha='center', va='bottom', rotation=90, color=COLOURS[controller])
                continue
            style = {'hatch': '///', 'edgecolor': 'white', 'linewidth': 0} if source == 'paper' else {}
            axis.bar(x, figures.I1, width * 0.95, color=COLOURS[controller], **style)
            axis.bar(x, figures.I2, width * 0.95, bottom=figures.I1, color=COLOURS[controller], alpha=0.4, **style)
            label = number(figures.I) if source == 'ours' else paper_number(figures.I)
            axis.text(x, max(figures.I, figures.I1 + figures.I2), label, ha='center', va='bottom', fontsize=8)
    axis.set_xticks(range(len(cases)),
                    [f'trajectory {t}\nT = {duration:g} s, Δ = {period:g} s' for t, duration, period in cases])
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


# The stability map's damping axis: around the ω rules' ζ = 1, through the d = 0 corner at ζ = 1/2.
STABILITY_ZETAS = np.linspace(0.3, 2.0, 171)


def stability_figure(path: Path, results: Results, settings: PaperSettings) -> None:
    """The stability map of computed torque with an exact model: the boundary ωΔ* against ζ for d = 0, 1, 2, the
    paper's operating point (ζ = 1, ω at the claimed Δ) and the recorded episodes at ω, each at its own ωΔ."""
    omega, claimed = settings.stability.omega, settings.stability.claimed_period
    delay = settings.delays['computed_torque']
    rows = sorted(results.section2.stability, key=lambda row: row.period)
    points = [omega * claimed] + [omega * row.period for row in rows]
    bottom, top = 0.5 * min(points), max(3.0, 1.5 * max(points))
    figure = _new_figure(11, 5.5)
    axis = figure.subplots()
    axis.set_yscale('log')
    styles = ('--', '-.', ':')
    for d in sorted({*settings.beyond.stability_map.delays, delay}):
        boundary = [boundary_omega_delta(d, zeta) for zeta in STABILITY_ZETAS]
        if d == delay:
            axis.fill_between(STABILITY_ZETAS, bottom, boundary, color='tab:green', alpha=0.08, linewidth=0)
        axis.plot(STABILITY_ZETAS, boundary, linewidth=2.2 if d == delay else 1.2,
                  color='tab:green' if d == delay else '0.4', linestyle='-' if d == delay else styles[d % 3],
                  label=f'boundary ωΔ*, d = {d}' + (' (the paper\'s delay;\nshaded: stable)' if d == delay else ''))
        axis.annotate(f'd = {d}', (STABILITY_ZETAS[-1], boundary[-1]), textcoords='offset points', xytext=(4, 0),
                      va='center', fontsize=9, annotation_clip=False)
    for diverged, marker, label in ((False, 'o', f'recorded episode at ω = {omega:g}: ran to T'),
                                    (True, 'X', f'recorded episode at ω = {omega:g}: diverged')):
        chosen = [row for row in rows if row.diverged_at_omega_15 == diverged]
        if chosen:
            axis.plot([1.0] * len(chosen), [omega * row.period for row in chosen], marker, linestyle='none',
                      color='tab:red' if diverged else 'tab:blue', markersize=8, zorder=4, label=label)
    for row in rows:
        axis.annotate(f'Δ = {row.period:g} s', (1.0, omega * row.period), textcoords='offset points',
                      xytext=(9, -3), fontsize=8)
    axis.plot([1.0], [omega * claimed], '*', color='gold', markeredgecolor='k', markersize=20, zorder=3,
              label=f'the paper: ω = {omega:g} at {1 / claimed:g} Hz (ωΔ = {omega * claimed:g}, ζ = 1)')
    axis.axvline(1.0, color='k', linewidth=0.5)
    axis.set_xlim(STABILITY_ZETAS[0], STABILITY_ZETAS[-1])
    axis.set_ylim(bottom, top)
    _plain_log_ticks(axis.yaxis)
    axis.set_xlabel('damping ζ of the ω rule (k_p = ω², k_v = 2ζω; the paper: ζ = 1)')
    axis.set_ylabel('ωΔ (ω in rad/s, Δ the sampling period in s)')
    axis.grid(True, which='both', alpha=0.3)
    axis.legend(fontsize=9, loc='upper left', bbox_to_anchor=(1.06, 1))
    axis.set_title('Computed torque with an exact model: the stability boundary ωΔ* of the sampled loop\n'
                   f'(zero-order hold, delay d samples); the recorded episodes at d = {delay}, ζ = 1', fontsize=10)
    figure.tight_layout()
    figure.savefig(path)


def pareto_figure(path: Path, results: Results, settings: PaperSettings) -> None:
    """The I1–I2 front (in-process) with the seeds' episodes as scored from their bags and the paper's Table 4 point."""
    front = results.pareto
    case = Case(trajectory=front.trajectory, duration=front.duration, period=front.period)
    figure = _new_figure(8, 5.5)
    axis = figure.subplots()
    I1 = np.array([point.I1 for point in front.front])
    I2 = np.array([point.I2 for point in front.front])
    axis.plot(I1, I2, '-o', color=COLOURS[front.controller], markersize=3.5,
              label=f'front, in-process ({len(I1)} of {front.front_size} non-dominated episodes)')
    # The seeds as their bags score them: the (2.5) optimum's undisturbed Table 2 episode, the (3.2) one's Table 4.
    recorded = {row.gains: row for row in results.table4 if row.gains in front.seeds}
    recorded.update({row.gains: row for row in results.table2 if row.gains in front.seeds and row.tau == 0
                     and not row.limited and row.gains not in recorded})
    markers = {'I1': ('s', 'our (2.5) optimum'), 'I': ('D', 'our (3.2) optimum')}
    for name in front.seeds:
        row = recorded.get(name)
        if row is None or row.diverged:
            continue
        marker, label = markers[results.gain_set(name).index]
        axis.plot(row.I1, row.I2, marker, color='k', markersize=9, markerfacecolor='none', markeredgewidth=1.6,
                  label=f'{label}, scored from its bag')
    paper = settings.table4_figures(front.controller, case)
    axis.plot(paper.I1, paper.I2, '*', color='tab:orange', markersize=13, label="the paper's Table 4 (3.2) optimum")
    axis.set_xscale('log')
    axis.set_yscale('log')
    _plain_log_ticks(axis.xaxis)
    _plain_log_ticks(axis.yaxis)
    axis.set_xlabel('I1 (2.5), tracking error')
    axis.set_ylabel('I2, torque deviation from nominal')
    axis.set_title(f'{CONTROLLER_NAMES[front.controller]}, {case_text(front.trajectory, front.duration, front.period)}')
    axis.grid(True, which='both', alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)
