"""Where a sweep stands: a live table on a terminal, plain log lines otherwise.

Per model and track: episodes done / planned, running, successes, unscored (errors and
infrastructure failures), episodes retried; overall: model calls in flight, calls per second,
tokens, cost and an ETA from the rate of finished episodes.
"""

from __future__ import annotations

import sys
import time
from collections import defaultdict
from typing import Any

from vabench.sweep.runner import CellCounts, SweepProgress


def _usage(progress: SweepProgress) -> tuple[int, int, int, float]:
    """(in flight, calls finished, tokens, cost) over every endpoint of the pool."""
    if progress.pool is None:
        return 0, 0, 0, 0.0
    stats = progress.pool.stats().values()
    return (
        sum(s.in_flight for s in stats),
        sum(s.succeeded for s in stats),
        sum(s.usage.total_tokens for s in stats),
        sum(s.cost_usd for s in stats),
    )


class Display:
    """Call `update(progress)` whenever something changes; it throttles itself."""

    def __init__(self, total_planned: int, interval_s: float = 1.0, live: bool | None = None):
        self.t0 = time.monotonic()
        self.total_planned = total_planned
        self.interval_s = interval_s
        self.live_mode = sys.stdout.isatty() if live is None else live
        self._last = 0.0
        self._done0: int | None = None
        self._calls0: tuple[float, int] | None = None
        self._live: Any = None
        if self.live_mode:
            from rich.live import Live

            self._live = Live(refresh_per_second=2, transient=False)
            self._live.start()
        else:
            self.interval_s = max(interval_s, 10.0)

    def _eta(self, total: CellCounts) -> str:
        if self._done0 is None:
            self._done0 = total.done
        new = total.done - self._done0
        elapsed = time.monotonic() - self.t0
        left = total.planned - total.done
        if new <= 0 or left <= 0:
            return "-" if left else "done"
        seconds = left * elapsed / new
        return time.strftime("%H:%M:%S", time.gmtime(seconds))

    def _rate(self, calls: int) -> float:
        now = time.monotonic()
        if self._calls0 is None:
            self._calls0 = (now, calls)
            return 0.0
        t0, c0 = self._calls0
        return (calls - c0) / max(now - t0, 1e-9)

    def update(self, progress: SweepProgress, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < self.interval_s:
            return
        self._last = now
        total = progress.total()
        in_flight, calls, tokens, cost = _usage(progress)
        head = (
            f"{total.done}/{total.planned} episodes, {total.running} running, "
            f"{total.success} successes, {total.unscored} unscored, {total.retried} retried"
            f" | calls in flight {in_flight}, {self._rate(calls):.1f}/s, "
            f"{tokens:,} tokens, ${cost:.2f} | ETA {self._eta(total)}"
        )
        if not self.live_mode:
            print(head, flush=True)
            return
        from rich.table import Table

        table = Table(title=head, title_justify="left")
        for col in ("model", "track", "done", "running", "success", "unscored", "retried"):
            table.add_column(col, justify="left" if col in ("model", "track") else "right")
        rows: dict[tuple[str, str], CellCounts] = defaultdict(CellCounts)
        for (model, track, _task), c in progress.cells.items():
            r = rows[(model, track)]
            for name in ("planned", "done", "success", "running", "unscored", "retried"):
                setattr(r, name, getattr(r, name) + getattr(c, name))
        for (model, track), r in sorted(rows.items()):
            table.add_row(
                model,
                track,
                f"{r.done}/{r.planned}",
                str(r.running),
                str(r.success),
                str(r.unscored),
                str(r.retried),
            )
        self._live.update(table)

    def close(self, progress: SweepProgress) -> None:
        self.update(progress, force=True)
        if self._live is not None:
            self._live.stop()
