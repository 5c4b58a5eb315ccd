"""The viewer's web application (aiohttp): the run read-only, plus the annotation endpoints.

Pages (plain HTML, CSS and JS from `static/`; every value is inserted as text, never as HTML):
    /                      the run: episodes with filters, success and checkpoint columns
    /episode?id=ID         the timeline of one episode and the annotation panel
    /diagnostics           the diagnostics, agreement and vote-rule tables of the annotations
    /compare?task=&seed=&track=   every model's episode of that trial (vabench.view.compare)
JSON:
    GET  /api/run?model=&track=&task=&outcome=&offset=&limit=
                                               one page of the episodes passing the filters,
                                               who annotated them, and the filters' values
    GET  /api/neighbours?id=ID&<filters>       the episodes before and after ID (n/p keys)
    GET  /api/episode?id=ID                    the timeline (vabench.view.timeline)
    GET  /api/frame?episode=ID&file=frames/..  one image the model saw
    GET  /api/rubric                           criteria, gates, rubric text
    GET  /api/annotations?episode=ID&annotator=NAME
    GET  /api/radar?model=&track=              the model's capability radar (PNG), from the
                                               annotations as they are now
    POST /api/judgment  {annotator, episode, item, value}

Safety: the server binds 127.0.0.1 unless told otherwise (`__main__`); episode ids are looked up
in the run's index and never used as paths; a frame must resolve inside its episode's frames/
folder (symlinks included); POSTs must be JSON from this origin (a page elsewhere cannot post
a form here, and a cross-origin JSON post is refused), and every response forbids framing and
inline scripts.
"""

from __future__ import annotations

import json
import time
from collections.abc import Awaitable, Callable
from html import escape
from pathlib import Path
from typing import Any

from aiohttp import web

from vabench.diagnostics.criteria import CRITERIA, GATES, MODULES, RUBRIC_VERSION
from vabench.diagnostics.episodes import RunIndex, UnknownEpisode
from vabench.diagnostics.store import (
    AnnotationError,
    AnnotationStore,
    Judgment,
    Key,
    activation,
    check_annotator,
    gate_votes,
    majority,
)
from vabench.run_layout import EpisodeDir, RunDir
from vabench.view.compare import Source, Trials
from vabench.view.compare import page as compare_page
from vabench.view.listing import Listing, LiveIndex, filters_of, paging_of
from vabench.view.timeline import build_timeline, frames_kept

STATIC = Path(__file__).parent / "static"
IMAGE_TYPES = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png"}
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self'; style-src 'self'; script-src 'self'; "
        "frame-ancestors 'none'; form-action 'self'"
    ),
}

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def _error(status: int, message: str, field: str = "") -> web.Response:
    return web.json_response({"error": message, "field": field}, status=status)


