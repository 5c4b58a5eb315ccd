"""Pages the viewer renders on the server as plain HTML (no script): the run list, the
side-by-side comparison of one trial, and the static bundle's pages.

Every value from a run is escaped here; only `Html` (markup built by these helpers) passes
through as is. Links and image sources are relative, so the same markup works under a run's
prefix (`/runs/<k>/`) and from disk (`--bundle`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from html import escape
from urllib.parse import urlencode


class Html(str):
    """Markup already escaped (built here): inserted as is."""


Cell = str | int | float | Html | None


def text(value: Cell) -> Html:
    if isinstance(value, Html):
        return value
    return Html(escape("" if value is None else str(value)))


def link(href: str, label: Cell) -> Html:
    return Html(f"<a href='{escape(href)}'>{text(label)}</a>")


def image(src: str, alt: str) -> Html:
    return Html(f"<img class='thumb' src='{escape(src)}' alt='{escape(alt)}'>")


def query(path: str, **params: object) -> str:
    """`path?a=1&b=2` (values quoted)."""
    return f"{path}?{urlencode({k: str(v) for k, v in params.items()})}"


def table(header: Sequence[str], rows: Iterable[Sequence[Cell]], css: str = "") -> Html:
    head = "".join(f"<th>{text(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{text(c)}</td>" for c in row) + "</tr>" for row in rows)
    return Html(f"<table class='{escape(css)}'><thead><tr>{head}</tr></thead>{body}</table>")


def document(title: str, parts: Iterable[Cell], css: str = "static/app.css") -> str:
    """A whole page; `css` relative to the page."""
    body = "\n".join(text(p) for p in parts)
    return (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{text(title)}</title><link rel='stylesheet' href='{escape(css)}'></head>"
        f"<body data-ready='1'>\n{body}\n</body></html>"
    )


def percent(part: int, whole: int) -> str:
    return f"{100 * part / whole:.1f} %" if whole else "–"
