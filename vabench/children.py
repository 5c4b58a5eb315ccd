"""Child processes never see the terminal's Ctrl-C; their parent ends them.

A terminal sends SIGINT to its whole foreground process group: every render worker, cell
worker and policy worker along with the command. One interrupted mid-call prints a traceback
and leaves its parent waiting for an answer, so vabench starts its children with SIGINT blocked
(`children_ignore_sigint`: the mask is inherited through fork and exec, so there is no window
before the child's first line) and each child ignores it from its first line
(`ignore_sigint`). The command decides what Ctrl-C means (`vabench.sweep.interrupt`) and stops
its children itself.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator


@contextlib.contextmanager
def children_ignore_sigint() -> Iterator[None]:
    """Processes started from this thread within the block begin with SIGINT blocked. Works
    from any thread (the signal mask is per thread); a press meanwhile reaches this process
    once the block ends."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def ignore_sigint() -> None:
    """In a child's main thread, first: ignore SIGINT from now on (a press that arrived while
    it was blocked is discarded, not delivered)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


PARENT_CHECK_S = 0.2
"""How often a child checks that its parent is alive."""


def exit_with_parent(parent_pid: int) -> None:
    """Start a thread that ends this process as soon as its parent is gone (reparented: another
    parent pid), so a SIGKILL of the parent leaves no child behind still working."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        os._exit(70)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
