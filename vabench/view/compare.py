"""Side by side: every model's episode of one trial (task, seed, track), within one run or
across the runs of a directory (`vabench.view.runs`).

A trial's episodes are found through a map from (task, seed, track) to episode ids, built once
per version of a run's index (`listing.LiveIndex.version`): a run of 200,000 episodes is
scanned once, not on every request. Each row shows the first and last image the model saw
(the first image of those observations: a passive bundle's top-down view), read from that
episode's events alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from vabench.diagnostics.episodes import EpisodeRef, RunIndex
from vabench.view.listing import LiveIndex, outcome_of
from vabench.view.pages import Cell, Html, document, image, link, query, table, text

Trial = tuple[str, int, str]
"""(task, seed, track)."""


@dataclass
class Trials:
    """The episodes of each trial of one run (see the module docstring)."""

    live: LiveIndex
    _version: int = -1
    _ids: dict[Trial, list[str]] = field(default_factory=dict)

    def of(self, trial: Trial) -> list[EpisodeRef]:
        index = self.live.index
        if self._version != self.live.version:
            ids: dict[Trial, list[str]] = {}
            for ref in index.episodes.values():
                ids.setdefault((ref.result.task, ref.result.seed, ref.track), []).append(ref.id)
            self._ids, self._version = ids, self.live.version
        return [index.episodes[i] for i in self._ids.get(trial, [])]


@dataclass(frozen=True)
class Source:
    """One run as the comparison sees it: its name, the relative URL prefix of its pages
    ("" for the run being served, `runs/<k>/` in a directory of runs) and its trials."""

    name: str
    prefix: str
    trials: Trials


def trial_of(params: Mapping[str, str]) -> Trial | str:
    """The trial a request names, or the one-line problem naming the parameter."""
    for name in ("task", "seed", "track"):
        if not params.get(name):
            return f"{name}: missing"
    try:
        seed = int(params["seed"])
    except ValueError:
        return f"seed: expected a whole number, got {params['seed']!r}"
    return params["task"], seed, params["track"]


def ends(index: RunIndex, episode: str) -> tuple[str | None, str | None]:
    """The first and last image file the model saw in `episode` (frames/...), if any."""
    shown = [
        e["frames"][0]
        for e in index.events(episode)
        if e.get("type") == "observation" and e.get("frames")
    ]
    return (shown[0], shown[-1]) if shown else (None, None)


def rows(sources: Sequence[Source], trial: Trial) -> list[list[Cell]]:
    out: list[list[Cell]] = []
    for source in sources:
        index = source.trials.live.index
        for ref in source.trials.of(trial):
            r = ref.result
            pictures: list[Cell] = []
            for file in ends(index, ref.id):
                src = query(f"{source.prefix}api/frame", episode=ref.id, file=file) if file else ""
                pictures.append(image(src, f"{ref.id} {file}") if file else None)
            out.append(
                [
                    source.name,
                    r.model,
                    r.run,
                    outcome_of(ref),
                    r.stop_reason,
                    f"{r.steps_used}/{r.step_budget}",
                    f"{r.progress}/{r.n_checkpoints}",
                    link(query(f"{source.prefix}episode", id=ref.id), ref.id),
                    *pictures,
                ]
            )
    return out


HEADER = ("run", "model", "repeat", "outcome", "stop", "steps", "checkpoints", "episode")


def page(sources: Sequence[Source], params: Mapping[str, str], home: str) -> tuple[int, str]:
    """(status, HTML) of the comparison page; without a trial, a form to choose one."""
    choices: dict[str, set[Any]] = {"task": set(), "track": set()}
    for source in sources:
        for ref in source.trials.live.index.episodes.values():
            choices["task"].add(ref.result.task)
            choices["track"].add(ref.track)
    form = _form(choices, params)
    nav = Html(f"<nav>{link(home, 'back')}</nav>")
    if not any(params.get(k) for k in ("task", "seed", "track")):
        return 200, document("compare", [nav, Html("<h1>Compare models on one trial</h1>"), form])
    trial = trial_of(params)
    if isinstance(trial, str):
        return 400, document("compare", [nav, Html(f"<p class='error'>{text(trial)}</p>"), form])
    task, seed, track = trial
    found = rows(sources, trial)
    title = f"{task}, seed {seed}, track {track}"
    body: list[Cell] = [nav, Html(f"<h1>{text(title)}</h1>"), form]
    if found:
        body.append(table([*HEADER, "first image", "last image"], found, "compare"))
    else:
        body.append(Html("<p>No finished episode of this trial.</p>"))
    return 200, document(f"compare: {title}", body)


def _form(choices: Mapping[str, set[Any]], params: Mapping[str, str]) -> Html:
    parts = ["<form method='get' action='compare' class='filters'>"]
    for name in ("task", "track"):
        options = "".join(
            f"<option{' selected' if v == params.get(name) else ''}>{text(v)}</option>"
            for v in sorted(choices[name])
        )
        parts.append(f"<label>{name} <select name='{name}'>{options}</select></label>")
    parts.append(
        f"<label>seed <input name='seed' size='8' value='{text(params.get('seed', ''))}'></label>"
        "<button>compare</button></form>"
    )
    return Html("".join(parts))
