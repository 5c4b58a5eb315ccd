"""A directory of runs: `python -m vabench.view runs/` when runs/ is no run itself.

A run directory is one holding results.jsonl or plan.json (a sweep writes the plan before its
first episode). The runs are looked for down to `MAX_DEPTH` levels below the directory given
(runs/<name>/, runs/<group>/<name>/, runs/<a>/<b>/<name>/), never inside a run and never in
hidden folders; they are found once, when the viewer starts (restart it to see a new run).

Pages:
    /                          the run list: name, models, episodes done / planned, success
                               rate over the scored episodes, date of the first episode
    /compare?task=&seed=&track=  every model's episode of that trial, across all runs
    /runs/<k>/...              run k's own pages (`app.Viewer`), unchanged

Each run's index is loaded when the viewer starts (as for one run) and kept current as its
sweep writes; a run that cannot be read is listed with its problem instead of its numbers.
The list's numbers are computed once per version of each run's index.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from aiohttp import web

from vabench.diagnostics.episodes import RunDirError
from vabench.run_layout import PLAN, RESULTS, RunDir
from vabench.view.app import SECURITY_HEADERS, STATIC, Handler, Viewer
from vabench.view.compare import Source, Trials, page
from vabench.view.pages import Cell, Html, document, link, percent, table, text

MAX_DEPTH = 3
"""How many levels below the given directory runs are looked for."""


def is_run(path: Path) -> bool:
    files = RunDir(path)
    return files.results.is_file() or files.plan.is_file()


def find_runs(root: Path, depth: int = MAX_DEPTH) -> Iterator[Path]:
    """The run directories below `root` (not `root` itself), in name order."""
    if depth <= 0:
        return
    try:
        children = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError:
        return
    for child in children:
        if is_run(child):
            yield child
        else:
            yield from find_runs(child, depth - 1)


@dataclass
class Entry:
    """One run of the list: its viewer, or why it has none."""

    name: str
    path: Path
    viewer: Viewer | None
    key: int
    problem: str = ""
    _row: tuple[int, list[Cell]] | None = None

    @property
    def prefix(self) -> str:
        """Its pages' URL prefix, relative to the run list."""
        return f"runs/{self.key}/"

    def row(self) -> list[Cell]:
        if self.viewer is None and self.problem == NOT_STARTED:
            from vabench.report.build import planned_episodes

            planned = planned_episodes(RunDir(self.path))
            done = f"0 / {planned:,}" if planned is not None else "0 / ?"
            return [self.name, "", done, "", "", NOT_STARTED]
        if self.viewer is None:
            return [
                self.name,
                "",
                "",
                "",
                "",
                Html(f"<span class='error'>{text(self.problem)}</span>"),
            ]
        self.viewer.index  # noqa: B018 (refreshes it: a sweep may still be writing)
        version = self.viewer.live.version
        if self._row is None or self._row[0] != version:
            self._row = (version, self._numbers())
        return self._row[1]

    def _numbers(self) -> list[Cell]:
        from vabench.report.build import planned_episodes

        assert self.viewer is not None
        refs = list(self.viewer.live.index.episodes.values())
        models = sorted({ref.result.model for ref in refs})
        scored = [ref for ref in refs if ref.result.scored]
        wins = sum(ref.result.success for ref in scored)
        planned = planned_episodes(RunDir(self.path))
        starts = [ref.result.started_at for ref in refs if ref.result.started_at]
        date = time.strftime("%Y-%m-%d %H:%M", time.localtime(min(starts))) if starts else ""
        done = f"{len(refs):,} / {planned:,}" if planned is not None else f"{len(refs):,} / ?"
        rate = f"{percent(wins, len(scored))} of {len(scored):,}"
        return [link(self.prefix, self.name), ", ".join(models), done, rate, date, ""]


NOT_STARTED = "no episode finished yet"


class RunsViewer:
    """The viewer of a directory of runs (module docstring)."""

    def __init__(self, root: Path | str):
        self.root = Path(root)
        self.run_dir = self.root  # what `__main__` prints
        paths = list(find_runs(self.root))
        if not paths:
            raise RunDirError(
                f"{RunDir(self.root).results}: not found, and no run directory (one holding "
                f"{RESULTS} or {PLAN}) within {MAX_DEPTH} levels below {self.root}"
            )
        self.entries: list[Entry] = []
        for key, path in enumerate(paths):
            name = path.relative_to(self.root).as_posix()
            if not RunDir(path).results.exists():  # planned, nothing finished yet: not an error
                self.entries.append(Entry(name, path, None, key, NOT_STARTED))
                continue
            try:
                self.entries.append(Entry(name, path, Viewer(path), key))
            except RunDirError as err:
                self.entries.append(Entry(name, path, None, key, str(err)))
        self.trials = {e.key: Trials(e.viewer.live) for e in self.entries if e.viewer}

    def sources(self) -> list[Source]:
        return [Source(e.name, e.prefix, self.trials[e.key]) for e in self.entries if e.viewer]

    def app(self) -> web.Application:
        app = web.Application(middlewares=[_headers])
        app.router.add_get("/", self.list_page)
        app.router.add_get("/compare", self.compare_page)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        for entry in self.entries:
            if entry.viewer is not None:
                app.add_subapp(f"/{entry.prefix}", entry.viewer.app())
        return app

    async def list_page(self, request: web.Request) -> web.Response:
        rows = [entry.row() for entry in self.entries]
        header = ("run", "models", "episodes done / planned", "success", "started", "problem")
        html = document(
            f"runs in {self.root.name}",
            [
                Html(f"<header><h1>Runs in {text(str(self.root))}</h1>"),
                Html(f"<nav>{link('compare', 'compare models on one trial')}</nav></header>"),
                table(header, rows, "runs"),
                Html(
                    f"<p class='muted'>Runs found once, at start, down to {MAX_DEPTH} levels "
                    "below this directory; success over the scored episodes.</p>"
                ),
            ],
        )
        return web.Response(text=html, content_type="text/html")

    async def compare_page(self, request: web.Request) -> web.Response:
        status, html = page(self.sources(), request.query, "./")
        return web.Response(text=html, content_type="text/html", status=status)


@web.middleware
async def _headers(request: web.Request, handler: Handler) -> web.StreamResponse:
    response = await handler(request)
    for key, value in SECURITY_HEADERS.items():
        response.headers.setdefault(key, value)
    return response
