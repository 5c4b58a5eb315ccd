"""Where a sweep stands, on a clock: a live table on a terminal, plain lines otherwise.

The driver hands `Display.update` one `Status` a second: the ledger's counts per model and track
as it grows (`Tally`), with the engines' reports (spend, episodes running and in flight, their
limit and why: `with_reports`). While rich's table is up, log lines print above it
(`_route_logs`); plain lines (`--plain`, logs, CI) come every `every_s` seconds and at the end.
"""

from __future__ import annotations

import collections
import json
import logging
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, TextIO

from vabench.llm_pool.spend import Pricing, cost_text
from vabench.run_layout import INFRASTRUCTURE, RESULTS
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Key, key_of

PLAIN_EVERY_S = 15.0
RATE_WINDOW_S = 60.0
ETA_MIN_EPISODES = 30
ETA_SHOWN_AFTER = 5
"""Episodes this invocation finishes before an ETA shows (fewer where a quarter of what is
left is fewer): the first ones come in bursts, and the ETAs they give overshoot many times."""


def plural(n: int, word: str, many: str | None = None) -> str:
    """ "1 success", "2 successes"."""
    return f"{n} {word if n == 1 else (many or word + 's')}"


@dataclass
class Counts:
    """Episodes of one cell, track or sweep: planned, recorded (done), successes, recorded but
    not scored, re-run after an infrastructure error, and running now."""

    planned: int = 0
    done: int = 0
    success: int = 0
    unscored: int = 0
    retried: int = 0
    running: int = 0

    def add(self, other: Counts) -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    @classmethod
    def total(cls, parts: Iterable[Counts]) -> Counts:
        out = cls()
        for part in parts:
            out.add(part)
        return out


@dataclass
class Status:
    """Where the sweep stands: `Counts` per (model, track), this invocation's spend, and the
    engines' calls and episodes in flight, the episodes' limit and why."""

    tracks: dict[tuple[str, str], Counts] = field(default_factory=dict)
    calls: int = 0
    tokens: int = 0
    cost: float = 0.0
    calls_in_flight: int = 0
    in_flight: int | None = None
    limit: int | None = None
    reason: str | None = None

    def total(self) -> Counts:
        return Counts.total(self.tracks.values())


def with_reports(status: Status, reports: list[dict], live: list[dict], unit: str) -> Status:
    """`status` (the ledger's counts) with the engines' reports (`ChunkEngine.status`): their
    spend, never below the ledger's (an engine closed at the end reports none), and the `live`
    ones' running episodes, in-flight counts, limits and reason (`unit` names them: "engines")."""
    for r in live:
        for name, n in r.get("running", {}).items():
            model, track = name.split("/")
            if (model, track) in status.tracks:
                status.tracks[(model, track)].running += n
    status.calls = max(status.calls, sum(r["calls"] for r in reports))
    status.tokens = max(status.tokens, sum(r["tokens"] for r in reports))
    status.cost = max(status.cost, sum(r["cost"] for r in reports))
    status.calls_in_flight = sum(r["calls_in_flight"] for r in live)
    if live:
        status.in_flight = sum(r["in_flight"] for r in live)
        status.limit = sum(r["limit"] for r in live)
        status.reason = (
            live[0]["reason"] if len(live) == 1 else f"{len(live)} {unit}, e.g. {live[0]['reason']}"
        )
    return status


class Tally:
    """A run directory's ledger and infrastructure log, counted as they grow (whoever writes)."""

    def __init__(self, run_dir: Path, keys: Iterable[EpisodeKey]):
        self.run_dir = Path(run_dir)
        self.planned = {(k.model, k.track, k.task, int(k.seed), int(k.run)) for k in keys}
        self.tracks: dict[tuple[str, str], Counts] = collections.defaultdict(Counts)
        for key in self.planned:
            self.tracks[key[:2]].planned += 1
        self.calls = self.tokens = 0
        self.cost = 0.0
        self._seen: set[Key] = set()
        self._offsets = {RESULTS: 0, INFRASTRUCTURE: 0}
        self.refresh()
        self.calls = self.tokens = 0  # this invocation's spend only, as the local display
        self.cost = 0.0

    def _new_lines(self, name: str) -> list[str]:
        try:
            with open(self.run_dir / name, "rb") as f:
                f.seek(self._offsets[name])
                data = f.read()
        except FileNotFoundError:
            return []
        whole = data[: data.rfind(b"\n") + 1]  # a line being appended is read next time
        self._offsets[name] += len(whole)
        return [line for line in whole.decode("utf-8").splitlines() if line.strip()]

    def refresh(self) -> None:
        for line in self._new_lines(RESULTS):
            record = json.loads(line)
            key = key_of(record)
            if key in self._seen or key not in self.planned:
                continue
            self._seen.add(key)
            c = self.tracks[key[:2]]
            c.done += 1
            c.success += bool(record.get("success"))
            c.unscored += record.get("status") not in ("success", "failure")
            tokens = record.get("tokens") or {}
            self.calls += int(record.get("model_calls") or 0)
            self.tokens += int(tokens.get("input", 0)) + int(tokens.get("output", 0))
            self.cost += float(record.get("cost_usd") or 0.0)
        for line in self._new_lines(INFRASTRUCTURE):
            key = key_of(json.loads(line))
            if key in self.planned:
                self.tracks[key[:2]].retried += 1

    def status(self) -> Status:
        return Status(
            {k: Counts(**vars(c)) for k, c in self.tracks.items()},
            calls=self.calls,
            tokens=self.tokens,
            cost=self.cost,
        )

    def ended(self, last: Status, own_limit: bool = False) -> Status:
        """The status once the engines have ended: the ledger's counts read now, with the spend of
        `last` (the last status shown: the engines' reports) where higher. `own_limit`: the one
        engine was this process's (`executor: local`): keep the episodes' limit and why."""
        self.refresh()
        status = self.status()
        status.calls = max(status.calls, last.calls)
        status.tokens = max(status.tokens, last.tokens)
        status.cost = max(status.cost, last.cost)
        if own_limit:
            status.limit, status.reason = last.limit, last.reason
        return status


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


