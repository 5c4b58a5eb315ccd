"""Where a recorded sweep's decisions spent their time, per task and over the run's time.

    python benchmarks/episode_timeline.py RUN [--task NAME[,NAME]] [--window S] [--t0 EPOCH]
        [--json FILE]
    python benchmarks/episode_timeline.py /tmp/run --task put_everything_in_basket --window 60

RUN is a sweep's run directory (`python -m vabench.sweep ... --out RUN`). Every episode's own
event log, RUN/episodes/<model>/<track>/<task>/seed_<s>/run_<r>/events.jsonl, is read line by
line (the attempts set aside in its partial_<n>/ and attempt_<n>/ folders are not: they would
count a step twice); --task reads only those tasks' logs.

A decision's step runs from its observation to the next observation (the engine's loop:
observation, request, reply, [tool/rejection, request, reply ...], decision, action or camera,
then the next step's render). Each interval between two consecutive events of the step goes to
the phase of the event that ends it, so the four phases add up to the step exactly:

    physics  decision -> action: the action queued, stepped on the GPU, read back
    images   action (or camera) -> next observation: render + JPEG
    model    request -> reply, each model call of the step; also the interval before a
             `compaction` event, which is the conversation's summary call
    other    observation -> request, reply -> decision, reply -> tool -> request, decision ->
             camera: the engine's CPU work (prompt building, parsing, tools)

A decision after which the episode ended (its last; no next observation, so no step time) and a
step that stops short (an episode cut off mid-step, a model failure) are not in the means; they
are counted per task as `final` and `cut`. Lines that are not JSON are skipped and counted.

Printed: (a) per task over the whole run, the decisions timed, the mean step seconds and each
phase's mean seconds and share of the step; (b) for the selected tasks (all by default), per
window of --window seconds since --t0 (default: the run's earliest event), the decisions whose
step ended in the window, with the same means: whether, e.g., a long task's decisions got faster
once the other tasks had finished. --json FILE writes both.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from vabench.run_layout import EPISODES, EVENTS, RUN_PREFIX, SEED_PREFIX

PHASES = ("physics", "images", "model", "other")
PHYSICS, IMAGES, MODEL, OTHER = range(4)
ENDED_BY = {"action": PHYSICS, "observation": IMAGES, "reply": MODEL, "compaction": MODEL}
"""The phase of the interval that an event of this type ends; any other type ends `other`."""

# `EpisodeRecorder.event` writes json.dumps({"v", "seq", "t", "type", ...}): the two fields
# needed are at the start of the line, read without parsing the rest (an action line is ~2 KB).
# A line of another shape is parsed whole.
HEAD = re.compile(r'\{"v": \d+, "seq": \d+, "t": ([0-9.eE+-]+), "type": "(\w+)"')


@dataclass
class Means:
    """Sums of timed decisions: their step seconds and each phase's seconds."""

    decisions: int = 0
    step: float = 0.0
    phases: list[float] = field(default_factory=lambda: [0.0] * len(PHASES))

    def add(self, step: float, phases: list[float]) -> None:
        self.decisions += 1
        self.step += step
        for i, s in enumerate(phases):
            self.phases[i] += s

    def row(self) -> dict[str, Any]:
        n = self.decisions
        mean = (lambda s: round(s / n, 4)) if n else (lambda s: None)
        return {
            "decisions": n,
            "step_s": mean(self.step),
            **{f"{p}_s": mean(s) for p, s in zip(PHASES, self.phases, strict=True)},
        }


@dataclass
class TaskStats:
    episodes: int = 0
    means: Means = field(default_factory=Means)
    final: int = 0  # decisions after which the episode ended: no next observation
    cut: int = 0  # steps that stopped short: no decision, or cut off before the next step

    def row(self) -> dict[str, Any]:
        return {"episodes": self.episodes, **self.means.row(), "final": self.final, "cut": self.cut}


@dataclass
class Timeline:
    t0: float
    window_s: float
    tasks: dict[str, TaskStats] = field(default_factory=dict)
    windows: dict[int, Means] = field(default_factory=dict)
    bad_lines: int = 0

    def window(self, t_end: float) -> Means:
        k = math.floor((t_end - self.t0) / self.window_s)
        means = self.windows.get(k)
        if means is None:
            means = self.windows[k] = Means()
        return means


def episode_logs(run: Path) -> Iterator[tuple[str, Path]]:
    """(task, events.jsonl) of every episode under RUN/episodes, sorted. An episode directory
    is run_<r> inside seed_<s> inside its task (a model name may hold slashes, so the depth
    varies); nothing below it is entered (frames/, set-aside attempts)."""

    def walk(directory: Path) -> Iterator[tuple[str, Path]]:
        with os.scandir(directory) as it:
            entries = sorted((e.name, e.path) for e in it if e.is_dir(follow_symlinks=False))
        for name, path in entries:
            if name.startswith(RUN_PREFIX) and directory.name.startswith(SEED_PREFIX):
                events = Path(path) / EVENTS
                if events.is_file():
                    yield directory.parent.name, events
            else:
                yield from walk(Path(path))

    root = run / EPISODES
    if not root.is_dir():
        raise SystemExit(f"{run}: no {EPISODES}/ folder (not a sweep's run directory?)")
    yield from walk(root)


def events(path: Path, stats: Timeline | None = None) -> Iterator[tuple[float, str]]:
    """(t, type) of each event of a log, in file order; a line that is not JSON is skipped
    (and counted in `stats`)."""
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = HEAD.match(line)
            if m is not None and line.endswith(("}\n", "}")):
                yield float(m[1]), m[2]
                continue
            try:
                record = json.loads(line)
                yield float(record["t"]), str(record["type"])
            except (ValueError, KeyError, TypeError):
                if line.strip() and stats is not None:
                    stats.bad_lines += 1


