"""Ctrl-C in the sweep: the first press stops it cleanly, the second at once (both exit 130).

The first press has the driver end its engines at its next tick (work already queued on the
simulator or renderer is waited for: `STOP_NOTICE`); what was recorded stays whole (one write per
ledger line, result.json renamed into place, a cut episode's partial events.jsonl set aside on
resume). The processes the sweep starts never see SIGINT (`vabench.children`): the sweep ends them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType

EXIT_INTERRUPTED = 130
"""128 + SIGINT, what a shell reports for a command ended by Ctrl-C."""
STOP_NOTICE_S = 3.0
"""A first press's stop still under way after this long prints `STOP_NOTICE`."""
STOP_NOTICE = (
    "stopping: episodes cancelled; waiting for the simulator and renderer to finish the work "
    "already queued (Ctrl-C again exits at once; every recorded episode is kept)"
)


class Interrupted(Exception):
    """Raised in the main thread at the first Ctrl-C where no executor took the press over."""


class CtrlC:
    """The sweep's SIGINT handler (main thread only)."""

    def __init__(self, notice_after_s: float = STOP_NOTICE_S) -> None:
        self.pressed = 0
        self.notice_after_s = notice_after_s
        self._on_first: Callable[[], object] | None = None
        self._previous: object = None
        self._notice: threading.Timer | None = None

    def install(self) -> None:
        self._previous = signal.signal(signal.SIGINT, self._handle)

    def restore(self) -> None:
        self.stopped()
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)  # type: ignore[arg-type]
            self._previous = None

    @contextlib.contextmanager
    def on_first(self, callback: Callable[[], object]) -> Iterator[None]:
        """Within the block, the first press calls `callback` (from the signal handler: it
        must only schedule the stop, e.g. `loop.call_soon_threadsafe(task.cancel)`) instead
        of raising `Interrupted`."""
        self._on_first = callback
        try:
            yield
        finally:
            self._on_first = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.pressed += 1
        if self.pressed > 1:
            os.write(2, b"\nstopped at once; run the same command to resume\n")
            os._exit(EXIT_INTERRUPTED)
        if self._on_first is not None:
            self._on_first()
            self._notice = threading.Timer(
                self.notice_after_s, os.write, (2, f"{STOP_NOTICE}\n".encode())
            )
            self._notice.daemon = True
            self._notice.start()
            return
        raise Interrupted()

    def stopped(self) -> None:
        """The first press's stop is done (before its last line): no notice after it."""
        if self._notice is not None:
            self._notice.cancel()
