"""One episode's records as the viewer's timeline: a card per step.

A step card holds what the model saw and did (the observation's images, its replies, rejected
replies, tool calls, the decision, the executed action's validity, planner result and
clipping, the robot state after it) and, kept apart under `evaluator`, what only the evaluator
knows (object poses, the predicate's checks, checkpoint progress, success). The page shows the
`evaluator` part in a marked panel; nothing here is ever sent to a model (the judge builds its
own prompt from model-visible fields: vabench.diagnostics.judge).
"""

from __future__ import annotations

from typing import Any

from vabench.diagnostics.episodes import RunIndex, task_instruction
from vabench.diagnostics.hints import hints

EVALUATOR_FIELDS = ("checks", "objects", "progress", "success")
"""Fields of an action event that belong to the evaluator-only panel."""


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
    return {
        "id": ref.id,
        "summary": ref.summary(),
        "instruction": task_instruction(r.task),
        "arms": start.get("arms"),
        "tools": start.get("tools"),
        "reset": reset,
        "end": end,
        "steps": [cards[s] for s in sorted(cards)],
        "hints": [h.record() for h in hints(events, ref.result.protocol)],
    }
