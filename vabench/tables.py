"""The table model of the report and the diagnostics, and its text: display tables and CSV
files grouped in sections, number formatting, Markdown and CSV.

Display tables show percentages with two decimals, as the paper does ("53.93 ± 3.17"), and
differences as signed points ("-10.00"); CSV files keep raw numbers (counts, rates in [0, 1])
in long format, one row per value. The sections themselves are built in `vabench.report`
(`base_tables`, `summary_tables`, `suite_tables`, `spend`) and `vabench.diagnostics.sections`.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any, Protocol


@dataclass
class Table:
    title: str
    header: list[str]
    rows: list[list[str]]


@dataclass
class Csv:
    name: str
    header: list[str]
    rows: list[list[Any]]


@dataclass
class Section:
    """One topic of the report: written as NAME.md (its tables) and one CSV file or more."""

    name: str
    title: str
    tables: list[Table]
    csvs: list[Csv]
    notes: list[str] = field(default_factory=list)


def pct(x: Fraction | float | None, sign: bool = False) -> str:
    """A share in percent, two decimals; `sign`: signed points ("+12.50")."""
    return "—" if x is None else f"{100 * float(x):{'+' if sign else ''}.2f}"


def signed(x: Fraction | None) -> str:
    return pct(x, sign=True)


class MeanSd(Protocol):
    """A mean and its sample SD (None for one value), as `report.stats.Spread` holds them."""

    @property
    def mean(self) -> Fraction: ...
    @property
    def sd(self) -> float | None: ...


def mean_sd_text(s: MeanSd | None, sign: bool = False) -> str:
    """ "mean ± SD" in percent ("mean (1 run)" without an SD); `sign`: a signed mean."""
    if s is None:
        return "—"
    if s.sd is None:
        return f"{pct(s.mean, sign)} (1 run)"
    return f"{pct(s.mean, sign)} ± {pct(s.sd)}"


def runs_label(runs: Sequence[int]) -> str:
    return f"run {runs[0]}" if len(runs) == 1 else "runs " + ",".join(map(str, runs)) + " pooled"


def runs_text(runs: Sequence[int]) -> str:
    return ",".join(map(str, runs)) if runs else "—"


def p_value_text(p: Fraction | None) -> str:
    """The sign test's p, or a dash where no family could be compared."""
    return "—" if p is None else f"{float(p):.4g}"


def to_markdown(table: Table) -> str:
    def esc(s: str) -> str:
        return s.replace("|", "\\|")

    lines = [f"### {table.title}", "", "| " + " | ".join(map(esc, table.header)) + " |"]
    lines.append("|" + "|".join("---" for _ in table.header) + "|")
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in table.rows]
    return "\n".join(lines) + "\n"


def section_markdown(section: Section) -> str:
    parts = [f"## {section.title}\n"]
    if section.notes:
        parts.append("".join(f"- {n}\n" for n in section.notes))
    parts += [to_markdown(t) for t in section.tables]
    return "\n".join(parts)


def to_csv(table: Csv) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(table.header)
    for row in table.rows:
        writer.writerow([float(v) if isinstance(v, Fraction) else v for v in row])
    return buf.getvalue()
