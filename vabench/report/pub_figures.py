"""The paper's three headline figures as PNG bytes: overall success bars, the task-by-model
heatmap, and the capability radar (one condition, or a sheet of small multiples).

Drawn like `figures` (a bare `Figure` on an Agg canvas, no pyplot state). Published reference
values are drawn grey and labelled `published.REFERENCE_LABEL` wherever they appear, so they
are never read as a run's own.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from vabench.report.figures import SUBSET_COLOURS, _png
from vabench.report.publication import CRITERIA, Bars, Profile
from vabench.report.published import REFERENCE_LABEL
from vabench.report.stats import SUBSET_TITLES, SUBSETS

REFERENCE_COLOURS = {"single": "#B8B8B8", "dual": "#D6D6D6", "all": "#999999"}
_GREY_TEXT = "#777777"
RADAR_RANGE = (0.0, 100.0)
"""Fixed for every condition (no min-max normalisation, as the paper plots them)."""


def overall_figure(rows: Sequence[Bars]) -> bytes:
    """Horizontal bars per condition (single-arm, dual-arm, all), mean ± sample SD across runs,
    the value printed at each bar; reference rows below the run's, grey, under their label."""
    n = len(rows)
    height = 0.8 / len(SUBSETS)
    fig = Figure(figsize=(8.6, max(2.6, 0.42 * n + 1.6)))
    ax = fig.add_subplot()
    for j, subset in enumerate(SUBSETS):
        for i, row in enumerate(rows):
            if subset not in row.values:
                continue
            mean, sd = row.values[subset]
            y = i + (j - 1) * height
            colour = (REFERENCE_COLOURS if row.reference else SUBSET_COLOURS)[subset]
            ax.barh(
                y,
                mean,
                height=height,
                xerr=None if sd is None else sd,
                color=colour,
                error_kw={"elinewidth": 0.8, "capsize": 1.5, "ecolor": "#333333"},
            )
            ax.text(
                min(mean + (sd or 0.0), 100.0) + 1.0,
                y,
                f"{mean:.1f}",
                va="center",
                fontsize=6,
                color=_GREY_TEXT if row.reference else "#222222",
            )
    ax.set_yticks(range(n), [r.label + r.mark for r in rows], fontsize=7.5)
    for tick, row in zip(ax.get_yticklabels(), rows, strict=True):
        if row.reference:
            tick.set_color(_GREY_TEXT)
            tick.set_fontstyle("italic")
    first_ref = next((i for i, r in enumerate(rows) if r.reference), None)
    if first_ref is not None and first_ref > 0:
        ax.axhline(first_ref - 0.5, color="#444444", linewidth=0.8, linestyle="--")
    ax.set_ylim(n - 0.5, -0.5)  # the first row at the top
    ax.set_xlim(0, 110)
    ax.set_xticks([0, 20, 40, 60, 80, 100])
    ax.set_xlabel("success (%): mean of the run-level macro-averages ± sample SD across runs")
    ax.set_title("Overall success per condition", fontsize=10)
    handles = [Patch(facecolor=SUBSET_COLOURS[s], label=SUBSET_TITLES[s]) for s in SUBSETS]
    if first_ref is not None:
        handles.append(Patch(facecolor=REFERENCE_COLOURS["all"], label=_wrap(REFERENCE_LABEL)))
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    if not rows:
        ax.text(0.5, 0.5, "no scored episode yet", ha="center", va="center", transform=ax.transAxes)
    return _png(fig)


def _wrap(text: str, width: int = 34) -> str:
    words, lines, line = text.split(), [], ""
    for w in words:
        if line and len(line) + 1 + len(w) > width:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    return "\n".join([*lines, line])


