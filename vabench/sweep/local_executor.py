"""`executor: local`: the sweep as one chunk (every pending episode in plan order, on the
command's `Choices` as they are) for one `chunk_engine.ChunkEngine` served in a thread of the
driver's process, its events straight into the driver's queue. Its pool keeps the limits and
spend caps itself; a dead engine is not replaced (another in this process would meet the same
fault); ended at once, its work is cancelled and the driver waits for it to unwind.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import threading
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from typing_extensions import Unpack

from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.sweep.cells import task_cost
from vabench.sweep.chunk_engine import LOST, BoardLink, ChunkEngine, Command, serve
from vabench.sweep.driver import Cells, Emit, Engines, Hooks, run_engines
from vabench.sweep.placement import Chunk
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import Key

log = logging.getLogger(__name__)


class InProcessEngine:
    """The driver's handle on the in-process engine (`placement.Engine`; see the module
    docstring)."""

    def __init__(self, emit: Emit, make: Callable[[], ChunkEngine]):
        self.emit = emit
        self.make = make
        self.loop: asyncio.AbstractEventLoop | None = None
        self.inbox: asyncio.Queue[Command | None] = asyncio.Queue()
        self.task: asyncio.Task[None] | None = None
        self.ready = threading.Event()
        """Set once its loop runs (or its thread has ended)."""
        self.thread = threading.Thread(target=self._main, name="engine", daemon=True)

    def start(self, tasks: Sequence[str]) -> None:
        """Start its thread (the kernels of `tasks` compile as its chunk starts)."""
        self.thread.start()

    def _main(self) -> None:
        # a press reaches the driver's thread; processes started here begin with it blocked
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            asyncio.run(self._serve())
        except asyncio.CancelledError:  # ended at once (`kill`)
            pass
        except Exception:  # its close failed: nothing more will come from it
            self.emit(LOST, f"it failed:\n{traceback.format_exc()}", False)
        finally:
            self.ready.set()

    async def _serve(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.task = asyncio.current_task()
        self.ready.set()
        await serve(self.make, None, self.inbox, lambda event: self.emit(*event))

    def _command(self, command: Command) -> None:
        self.ready.wait()
        if self.loop is not None:
            with contextlib.suppress(RuntimeError):  # its loop has ended: nothing to tell
                self.loop.call_soon_threadsafe(self.inbox.put_nowait, command)

    def run_chunk(self, chunk: Chunk) -> None:
        self._command(("run", chunk.name, chunk.keys))

    def close(self) -> None:
        self._command(("close",))

    def kill(self) -> None:
        """Cancel its work and wait for its loop to unwind (see the module docstring)."""
        if self.thread.ident is None:  # never started
            return
        self.ready.wait()
        if self.loop is not None and self.task is not None:
            with contextlib.suppress(RuntimeError):  # its loop has ended already
                self.loop.call_soon_threadsafe(self.task.cancel)
        if self.thread is not threading.current_thread():
            self.thread.join()


class LocalEngines(Engines):
    """`driver.Engines` of `executor: local`: one in-process engine, one chunk (its kernels
    compiled as it starts)."""

    label = "local"
    log = log
    engines_wanted = 1
    max_restarts = 0
    shares_board = False

    def __init__(
        self, config: SweepConfig, choices: Choices, run_dir: Path, keys: list[EpisodeKey]
    ):
        super().__init__(config, choices, run_dir)
        cost = max(task_cost(config, k.task) for k in keys)
        self.chunks = [Chunk("sweep", keys, cost)]

    def new_engine(
        self, index: int, slot: int, emit: Emit, board: BoardLink | None
    ) -> InProcessEngine:
        return InProcessEngine(
            emit, lambda: ChunkEngine(self.config, self.choices, self.run_dir, dealt=False)
        )


def run_local(
    config: SweepConfig,
    keys: Sequence[EpisodeKey],
    run_dir: Path,
    choices: Choices,
    **hooks: Unpack[Hooks],
) -> dict[Key, dict[str, Any]]:
    """Run the pending episodes of `keys` in this process on `choices` (`driver.run_engines`)."""

    def engines(cells: Cells) -> contextlib.nullcontext[Engines]:
        pending = {k for part in cells.values() for k in part}
        left = [k for k in keys if k in pending]  # in plan order
        return contextlib.nullcontext(LocalEngines(config, choices, run_dir, left))

    return run_engines(engines, log, "local", keys, run_dir, **hooks)
