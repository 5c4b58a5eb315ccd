"""One episode's records as the viewer's timeline: a card per step.

A step card holds what the model saw and did (the observation's images, its replies, rejected
replies, tool calls, the decision, the executed action's validity, planner result and
clipping, the robot state after it) and, kept apart under `evaluator`, what only the evaluator
knows (object poses, the predicate's checks, checkpoint progress, success). The page shows the
`evaluator` part in a marked panel; nothing here is ever sent to a model (the judge builds its
own prompt from model-visible fields: vabench.diagnostics.judge).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from vabench.diagnostics.episodes import RunIndex, task_instruction
from vabench.diagnostics.hints import hints
from vabench.run_layout import EpisodeDir, RunDir

EVALUATOR_FIELDS = ("checks", "objects", "progress", "success")
"""Fields of an action event that belong to the evaluator-only panel."""


FRAMES_POLICIES = ("all", "failed", "none")


def frames_kept(run_dir: Path) -> str:
    """The run's `records.frames` (which episodes keep the images the model saw), from its
    resolved config; `all` where the config does not say (the default)."""
    try:
        doc = yaml.safe_load(RunDir(run_dir).config.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return "all"
    records = doc.get("records") if isinstance(doc, dict) else None
    value = records.get("frames") if isinstance(records, dict) else None
    return value if value in FRAMES_POLICIES else "all"


def frames_note(policy: str, success: bool | None, any_frames: bool) -> str | None:
    """Why an episode's images are not shown, or None where they are (or should be)."""
    if any_frames:
        return None
    if policy == "none":
        return "images not kept: the run kept no frames (records.frames: none)"
    if policy == "failed" and success:
        return (
            "images not kept: the run kept the frames of failed episodes only "
            "(records.frames: failed)"
        )
    return None


def _card(step: int) -> dict[str, Any]:
    return {
        "step": step,
        "view": None,
        "frames": [],
        "replies": [],
        "rejections": [],
        "tools": [],
        "decision": None,
        "camera": None,
        "action": None,
        "robot": None,
        "evaluator": None,
    }


def build_timeline(index: RunIndex, episode: str) -> dict[str, Any]:
    ref = index.get(episode)
    events = index.events(episode)
    cards: dict[int, dict[str, Any]] = {}
    start: dict[str, Any] = {}
    reset: dict[str, Any] = {}
    end: dict[str, Any] = {}
    for e in events:
        kind = e.get("type")
        if kind == "episode_start":
            start = e
            continue
        if kind == "reset":
            reset = {k: e.get(k) for k in ("ok", "reason", "drift_deg", "objects")}
            continue
        if kind in ("end", "harness_error", "llm_failure"):
            end = {**end, **{k: v for k, v in e.items() if k not in ("v", "seq", "t", "type")}}
            continue
        step = e.get("step")
        if not isinstance(step, int):
            continue
        card = cards.setdefault(step, _card(step))
        if kind == "observation":
            card["view"] = e.get("view")
            card["frames"] = list(e.get("frames") or [])
        elif kind == "reply":
            card["replies"].append({"text": e.get("text", ""), "latency_s": e.get("latency_s")})
        elif kind == "rejection":
            card["rejections"].append({"field": e.get("field"), "message": e.get("message")})
        elif kind == "tool":
            card["tools"].append({k: e.get(k) for k in ("label", "ok", "result", "images")})
        elif kind == "decision":
            card["decision"] = {k: e.get(k) for k in ("kind", "label", "reason", "decision")}
        elif kind == "camera":
            card["camera"] = {k: e.get(k) for k in ("label", "view")}
        elif kind == "action":
            card["action"] = {
                k: e.get(k)
                for k in (
                    "label",
                    "valid",
                    "error",
                    "planner_success",
                    "executed",
                    "clipped",
                    "executed_mm",
                )
            }
            card["robot"] = e.get("proprio")
            card["evaluator"] = {k: e.get(k) for k in EVALUATOR_FIELDS}
        elif kind == "compaction":
            card.setdefault("notes", []).append("history compacted before this call")
    r = ref.result
    policy = start.get("frames") or frames_kept(index.run_dir)
    frames = EpisodeDir(index.directory(episode)).frames
    any_frames = frames.is_dir() and any(frames.iterdir())
    return {
        "id": ref.id,
        "frames_kept": policy,
        "frames_note": frames_note(policy, r.success, any_frames),
        "summary": ref.summary(),
        "instruction": task_instruction(r.task),
        "arms": start.get("arms"),
        "tools": start.get("tools"),
        "reset": reset,
        "end": end,
        "steps": [cards[s] for s in sorted(cards)],
        "hints": [h.record() for h in hints(events, ref.result.protocol)],
    }
