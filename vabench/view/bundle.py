"""`python -m vabench.view RUN_DIR --bundle DIR`: a run as a static site that opens from disk.

Written, read-only (no annotation panel, no script: a browser opens file:// pages without a
server, and a page from disk cannot fetch the viewer's JSON):

    DIR/index.html, index_2.html, ...   the episodes, `PAGE_SIZE` a page, in the run page's order
    DIR/e/<n>.html                      episode n's timeline: its images, replies, decisions,
                                        actions, the evaluator-only panel, the hints
    DIR/e/<n>/<image>                   the images the model saw (hard links where the file
                                        system allows, else copies)
    DIR/app.css

Every link and image source is relative, so DIR can be zipped, moved and opened anywhere.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from vabench.diagnostics.episodes import RunIndex
from vabench.run_layout import EpisodeDir
from vabench.view.app import STATIC
from vabench.view.listing import PAGE_SIZE, outcome_of
from vabench.view.pages import Cell, Html, document, image, link, table, text
from vabench.view.timeline import build_timeline


class BundleError(ValueError):
    """A bundle that cannot be written; the message names `--bundle`."""


def _index_name(page: int) -> str:
    return "index.html" if page == 0 else f"index_{page + 1}.html"


def _place(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def write_bundle(run_dir: Path | str, out: Path | str) -> int:
    """Write the bundle of `run_dir` into `out` (absent or empty); the episodes written."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BundleError(f"--bundle: {out} exists and is not an empty directory")
    index = RunIndex.load(run_dir)  # raises RunDirError with a clear message
    refs = list(index.episodes.values())
    (out / "e").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(STATIC / "app.css", out / "app.css")
    pages = max(1, -(-len(refs) // PAGE_SIZE))
    for page in range(pages):
        rows: list[list[Cell]] = []
        for n in range(page * PAGE_SIZE, min(len(refs), (page + 1) * PAGE_SIZE)):
            ref, r = refs[n], refs[n].result
            rows.append(
                [
                    link(f"e/{n}.html", ref.id),
                    r.model,
                    ref.track,
                    r.task,
                    r.seed,
                    r.run,
                    outcome_of(ref),
                    r.stop_reason,
                    f"{r.steps_used}/{r.step_budget}",
                    f"{r.progress}/{r.n_checkpoints}",
                ]
            )
            _episode(index, ref.id, n, _index_name(page), out / "e")
        nav = [link(_index_name(page - 1), "previous") if page else ""]
        nav += [link(_index_name(page + 1), "next") if page + 1 < pages else ""]
        header = ("episode", "model", "track", "task", "seed", "run", "outcome", "stop")
        parts: list[Cell] = [
            Html(f"<header><h1>run {text(index.run_dir.name)}</h1>"),
            Html(f"<p class='muted'>{len(refs):,} episodes; page {page + 1} of {pages}</p>"),
            Html(f"<nav>{text(nav[0])} {text(nav[1])}</nav></header>"),
            table([*header, "steps", "checkpoints"], rows, "episodes"),
        ]
        (out / _index_name(page)).write_text(
            document(f"run {index.run_dir.name}", parts, "app.css"), encoding="utf-8"
        )
    return len(refs)


def _episode(index: RunIndex, episode: str, n: int, back: str, out: Path) -> None:
    timeline = build_timeline(index, episode)
    frames = EpisodeDir(index.directory(episode)).frames.resolve()
    images = out / str(n)
    placed: set[str] = set()

    def picture(file: str) -> Cell:
        source = (frames.parent / file).resolve()
        if not source.is_relative_to(frames) or not source.is_file():
            return Html(f"<span class='muted'>{text(file)}: missing</span>")
        if source.name not in placed:
            images.mkdir(exist_ok=True)
            _place(source, images / source.name)
            placed.add(source.name)
        return image(f"{n}/{source.name}", file)

    s = timeline["summary"]
    parts: list[Cell] = [
        Html(f"<header><nav>{link('../' + back, 'run')}</nav><h1>{text(episode)}</h1>"),
        Html(f"<p>{text(timeline['instruction'])}</p></header>"),
        table(
            ["outcome", "stop", "steps", "checkpoints", "protocol"],
            [
                [
                    s["status"],
                    s["stop_reason"],
                    f"{s['steps_used']}/{s['step_budget']}",
                    f"{s['progress']}/{s['n_checkpoints']}",
                    s["protocol"],
                ]
            ],
        ),
    ]
    if timeline["hints"]:
        items = "".join(
            f"<li>{text(h['item'])}, step {text(h['step'])}: {text(h['text'])}"
            f"{' (evaluator-only)' if h['source'] == 'evaluator' else ''}</li>"
            for h in timeline["hints"]
        )
        parts.append(Html(f"<h2>Evidence hints</h2><ul>{items}</ul>"))
    for step in timeline["steps"]:
        parts.append(_step(step, picture))
    if timeline["end"]:
        parts.append(Html(f"<h2>End</h2><pre>{text(_kv(timeline['end']))}</pre>"))
    (out / f"{n}.html").write_text(document(episode, parts, "../app.css"), encoding="utf-8")


def _kv(values: dict[str, Any] | None) -> str:
    return "\n".join(f"{k}: {v}" for k, v in (values or {}).items() if v is not None)


def _step(step: dict[str, Any], picture: Any) -> Html:
    out = [f"<section class='step'><h3>step {text(step['step'])} ({text(step['view'])})</h3>"]
    out.append("<div class='frames'>" + "".join(picture(f) for f in step["frames"]) + "</div>")
    for reply in step["replies"]:
        out.append(f"<pre>{text(reply['text'])}</pre>")
    for rejection in step["rejections"]:
        out.append(f"<p class='rejected'>rejected: {text(_kv(rejection))}</p>")
    for tool in step["tools"]:
        out.append(f"<p>tool {text(tool['label'])}: {text(tool['result'])}</p>")
    for part in ("decision", "camera", "action", "robot"):
        if step[part]:
            out.append(f"<h4>{part}</h4><pre>{text(_kv(step[part]))}</pre>")
    if step["evaluator"]:
        out.append(
            "<details class='evaluator'><summary>EVALUATOR-ONLY</summary>"
            f"<pre>{text(_kv(step['evaluator']))}</pre></details>"
        )
    return Html("".join(out) + "</section>")
