"""report.html: one self-contained page; figures are embedded as base64 data URLs and the
style is inline, so the file can be mailed or archived alone.

The page opens with what a reader must know first (an unfinished sweep), the summary and a
table of contents; each figure sits beside the table it draws (side by side where the window
is wide enough, one above the other where it is not), so a number and its picture are read
together; a figure without a table of its own closes its section.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass
from html import escape

from vabench.report.published import REFERENCE_SHORT
from vabench.tables import Section, Table

_STYLE = """
body { font-family: system-ui, sans-serif; color: #222; line-height: 1.4;
       max-width: 1600px; margin: 0 auto; padding: 1.5rem clamp(1rem, 4vw, 3.5rem) 4rem; }
h1 { margin-top: 0; }
h2 { margin-top: 2.5rem; border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
h3 { margin: 1em 0 0.3em; font-size: 1em; }
table { border-collapse: collapse; margin: 0.3em 0 1.2em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f2f2f2; }
.alert { background: #fff3cd; border: 1px solid #e0b400; padding: 0.6em 1em; font-weight: 600; }
nav.toc { background: #f7f7f7; border: 1px solid #e2e2e2; padding: 0.4em 1.2em;
          display: inline-block; }
nav.toc h2 { margin: 0.3em 0; border: none; font-size: 1.1em; }
.pair { display: flex; flex-wrap: wrap; gap: 0 2rem; align-items: flex-start; }
.pair > .table { flex: 0 1 auto; max-width: 100%; overflow-x: auto; }
.pair > figure { flex: 1 1 420px; max-width: 720px; margin: 0.8em 0 1.2em; }
figure { margin: 0.8em 0 1.2em; }
img { max-width: 100%; height: auto; display: block; }
figcaption { font-size: 0.85em; color: #555; }
.notes li { color: #844; }
tr.reference td { color: #888; background: #f7f7f7; font-style: italic; }
"""


@dataclass(frozen=True)
class Figure:
    section: str
    """The name of the section it belongs under."""
    title: str
    png: bytes
    beside: str | None = None
    """The title of the table it draws; None (or no such table): at the section's end."""


def _row(row: Sequence[str]) -> str:
    """A published reference row (its source cell `REFERENCE_SHORT`) is greyed: never read as
    a run's own numbers."""
    cls = " class='reference'" if REFERENCE_SHORT in row else ""
    return f"<tr{cls}>" + "".join(f"<td>{escape(c)}</td>" for c in row) + "</tr>"


def _table(t: Table) -> str:
    head = "".join(f"<th>{escape(h)}</th>" for h in t.header)
    body = "".join(_row(row) for row in t.rows)
    return f"<h3>{escape(t.title)}</h3>\n<table><tr>{head}</tr>{body}</table>\n"


def _image(title: str, png: bytes) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (
        f'<figure><img alt="{escape(title)}" title="{escape(title)}" '
        f'src="data:image/png;base64,{data}"><figcaption>{escape(title)}</figcaption></figure>\n'
    )


def _section(section: Section, figures: Sequence[Figure]) -> list[str]:
    parts = [f"<section id='{escape(section.name)}'>", f"<h2>{escape(section.title)}</h2>"]
    if section.notes:
        parts.append(
            "<ul class='notes'>" + "".join(f"<li>{escape(n)}</li>" for n in section.notes) + "</ul>"
        )
    titles = {t.title for t in section.tables}
    for table in section.tables:
        beside = [f for f in figures if f.beside == table.title]
        if beside:
            images = "".join(_image(f.title, f.png) for f in beside)
            parts.append(
                f"<div class='pair'><div class='table'>{_table(table)}</div>{images}</div>"
            )
        else:
            parts.append(_table(table))
    parts += [_image(f.title, f.png) for f in figures if f.beside not in titles]
    parts.append("</section>")
    return parts


def render(
    title: str,
    summary: Sequence[str],
    sections: Sequence[Section],
    figures: Sequence[Figure],
    alerts: Sequence[str] = (),
) -> str:
    """The page: `alerts` (shown first, highlighted), `summary`, contents, the sections."""
    toc = "".join(f"<li><a href='#{escape(s.name)}'>{escape(s.title)}</a></li>" for s in sections)
    parts = [
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>{escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{escape(title)}</h1>",
        *[f"<p class='alert'>{escape(a)}</p>" for a in alerts],
        "<ul>" + "".join(f"<li>{escape(s)}</li>" for s in summary) + "</ul>",
        f"<nav class='toc'><h2>Contents</h2><ol>{toc}</ol></nav>",
    ]
    for section in sections:
        parts += _section(section, [f for f in figures if f.section == section.name])
    parts.append("</body></html>\n")
    return "\n".join(parts)