class Display:
    """`update(status)` about once a second; `close(status)` at the end."""

    def __init__(
        self,
        title: str = "sweep",
        live: bool | None = None,
        every_s: float = PLAIN_EVERY_S,
        out: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
        pricing: Mapping[str, Pricing] | None = None,
        verbose: bool = False,
        elapsed_before_s: float = 0.0,
    ):
        """`pricing`: how each model's cost shows (`SweepConfig.pricing`; without it, dollars).
        `verbose`: say why the episodes' limit is what it is. `elapsed_before_s`: the time
        earlier invocations of this run directory ran (a resumed sweep's clock continues)."""
        self.title = title
        self.verbose = verbose
        self.elapsed_before_s = elapsed_before_s
        self._done_at_start: int | None = None
        self.pricing = dict(pricing or {})
        self.out = out or sys.stdout
        self.live_mode = self.out.isatty() if live is None else live
        self.every_s = every_s
        self.clock = clock
        self.t0 = clock()
        self._last_print: float | None = None
        self._last_line = ""
        self._history: collections.deque[tuple[float, int, int]] = collections.deque()
        self._done_at: collections.deque[tuple[float, int]] = collections.deque()
        """(time, episodes done) where the count rose: the ETA's last ETA_MIN_EPISODES."""
        self._live: Any = None
        self._rerouted: list[tuple[logging.StreamHandler, TextIO]] = []
        if self.live_mode:
            from rich.console import Console
            from rich.live import Live

            before = sys.stdout, sys.stderr
            # force_terminal: a caller that asks for the table gets its terminal behaviour
            # (the proxies below included) whatever `out` is; a terminal is one anyway
            console = Console(file=self.out, force_terminal=True)
            self._live = Live(console=console, auto_refresh=False)
            self._live.start()
            self._rerouted = _route_logs(before, (sys.stdout, sys.stderr))

    # -- rates -----------------------------------------------------------------------------
    def _rates(self, done: int, calls: int) -> tuple[float, float]:
        """(episodes per second, calls per second) over the last `RATE_WINDOW_S`; the episodes'
        window reaches back to the last `ETA_MIN_EPISODES` where it holds fewer (a small machine
        finishes a few a minute, in bursts). A call count gone backwards (a reporter's spend
        lost with its process) lowers the window's earlier counts by as much: never negative."""
        now = self.clock()
        if self._history and calls < self._history[-1][2]:
            drop = self._history[-1][2] - calls
            self._history = collections.deque((t, d, c - drop) for t, d, c in self._history)
        self._history.append((now, done, calls))
        while len(self._history) > 2 and now - self._history[1][0] >= RATE_WINDOW_S:
            self._history.popleft()
        if not self._done_at or done > self._done_at[-1][1]:
            self._done_at.append((now, done))
        while len(self._done_at) > 2 and done - self._done_at[1][1] >= ETA_MIN_EPISODES:
            self._done_at.popleft()
        t0, done0, calls0 = self._history[0]
        if done - done0 < ETA_MIN_EPISODES and self._done_at[0][0] < t0:
            t_eps, done_eps = self._done_at[0]
        else:
            t_eps, done_eps = t0, done0
        span, span_eps = now - t0, now - t_eps
        episodes_per_s = max(done - done_eps, 0) / span_eps if span_eps > 0 else 0.0
        return episodes_per_s, (calls - calls0) / span if span > 0 else 0.0

    def _eta(self, total: Counts, episodes_per_s: float) -> str:
        """The remaining episodes' time at the current pace, once `ETA_SHOWN_AFTER` are done."""
        left = total.planned - total.done
        if left <= 0:
            return "done"
        if self._done_at_start is None:
            self._done_at_start = total.done
        wanted = min(ETA_SHOWN_AFTER, max(1, (total.planned - self._done_at_start) // 4))
        finished = total.done - self._done_at_start
        if finished < wanted:
            return f"after {plural(wanted - finished, 'more episode')}"
        return _duration(left / episodes_per_s) if episodes_per_s > 0 else "-"

    def elapsed_s(self) -> float:
        """The sweep's clock: earlier invocations' time and this one's."""
        return self.elapsed_before_s + self.clock() - self.t0

    # -- output ----------------------------------------------------------------------------
    def line(self, status: Status) -> str:
        """The plain line (also the live table's heading)."""
        total = status.total()
        per_s, calls_per_s = self._rates(total.done, status.calls)
        pct = 100.0 * total.done / total.planned if total.planned else 100.0
        episodes = (
            f"episodes {total.done}/{total.planned} ({pct:.0f}%): "
            f"{plural(total.success, 'success', 'successes')}, {total.unscored} unscored, "
            f"{total.retried} retried, {total.running} running"
        )
        if status.limit is not None:
            # "in flight" is the model calls awaiting a reply, nothing else; the episodes'
            # limit and why it moves (the adaptive gate's words) are for --verbose
            why = f": {status.reason}" if status.reason and self.verbose else ""
            above = total.running - status.limit  # the gate's slots: the same episodes
            if above > 0:
                # a limit lowered below the episodes already running ends none of them:
                # "3 running (at most 2 at once)" reads as a bug unless said
                episodes += (
                    f" (limit now {status.limit}{why}; the {above} above it finish before a "
                    "new one starts)"
                )
            else:
                episodes += f" (at most {status.limit} at once{why})"
        parts = [episodes]
        parts.append(
            f"calls {calls_per_s:.1f}/s, {status.calls_in_flight} in flight, "
            f"{status.tokens:,} tokens, {cost_text(status.cost, self.pricing)}"
        )
        parts.append(f"elapsed {_duration(self.elapsed_s())}, ETA {self._eta(total, per_s)}")
        if len(status.tracks) > 1:
            parts.append(
                ", ".join(
                    f"{'/'.join(k) if len({m for m, _ in status.tracks}) > 1 else k[1]} "
                    f"{c.done}/{c.planned}"
                    for k, c in sorted(status.tracks.items())
                )
            )
        return " | ".join(parts)

    def update(self, status: Status, force: bool = False) -> None:
        now = self.clock()
        if self.live_mode:
            self._live.update(self._table(status), refresh=True)
            return
        if force or self._last_print is None or now - self._last_print >= self.every_s:
            line = self.line(status)
            self._last_print, self._last_line = now, line
            stamp = time.strftime("%H:%M:%S")
            print(f"{stamp} {self.title}: {line}", file=self.out, flush=True)

    def _table(self, status: Status) -> Any:
        from rich.console import Group
        from rich.progress_bar import ProgressBar
        from rich.table import Table
        from rich.text import Text

        head = Text(f"{self.title}: {self.line(status).replace(' | ', chr(10))}")
        table = Table(box=None, pad_edge=False)
        for col in ("model", "track", "", "done", "success", "running", "unscored", "retried"):
            table.add_column(col, justify="left" if col in ("model", "track", "") else "right")
        for (model, track), c in sorted(status.tracks.items()):
            table.add_row(
                model,
                track,
                ProgressBar(total=max(c.planned, 1), completed=c.done, width=30),
                f"{c.done}/{c.planned}",
                str(c.success),
                str(c.running),
                str(c.unscored),
                str(c.retried),
            )
        return Group(head, table)

    def close(self, status: Status, show: bool = True) -> None:
        """The last line (unless just printed); `show=False`: none, the caller says how it ended."""
        if show and (self.live_mode or self.line(status) != self._last_line):
            self.update(status, force=True)
        if self._live is not None:
            self._live.stop()
            self._live = None
            for handler, stream in self._rerouted:
                handler.setStream(stream)
            self._rerouted = []


def _route_logs(
    old: tuple[TextIO, TextIO], new: tuple[TextIO, TextIO]
) -> list[tuple[logging.StreamHandler, TextIO]]:
    """Point the root logger's handlers that write to the `old` stdout/stderr at the `new`
    ones (rich's proxies); returns (handler, its old stream) to restore."""
    moved = []
    for handler in logging.getLogger().handlers:
        if not isinstance(handler, logging.StreamHandler):
            continue
        for before, after in zip(old, new, strict=True):
            if handler.stream is before and after is not before:
                moved.append((handler, before))
                handler.setStream(after)
    return moved
