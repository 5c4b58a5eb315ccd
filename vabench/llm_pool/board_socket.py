"""The limit board of a sweep's worker processes, served by their parent on a local socket.

`executor: processes` runs its cells in worker processes of one host; each has its own LLM
pool, and all of them take their admissions, concurrency slots and spend reservations from one
`limit_board.LimitBoard` in the parent. `BoardServer` runs that board in a thread of the parent, in
its own event loop, on a Unix socket in a private folder; a worker reaches it through a
`SocketChannel` (`shared_limits.LimitChannel`): `call` waits for the board's answer, `send`
does not. Messages are length-prefixed pickles between processes of the same user (the folder
is theirs alone). One connection is one holder: when it closes (the pool closed, or its
process died, out of memory or killed) the board forgets the holder and frees what it held, so
no dead worker's slot is lost to the others.

Per connection, messages are handled in the order sent: a board method that answers at once
(`hold`, every `send`) runs before the next message is read, so a spend reservation is always
made before its settlement arrives; those that wait (`slots`, `admit`) answer when granted.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import pickle
import struct
import tempfile
import threading
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vabench.llm_pool.limit_board import BoardLimits, LimitBoard

log = logging.getLogger(__name__)

_HEADER = struct.Struct("!I")
SEND = 0
"""A message's number when it wants no answer."""


async def _read(reader: asyncio.StreamReader) -> Any:
    size = _HEADER.unpack(await reader.readexactly(_HEADER.size))[0]
    return pickle.loads(await reader.readexactly(size))


def _frame(message: Any) -> bytes:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(data)) + data


class BoardServer:
    """`board` served on a Unix socket by a thread of this process: `start()` returns the
    address the workers connect to (`SocketChannel`); `close()` stops it."""

    def __init__(self, board: LimitBoard):
        self.board = board
        self._folder = tempfile.mkdtemp(prefix="vabench-board-")
        self.address = str(Path(self._folder) / "board.sock")
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.AbstractServer | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, name="limit-board")
        self._thread.daemon = True

    def start(self) -> str:
        self._thread.start()
        future = asyncio.run_coroutine_threadsafe(self._listen(), self._loop)
        future.result(timeout=30)
        return self.address

    async def _listen(self) -> None:
        self._server = await asyncio.start_unix_server(self._serve, path=self.address)
        os.chmod(self.address, 0o600)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        holder: str | None = None
        waiting: set[asyncio.Task[None]] = set()
        try:
            holder = await _read(reader)
            while True:
                number, method, args = await _read(reader)
                failed: Exception | None = None
                try:
                    answer = getattr(self.board, method)(*args)
                except Exception as err:  # a bad message answers an error, the board lives on
                    answer, failed = None, err
                if asyncio.iscoroutine(answer):
                    task = asyncio.ensure_future(self._answer(writer, number, answer))
                    waiting.add(task)
                    task.add_done_callback(waiting.discard)
                elif number != SEND:
                    value = answer if failed is None else f"{type(failed).__name__}: {failed}"
                    writer.write(_frame((number, failed is None, value)))
                elif failed is not None:
                    log.warning("limit board: %s(%s) failed: %s", method, holder, failed)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass  # the worker closed its pool, or its process is gone
        finally:
            for task in waiting:
                task.cancel()
            if holder is not None:
                self.board.forget(holder)
            writer.close()

    async def _answer(self, writer: asyncio.StreamWriter, number: int, answer: Any) -> None:
        try:
            value, ok = await answer, True
        except Exception as err:
            value, ok = f"{type(err).__name__}: {err}", False
        if not writer.is_closing():
            writer.write(_frame((number, ok, value)))

    def stats(self) -> dict[str, dict[str, Any]]:
        """The board's `stats()`, read in its own thread."""
        return self.call(self.board.stats)

    def call(self, function: Any, *args: Any) -> Any:
        """`function(*args)` run in the board's loop, from another thread."""

        async def run() -> Any:
            return function(*args)

        return asyncio.run_coroutine_threadsafe(run(), self._loop).result(timeout=30)

    def close(self) -> None:
        async def stop() -> None:
            if self._server is not None:
                self._server.close()

        if self._thread.is_alive():
            with contextlib.suppress(Exception):
                asyncio.run_coroutine_threadsafe(stop(), self._loop).result(timeout=10)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)
        with contextlib.suppress(OSError):
            os.unlink(self.address)
            os.rmdir(self._folder)


class SocketChannel:
    """`shared_limits.LimitChannel` to a `BoardServer` at `address`, for one holder (one
    connection). Open it with `connect`, in the loop that uses it."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self._reader = reader
        self._writer = writer
        self._numbers = itertools.count(1)
        self._answers: dict[int, asyncio.Future[Any]] = {}
        self._reading = asyncio.ensure_future(self._read_answers())

    @classmethod
    async def connect(cls, address: str, holder: str) -> SocketChannel:
        reader, writer = await asyncio.open_unix_connection(address)
        writer.write(_frame(holder))
        return cls(reader, writer)

    async def _read_answers(self) -> None:
        try:
            while True:
                number, ok, value = await _read(self._reader)
                future = self._answers.pop(number, None)
                if future is None or future.done():
                    continue
                if ok:
                    future.set_result(value)
                else:
                    future.set_exception(RuntimeError(value))
        except (asyncio.IncompleteReadError, ConnectionError) as err:
            gone = ConnectionError(f"the limit board closed the connection ({err})")
        for future in self._answers.values():
            if not future.done():
                future.set_exception(gone)
        self._answers.clear()

    async def call(self, method: str, *args: Any) -> Any:
        if self._reading.done():
            raise ConnectionError("the limit board closed the connection")
        number = next(self._numbers)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._answers[number] = future
        self._writer.write(_frame((number, method, args)))
        try:
            return await future
        finally:
            self._answers.pop(number, None)

    def send(self, method: str, *args: Any) -> None:
        if not self._writer.is_closing():
            self._writer.write(_frame((SEND, method, args)))

    async def close(self) -> None:
        with contextlib.suppress(Exception):
            await self._writer.drain()
        self._writer.close()
        with contextlib.suppress(Exception):
            await self._writer.wait_closed()
        self._reading.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._reading


@dataclass(frozen=True)
class BoardAddress:
    """What a worker needs to take its limits from the parent's board: the socket, the
    endpoints the board keeps (names), and whether it keeps the spend caps."""

    address: str
    shared: tuple[str, ...]
    capped: bool

    def joined(self, holder: str = "") -> contextlib.AbstractAsyncContextManager[BoardLimits]:
        """`joined(self, holder)`: the limits of this board for the block."""
        return joined(self, holder or None)


@contextlib.asynccontextmanager
async def joined(board: BoardAddress, holder: str | None = None) -> AsyncIterator[BoardLimits]:
    """This process's `BoardLimits` on `board`, for the block (close the pool inside it: the
    board then gets back everything this holder held). `holder`: a name of its own by default
    (a forgotten holder is never served again, so each pool needs a new one)."""
    holder = holder or f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
    channel = await SocketChannel.connect(board.address, holder)
    limits = BoardLimits(channel, holder, board.shared, board.capped)
    try:
        yield limits
    finally:
        await limits.close()
        await channel.close()
