"""The embedded server in several processes on one port (`ServerConfig.server_processes`).

One process cannot read, validate and answer every request of a many-core sweep: each request
carries megabytes of JSON with base64 images, and the reference agent decodes and segments
them. Here n processes each run the whole server (routes, validation, policy in threads,
simulated latency, cache and faults) and listen on the same port with SO_REUSEPORT, so the
kernel spreads the client's connections over them, and the process that started them (the
sweep's engine) does no HTTP work at all.

The parent reserves the port (a bound socket with SO_REUSEPORT that never listens), starts the
processes (spawned, never forked: the parent may hold JAX and threads), waits until each
listens, and collects the record of every request they finish through a pipe, so its
`LocalServer.log`, `counts` and JSONL log are those of one server. The processes ignore Ctrl-C
and exit when their parent is gone (`vabench.children`); `stop` ends them.

This module sits below the server, which starts the processes: what each process runs (the
server's `_serve_in_process`) is passed in, and the record it sends is `request_record`'s, so
nothing here imports the server back.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import socket
import threading
import time
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any

from vabench.children import children_ignore_sigint, exit_with_parent, ignore_sigint
from vabench.llm_pool.request_record import RequestRecord

if TYPE_CHECKING:
    from vabench.llm_pool.server_config import ServerConfig

Serve = Callable[["ServerConfig", int, str, int, Any, Any], Coroutine[Any, Any, None]]
"""How one process serves: (its config, its index, host, port, the records queue, the stop
event); the server's `_serve_in_process`, a module-level function so that it reaches the
spawned process by name."""

START_TIMEOUT_S = 120.0
"""How long the processes may take to import and listen (the reference agent's code included)."""
READY = "ready"


class ServingProcesses:
    """n server processes on one port; `on_record` is told each finished request (in a thread
    of this process)."""

    def __init__(
        self,
        config: ServerConfig,
        n: int,
        serve: Serve,
        on_record: Callable[[RequestRecord], None],
    ) -> None:
        self.config, self.n, self.serve, self.on_record = config, n, serve, on_record
        self._context = multiprocessing.get_context("spawn")
        self._records = self._context.SimpleQueue()
        self._stop = self._context.Event()
        self._processes: list[Any] = []
        self._reader: threading.Thread | None = None
        self._ready = threading.Semaphore(0)
        self._port_holder: socket.socket | None = None

    def start(self, host: str, port: int) -> tuple[str, int]:
        """Start the processes on host:port (0: a free one); returns where they listen."""
        holder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        holder.bind((host, port))  # never listens: it keeps the port for the processes
        self._port_holder = holder
        host, port = holder.getsockname()[:2]
        self._reader = threading.Thread(target=self._read, name="server-records", daemon=True)
        self._reader.start()
        with children_ignore_sigint():
            for index in range(self.n):
                process = self._context.Process(
                    target=_serve_in_child,
                    args=(
                        self.serve,
                        self.config,
                        index,
                        host,
                        port,
                        self._records,
                        self._stop,
                        os.getpid(),
                    ),
                    name=f"vabench-server-{index}",
                    daemon=True,
                )
                process.start()
                self._processes.append(process)
        deadline = time.monotonic() + START_TIMEOUT_S
        for _ in range(self.n):
            while not self._ready.acquire(timeout=0.2):
                dead = [p for p in self._processes if p.exitcode is not None]
                if dead or time.monotonic() > deadline:
                    self.stop()
                    why = f"exited with {dead[0].exitcode}" if dead else "did not start in time"
                    raise RuntimeError(f"an embedded server process {why}")
        return host, port

    def stop(self) -> None:
        """End the processes (each finishes what it is answering), then the record reader."""
        self._stop.set()
        for process in self._processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
                process.join(timeout=5)
        self._records.put(None)
        if self._reader is not None:
            self._reader.join(timeout=10)
        if self._port_holder is not None:
            self._port_holder.close()
            self._port_holder = None

    def _read(self) -> None:
        while (item := self._records.get()) is not None:
            if item == READY:
                self._ready.release()
            else:
                self.on_record(item)


def _serve_in_child(
    serve: Serve,
    config: ServerConfig,
    index: int,
    host: str,
    port: int,
    records: Any,
    stop: Any,
    parent_pid: int,
) -> None:
    """One serving process: the whole server in this process's event loop, its policies in
    threads, each finished request's record sent to the parent."""
    ignore_sigint()
    exit_with_parent(parent_pid)
    seed = None if config.seed is None else config.seed + index
    own = config.model_copy(
        update={"server_processes": 0, "policy_processes": 0, "log_path": None, "seed": seed}
    )
    asyncio.run(serve(own, index, host, port, records, stop))