def heatmap_figure(
    tasks: Sequence[str],
    columns: Sequence[str],
    values: Mapping[tuple[str, str], tuple[float, float | None]],
    title: str,
    dual: Sequence[str] = (),
    reference: bool = False,
) -> bytes:
    """Tasks (rows) by conditions (columns): the mean success % printed in each cell, its SD
    below; an empty cell: the condition did not run the task. `dual`: the dual-arm tasks,
    set apart by a line above the first of them."""
    grid = np.full((len(tasks), len(columns)), np.nan)
    for i, task in enumerate(tasks):
        for j, col in enumerate(columns):
            if (task, col) in values:
                grid[i, j] = values[(task, col)][0]
    fig = Figure(figsize=(max(5.0, 0.78 * len(columns) + 3.2), 0.36 * len(tasks) + 2.2))
    ax = fig.add_subplot()
    cmap = "Greys" if reference else "Blues"
    image = ax.imshow(np.ma.masked_invalid(grid), cmap=cmap, vmin=0, vmax=100, aspect="auto")
    for (i, j), v in np.ndenumerate(grid):
        if math.isnan(v):
            continue
        sd = values[(tasks[i], columns[j])][1]
        text = f"{v:.1f}" if sd is None else f"{v:.1f}\n±{sd:.1f}"
        ax.text(
            j,
            i,
            text,
            ha="center",
            va="center",
            fontsize=6,
            linespacing=0.95,
            color="white" if v > 60 else "#111111",
        )
    ax.set_xticks(range(len(columns)), columns, rotation=40, ha="right", fontsize=7.5)
    ax.set_yticks(range(len(tasks)), tasks, fontsize=7.5)
    first_dual = next((i for i, t in enumerate(tasks) if t in set(dual)), None)
    if first_dual:
        ax.axhline(first_dual - 0.5, color="#333333", linewidth=1.0)
    ax.set_title(title, fontsize=9, color=_GREY_TEXT if reference else "#222222")
    bar = fig.colorbar(image, ax=ax, fraction=0.03, pad=0.02)
    bar.set_label("success (%), mean ± SD across runs", fontsize=7)
    bar.ax.tick_params(labelsize=7)
    return _png(fig)


def _radar(ax, profile: Profile, title_size: float = 8.5) -> None:
    # TL at the top, clockwise: angles in [0, 2 pi) on an axis turned and mirrored
    ax.set_theta_offset(math.pi / 2)
    ax.set_theta_direction(-1)
    angles = [2 * math.pi * k / len(CRITERIA) for k in range(len(CRITERIA))]
    values = [profile.values[c] for c in CRITERIA]
    # NaN breaks the outline where a criterion is NA: a gap, not a drop to 0
    closed = [*values, values[0]]
    ys = [np.nan if v is None else v for v in closed]
    xs = [*angles, angles[0]]
    ax.plot(xs, ys, color="#4C72B0", linewidth=1.4)
    known = [(a, v) for a, v in zip(angles, values, strict=True) if v is not None]
    if len(known) == len(values):
        ax.fill(angles, values, color="#4C72B0", alpha=0.22)
    ax.scatter([a for a, _ in known], [v for _, v in known], s=9, color="#4C72B0", zorder=3)
    ax.set_ylim(*RADAR_RANGE)
    ax.set_yticks([25, 50, 75, 100], ["25", "50", "75", "100"], fontsize=5.5, color="#888888")
    ax.set_rlabel_position(180 / len(CRITERIA))
    labels = [
        f"{c}\n{'NA' if v is None else f'{v:.0f}'}" for c, v in zip(CRITERIA, values, strict=True)
    ]
    ax.set_xticks(angles, labels, fontsize=6.5)
    ax.tick_params(axis="x", pad=-1)
    ax.set_title(
        f"{profile.model} — {profile.track}\nannotated {profile.runs_text}, "
        f"{profile.episodes} episodes",
        fontsize=title_size,
        pad=12,
    )


def _polar_axes(fig: Figure, rows: int, cols: int, k: int):
    return fig.add_subplot(rows, cols, k, projection="polar")


def radar_figure(profile: Profile) -> bytes:
    """One condition's nine criteria on a fixed 0-100 radar, each axis labelled with its %."""
    fig = Figure(figsize=(3.6, 3.7))
    _radar(_polar_axes(fig, 1, 1, 1), profile)
    return _png(fig)


def radar_sheet(profiles: Sequence[Profile], columns: int = 4) -> bytes:
    """Small multiples: every condition's radar on the same fixed scale, `columns` a row."""
    n = max(1, len(profiles))
    cols = min(columns, n)
    rows = math.ceil(n / cols)
    height = 3.15 * rows + 1.0
    fig = Figure(figsize=(2.9 * cols, height))
    for k, profile in enumerate(profiles, start=1):
        _radar(_polar_axes(fig, rows, cols, k), profile, title_size=7.5)
    fig.suptitle(
        "Capability profile (%, majority vote; ED, OC, PF over episodes with an error; "
        "AE over episodes with an ambiguity)",
        fontsize=8.5,
        y=1 - 0.2 / height,
    )
    fig.subplots_adjust(hspace=0.62, wspace=0.45, top=1 - 1.0 / height)
    return _png(fig)