def first_event_time(path: Path) -> float | None:
    for t, _ in events(path):
        return t
    return None


def read_episode(path: Path, task: TaskStats, timeline: Timeline) -> None:
    """Split each step of one episode into its phases and add the timed ones."""
    task.episodes += 1
    start: float | None = None  # the observation that opened the step being read
    prev = 0.0
    phases = [0.0] * len(PHASES)
    decided = False
    for t, kind in events(path, timeline):
        if kind == "observation":
            if start is not None:
                if decided:
                    phases[IMAGES] += t - prev
                    task.means.add(t - start, phases)
                    timeline.window(t).add(t - start, phases)
                else:
                    task.cut += 1
            start, prev, phases, decided = t, t, [0.0] * len(PHASES), False
        elif start is None:
            continue  # before the first observation: episode_start, reset
        elif kind == "end":
            if decided:  # its last decision (a stop, or the budget spent)
                task.final += 1
            else:
                task.cut += 1
            start = None
        else:
            phases[ENDED_BY.get(kind, OTHER)] += t - prev
            prev = t
            decided = decided or kind == "decision"
    if start is not None:  # the log stops mid-step
        task.cut += 1


def measure(
    run: Path, tasks: set[str] | None = None, window_s: float = 20.0, t0: float | None = None
) -> Timeline:
    """Read the run's episodes (those of `tasks` only, if given). t0 defaults to the earliest
    event of the whole run: the earliest first line of any episode's log."""
    logs = list(episode_logs(run))
    found = {task for task, _ in logs}
    if tasks is not None and not tasks <= found:
        unknown = ", ".join(sorted(tasks - found))
        raise SystemExit(
            f"no episodes of task {unknown} in {run}; tasks: {', '.join(sorted(found))}"
        )
    if t0 is None:
        firsts = [t for _, path in logs if (t := first_event_time(path)) is not None]
        if not firsts:
            raise SystemExit(f"{run}: no events in {len(logs)} episode logs")
        t0 = min(firsts)
    timeline = Timeline(t0=t0, window_s=window_s)
    for task, path in logs:
        if tasks is None or task in tasks:
            stats = timeline.tasks.setdefault(task, TaskStats())
            read_episode(path, stats, timeline)
    return timeline


def summary(timeline: Timeline) -> dict[str, Any]:
    everything = TaskStats()
    for stats in timeline.tasks.values():
        everything.episodes += stats.episodes
        everything.final += stats.final
        everything.cut += stats.cut
        everything.means.decisions += stats.means.decisions
        everything.means.step += stats.means.step
        for i, s in enumerate(stats.means.phases):
            everything.means.phases[i] += s
    keys = sorted(timeline.windows)
    windows = []
    for k in range(keys[0], keys[-1] + 1) if keys else ():
        means = timeline.windows.get(k, Means())
        windows.append({"start_s": round(k * timeline.window_s, 3), **means.row()})
    return {
        "t0": timeline.t0,
        "window_s": timeline.window_s,
        "tasks": {task: timeline.tasks[task].row() for task in sorted(timeline.tasks)},
        "all": everything.row(),
        "windows": windows,
        "bad_lines": timeline.bad_lines,
    }


def _seconds(row: dict[str, Any]) -> list[str]:
    step = row["step_s"]
    if step is None:
        return ["-"] * (1 + len(PHASES))
    cells = [f"{step:.3f}"]
    for p in PHASES:
        share = row[f"{p}_s"] / step if step > 0 else 0.0
        cells.append(f"{row[f'{p}_s']:.3f} {share:4.0%}")
    return cells


def _table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = []
    for r in [header, *rows]:
        first = r[0].ljust(widths[0])
        lines.append(
            "  ".join([first, *(c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=True))])
        )
    return "\n".join(lines)


def render(out: dict[str, Any], selected: str) -> str:
    phases = [f"{p} s" for p in PHASES]
    header = ["task", "episodes", "decisions", "step s", *phases, "final", "cut"]
    rows = [
        [
            name,
            str(r["episodes"]),
            str(r["decisions"]),
            *_seconds(r),
            str(r["final"]),
            str(r["cut"]),
        ]
        for name, r in [*out["tasks"].items(), ("all", out["all"])]
    ]
    parts = [
        "Per task, whole run: mean seconds per timed decision (share of the step). final: the "
        "episode's last decision (no next step); cut: a step cut short. Neither is in the means.",
        _table(header, rows),
        "",
        f"Every {out['window_s']:g} s since t0 = {out['t0']:.3f} ({selected}): the decisions "
        "whose step ended in the window.",
        _table(
            ["from s", "decisions", "step s", *phases],
            [[f"{w['start_s']:g}", str(w["decisions"]), *_seconds(w)] for w in out["windows"]],
        ),
    ]
    if out["bad_lines"]:
        parts.append(f"{out['bad_lines']} lines that are not JSON skipped")
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("run", type=Path, help="the sweep's run directory")
    p.add_argument("--task", help="read only these tasks (comma-separated)")
    p.add_argument("--window", type=float, default=20.0, help="seconds per window (default 20)")
    p.add_argument("--t0", type=float, help="epoch seconds of window 0 (default: first event)")
    p.add_argument("--json", type=Path, help="write the table and the windows here")
    args = p.parse_args(argv)
    if args.window <= 0:
        p.error(f"--window must be positive, not {args.window}")
    tasks = {t for t in args.task.split(",") if t} if args.task else None
    timeline = measure(args.run, tasks, args.window, args.t0)
    out = summary(timeline)
    print(render(out, "tasks " + ", ".join(sorted(tasks)) if tasks else "all tasks"))
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
