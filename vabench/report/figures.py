"""PNG figures, returned as bytes.

Each figure is a bare matplotlib `Figure` drawn by an explicit Agg canvas: no display, and no
pyplot global state (backend, open-figure list), so the report can run inside a long-lived
sweep process without changing its backend or leaking figures.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.container import BarContainer
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from vabench.report.active_passive import TrackComparison, in_order
from vabench.report.stats import SUBSET_TITLES, SUBSETS, Cell, Spread

_DPI = 110
_OUTSIDE: dict = {"fontsize": 8, "loc": "upper left", "bbox_to_anchor": (1.01, 1.0)}
"""Legends right of the axes: inside, they would cover the bars near 100 %."""


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI, bbox_inches="tight", metadata={"Software": None})
    return buf.getvalue()


def _values(ax: Axes, bars: BarContainer, values: Sequence[float]) -> None:
    """Each bar's value above it: a bar at 0 % is otherwise no bar at all, and a reader cannot
    tell a failed family from a missing one."""
    ax.bar_label(bars, labels=[f"{v:.0f}" for v in values], fontsize=7, padding=2)


def task_success_figure(
    cells: Sequence[Cell],
    spreads: Mapping[tuple[str, str, str], Spread],
    model: str,
    track: str,
    order: Sequence[str],
) -> bytes:
    """Bars: mean success per task across runs; error bars: sample SD; dots: each run."""
    rank = {t: i for i, t in enumerate(order)}
    mine = [c for c in cells if (c.model, c.track) == (model, track)]
    tasks = sorted({c.task for c in mine}, key=lambda t: (rank.get(t, len(rank)), t))
    means = [100 * float(spreads[(model, track, t)].mean) for t in tasks]
    sds = [100 * (spreads[(model, track, t)].sd or 0.0) for t in tasks]
    fig = Figure(figsize=(max(6.0, 0.55 * len(tasks) + 2), 4.2))
    ax = fig.add_subplot()
    xs = range(len(tasks))
    bars = ax.bar(xs, means, yerr=sds, capsize=3, color="#4C72B0", alpha=0.8, label="mean ± SD")
    _values(ax, bars, means)
    for i, task in enumerate(tasks):
        runs = [100 * float(c.rate) for c in mine if c.task == task]
        # spread the run dots sideways so equal rates of different runs stay visible
        offsets = [0.3 * (k / max(1, len(runs) - 1) - 0.5) for k in range(len(runs))]
        ax.scatter(
            [i + o for o in offsets],
            runs,
            color="black",
            s=12,
            zorder=3,
            label="run" if i == 0 else None,
        )
    ax.set_xticks(list(xs), tasks, rotation=60, ha="right", fontsize=8)
    ax.set_ylim(0, 105)
    ax.set_ylabel("success (%)")
    ax.set_title(f"{model} — {track}: per-task success")
    ax.legend(**_OUTSIDE)
    return _png(fig)


def active_passive_figure(cmp: TrackComparison, order: Sequence[str]) -> bytes:
    """Grouped bars of active and passive success rate per family, with the sign test."""
    families = in_order(cmp.families, order)
    tasks = [p.task for p in families]
    active = [100 * p.active / p.active_total for p in families]
    passive = [100 * p.passive / p.passive_total for p in families]
    fig = Figure(figsize=(max(6.0, 0.55 * len(tasks) + 2), 4.2))
    ax = fig.add_subplot()
    xs = list(range(len(tasks)))
    bars = ax.bar([x - 0.2 for x in xs], active, width=0.4, label="active", color="#4C72B0")
    _values(ax, bars, active)
    bars = ax.bar([x + 0.2 for x in xs], passive, width=0.4, label="passive", color="#DD8452")
    _values(ax, bars, passive)
    ax.set_xticks(xs, tasks, rotation=60, ha="right", fontsize=8)
    ax.set_ylim(0, 105)
    ax.set_ylabel("success (%)")
    runs = ",".join(map(str, cmp.runs))
    ax.set_title(
        f"{cmp.model} (runs {runs}): passive worse on {cmp.passive_worse} of {cmp.non_tied} "
        f"non-tied families, sign test p = "
        + ("—" if cmp.p_value is None else f"{float(cmp.p_value):.3g}")
        + (f" ({len(cmp.skipped)} all-skipped left out)" if cmp.skipped else ""),
        fontsize=9,
    )
    ax.legend(**_OUTSIDE)
    return _png(fig)


SUBSET_COLOURS = {"single": "#4C72B0", "dual": "#DD8452", "all": "#55A868"}
"""Fixed per subset: a subset without bars must not shift the others' colours, nor take a
colour of theirs in the legend (matplotlib gives an empty bar series the first colour)."""


def macro_figure(spreads: Mapping[tuple[str, str, str], Spread]) -> bytes:
    """Macro-average success per model and track (mean ± SD) for each family subset. A subset
    with no family in any run is named in the legend as having no data, hatched and empty;
    without any scored episode the axes say so."""
    pairs = sorted({(m, t) for m, t, _ in spreads})
    fig = Figure(figsize=(max(6.0, 1.2 * len(pairs) + 2), 4.2))
    ax = fig.add_subplot()
    width = 0.8 / len(SUBSETS)
    handles = []
    for j, subset in enumerate(SUBSETS):
        xs, ys, es = [], [], []
        for i, pair in enumerate(pairs):
            s = spreads.get((*pair, subset))
            if s is not None:
                xs.append(i + (j - 1) * width)
                ys.append(100 * float(s.mean))
                es.append(100 * (s.sd or 0.0))
        colour = SUBSET_COLOURS[subset]
        _values(ax, ax.bar(xs, ys, width=width, yerr=es, capsize=3, color=colour), ys)
        title = SUBSET_TITLES[subset]
        handles.append(
            Patch(facecolor=colour, label=title)
            if xs
            else Patch(facecolor="white", edgecolor=colour, hatch="//", label=f"{title} (no data)")
        )
    ax.set_xticks(range(len(pairs)), [f"{m}\n{t}" for m, t in pairs], fontsize=8)
    ax.set_ylim(0, 105)
    ax.set_ylabel("macro-average success (%)")
    ax.set_title("Macro-average success, mean ± sample SD across runs")
    if pairs:
        ax.legend(handles=handles, **_OUTSIDE)
    else:
        ax.text(0.5, 0.5, "no scored episode yet", ha="center", va="center", transform=ax.transAxes)
    return _png(fig)
