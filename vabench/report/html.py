"""report.html: one self-contained page; figures are embedded as base64 data URLs and the
style is inline, so the file can be mailed or archived alone."""

from __future__ import annotations

import base64
from collections.abc import Sequence
from html import escape

from vabench.tables import Section, Table

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f2f2f2; }
img { max-width: 100%; display: block; margin: 0.5em 0 1.5em; }
.notes li { color: #844; }
"""


def _table(t: Table) -> str:
    head = "".join(f"<th>{escape(h)}</th>" for h in t.header)
    body = "".join(
        "<tr>" + "".join(f"<td>{escape(c)}</td>" for c in row) + "</tr>" for row in t.rows
    )
    return f"<h3>{escape(t.title)}</h3>\n<table><tr>{head}</tr>{body}</table>\n"


def _image(title: str, png: bytes) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (
        f'<img alt="{escape(title)}" title="{escape(title)}" src="data:image/png;base64,{data}">\n'
    )


def render(
    title: str,
    summary: Sequence[str],
    sections: Sequence[Section],
    figures: Sequence[tuple[str, str, bytes]],
) -> str:
    """`figures`: (section name it belongs under, title, PNG bytes)."""
    parts = [
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>",
        f"<title>{escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{escape(title)}</h1>",
        "<ul>" + "".join(f"<li>{escape(s)}</li>" for s in summary) + "</ul>",
    ]
    for section in sections:
        parts.append(f"<h2>{escape(section.title)}</h2>")
        if section.notes:
            parts.append(
                "<ul class='notes'>"
                + "".join(f"<li>{escape(n)}</li>" for n in section.notes)
                + "</ul>"
            )
        parts += [_image(t, png) for name, t, png in figures if name == section.name]
        parts += [_table(t) for t in section.tables]
    parts.append("</body></html>\n")
    return "\n".join(parts)