class Viewer:
    """Holds the run's index (kept current while the sweep writes: `listing.LiveIndex`), its
    episode listing and its annotation store."""

    def __init__(self, run_dir: Path | str):
        self.run_dir = Path(run_dir)
        self.live = LiveIndex(self.run_dir)  # raises RunDirError with a clear message
        self.listing = Listing(self.live)
        self.trials = Trials(self.live)
        self.store = AnnotationStore(self.live.index)
        self._reloads = self.live.reloads
        self._state: tuple[Any, dict[Key, Judgment]] = (None, {})
        # What the run page's first request needs, ready before the viewer says it serves.
        self.listing.matching({})
        self.judgments()

    @property
    def index(self) -> RunIndex:
        if self.live.refresh():  # the sweep is still writing: pick up new episodes
            if self.live.reloads != self._reloads:  # read from the start: a new store
                self.store = AnnotationStore(self.live.index)
                self._reloads = self.live.reloads
            else:  # grown: the store's judgments all name episodes it still holds
                self.store.index = self.live.index
        return self.live.index

    def judgments(self) -> dict[Key, Judgment]:
        """The judgments in force (`AnnotationStore.state`), computed again only when an
        annotation file changed: every request reads them, and at 100,000 judgments that
        takes a tenth of a second."""
        files = RunDir(self.run_dir).annotation_files()
        stamp = (self.store, [(f, f.stat().st_size, f.stat().st_mtime_ns) for f in files])
        if self._state[0] != stamp:
            self._state = (stamp, self.store.state())
        return self._state[1]

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._guard], client_max_size=64 * 1024)
        app.router.add_get("/", self._page("run.html"))
        app.router.add_get("/episode", self._page("episode.html"))
        app.router.add_get("/diagnostics", self.diagnostics_page)
        app.router.add_get("/compare", self.compare_page)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        app.router.add_get("/api/run", self.run)
        app.router.add_get("/api/neighbours", self.neighbours)
        app.router.add_get("/api/episode", self.episode)
        app.router.add_get("/api/frame", self.frame)
        app.router.add_get("/api/rubric", self.rubric)
        app.router.add_get("/api/annotations", self.annotations)
        app.router.add_get("/api/radar", self.radar)
        app.router.add_post("/api/judgment", self.judgment)
        return app

    @web.middleware
    async def _guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.method == "POST":
            if request.content_type != "application/json":
                return _error(415, "send the judgment as application/json", "content-type")
            origin = request.headers.get("Origin")
            if origin is not None and origin != f"{request.scheme}://{request.host}":
                return _error(403, f"cross-origin request from {origin} refused", "origin")
        try:
            response = await handler(request)
        except web.HTTPException as exc:
            for key, value in SECURITY_HEADERS.items():
                exc.headers.setdefault(key, value)
            raise
        for key, value in SECURITY_HEADERS.items():
            response.headers.setdefault(key, value)
        return response

    def _page(self, name: str) -> Handler:
        async def page(request: web.Request) -> web.StreamResponse:
            return web.FileResponse(STATIC / name)

        return page

    # -- run and episodes -------------------------------------------------------------------
    async def run(self, request: web.Request) -> web.Response:
        index = self.index
        try:
            offset, limit = paging_of(request.query)
        except ValueError as err:
            return _error(400, str(err), str(err).split(":")[0])
        page = self.listing.page(filters_of(request.query), offset, limit)
        shown = {ref.id for ref in page["episodes"]}
        annotated: dict[str, set[str]] = {}
        for episode, annotator, _ in self.judgments():
            if episode in shown:
                annotated.setdefault(episode, set()).add(annotator)
        page["episodes"] = [
            {**ref.summary(), "annotators": sorted(annotated.get(ref.id, ()))}
            for ref in page["episodes"]
        ]
        return web.json_response(
            {
                "run_dir": str(index.run_dir),
                "name": index.run_dir.name,
                "frames_kept": frames_kept(index.run_dir),
                **page,
            }
        )

    async def neighbours(self, request: web.Request) -> web.Response:
        episode = self._episode_id(request)
        return web.json_response(self.listing.neighbours(filters_of(request.query), episode))

    def _episode_id(self, request: web.Request, key: str = "id") -> str:
        episode = request.query.get(key, "")
        try:
            self.index.get(episode)
        except UnknownEpisode as err:
            raise web.HTTPNotFound(
                text=json.dumps({"error": str(err), "field": key}), content_type="application/json"
            ) from None
        return episode

    async def episode(self, request: web.Request) -> web.Response:
        return web.json_response(build_timeline(self.index, self._episode_id(request)))

    async def frame(self, request: web.Request) -> web.StreamResponse:
        episode = self._episode_id(request, "episode")
        frames = EpisodeDir(self.index.directory(episode)).frames.resolve()
        name = request.query.get("file", "")
        path = (frames.parent / name).resolve()
        if not path.is_relative_to(frames) or path.suffix.lower() not in IMAGE_TYPES:
            return _error(403, f"file {name!r} is not an image of this episode", "file")
        if not path.is_file():
            return _error(404, f"no image {name!r} in episode {episode!r}", "file")
        return web.FileResponse(path, headers={"Content-Type": IMAGE_TYPES[path.suffix.lower()]})

    async def compare_page(self, request: web.Request) -> web.Response:
        self.index  # noqa: B018 (refreshes it: the sweep may still be writing)
        source = Source(self.run_dir.name, "", self.trials)
        status, html = compare_page([source], request.query, "./")
        return web.Response(text=html, content_type="text/html", status=status)

    # -- annotation ---------------------------------------------------------------------------
    async def rubric(self, request: web.Request) -> web.Response:
        return web.json_response(
            {
                "version": RUBRIC_VERSION,
                "modules": MODULES,
                "gates": [
                    {
                        "code": g.code,
                        "name": g.name,
                        "question": g.question,
                        "rubric": g.rubric,
                        "activates": list(g.activates),
                    }
                    for g in GATES.values()
                ],
                "criteria": [
                    {
                        "code": c.code,
                        "module": c.module,
                        "name": c.name,
                        "summary": c.summary,
                        "rubric": c.rubric,
                        "gate": c.gate,
                    }
                    for c in CRITERIA.values()
                ],
            }
        )

    def _annotation_state(self, episode: str, annotator: str) -> dict[str, Any]:
        """What the annotator sees: their own judgments, each gate's vote count and majority
        (not the other annotators' values: judgments stay independent), and which criteria
        are activated for them. Computed from this episode's judgments alone: the vote
        helpers scan what they are given, once per gate and criterion."""
        state = {k: j for k, j in self.judgments().items() if k[0] == episode}
        own = {
            item: j.value for (e, a, item), j in state.items() if e == episode and a == annotator
        }
        gates = {}
        for gate in GATES:
            votes = gate_votes(state, episode, gate)
            gates[gate] = {"votes": len(votes), "majority": majority(votes.values())}
        active = {item: activation(state, episode, annotator, item) for item in CRITERIA}
        return {
            "episode": episode,
            "annotator": annotator,
            "own": own,
            "gates": gates,
            "not_activated": {k: v for k, v in active.items() if v},
        }

    async def annotations(self, request: web.Request) -> web.Response:
        episode = self._episode_id(request, "episode")
        try:
            annotator = check_annotator(request.query.get("annotator", ""))
        except AnnotationError as err:
            return _error(400, str(err), err.field)
        return web.json_response(self._annotation_state(episode, annotator))

    async def judgment(self, request: web.Request) -> web.Response:
        try:
            body = await request.json()
        except (json.JSONDecodeError, UnicodeDecodeError):
            return _error(400, "the body is not valid JSON", "body")
        if not isinstance(body, dict):
            return _error(400, "expected a JSON object", "body")
        unknown = sorted(set(body) - {"annotator", "episode", "item", "value", "note"})
        if unknown:
            return _error(400, f"unknown field {unknown[0]!r}", unknown[0])
        for key in ("annotator", "episode", "item", "value"):
            if key not in body:
                return _error(400, f"{key}: missing", key)
        note = body.get("note")
        if note is not None and (not isinstance(note, str) or len(note) > 2000):
            return _error(400, "note: expected text of at most 2000 characters", "note")
        try:
            self.store.record(
                body["annotator"], body["episode"], body["item"], body["value"], note=note
            )
        except AnnotationError as err:
            status = 404 if err.field == "episode" and "unknown" in str(err) else 400
            return _error(status, str(err), err.field)
        return web.json_response(self._annotation_state(body["episode"], body["annotator"]))

    # -- diagnostics ------------------------------------------------------------------------
    async def radar(self, request: web.Request) -> web.Response:
        from vabench.view.radar import radar_png

        model = request.query.get("model", "")
        png = radar_png(self.run_dir, self.index, model, request.query.get("track", ""))
        if png is None:
            return _error(404, f"no annotated episode of model {model!r} yet", "model")
        return web.Response(body=png, content_type="image/png")

    async def diagnostics_page(self, request: web.Request) -> web.Response:
        from vabench.diagnostics import sections as diagnostics

        data = diagnostics.load(self.run_dir, self.index)
        parts = [
            "<!DOCTYPE html><html><head><meta charset='utf-8'><title>diagnostics — "
            f"{escape(self.run_dir.name)}</title>",
            "<link rel='stylesheet' href='static/app.css'></head><body class='tables'>",
            "<nav><a href='./'>run</a></nav>",
            f"<h1>Diagnostics of {escape(self.run_dir.name)}</h1>",
            f"<p class='muted'>computed {escape(time.strftime('%Y-%m-%d %H:%M:%S'))}</p>",
        ]
        if data is None:
            parts.append("<p>No annotations yet: open an episode and annotate it.</p>")
        else:
            for section in diagnostics.sections(data):
                parts.append(f"<h2 id='{escape(section.name)}'>{escape(section.title)}</h2>")
                parts += [f"<li class='note'>{escape(n)}</li>" for n in section.notes]
                for table in section.tables:
                    head = "".join(f"<th>{escape(h)}</th>" for h in table.header)
                    rows = "".join(
                        "<tr>" + "".join(f"<td>{escape(c)}</td>" for c in row) + "</tr>"
                        for row in table.rows
                    )
                    parts.append(
                        f"<h3>{escape(table.title)}</h3><table><tr>{head}</tr>{rows}</table>"
                    )
        parts.append("</body></html>")
        return web.Response(text="\n".join(parts), content_type="text/html")
