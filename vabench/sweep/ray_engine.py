"""The engine actor of a Ray sweep: one long-lived process per GPU (or per CPU share) that runs
the chunks of the plan the driver hands it, and streams their ledger lines back.

An `EngineActor` holds one engine (`runner.open_engine`) for its whole life: the LLM pool (for
endpoints that are not embedded, with the limits of the sweep's limit board,
`sweep.limiter`), the embedded server when a model uses one, the renderer and the in-flight
gate. On a GPU node it claims one GPU (Ray sets CUDA_VISIBLE_DEVICES to it) and owns the GPU
work of its chunks: MuJoCo Warp physics and Warp's renderer; on a CPU node it runs C MuJoCo and
the GL render workers. Each chunk it is given (`run_chunk`, several at once) runs as a
`LocalSweep` restricted to the chunk, inside that one engine, so its episodes share the
actor's pool, renderer and in-flight limit.

The actor never writes results.jsonl or infrastructure.jsonl: `run_chunk` is a streaming
generator that yields each ledger line (`LINE`) as its episode ends, and a summary (`DONE`)
last; the driver appends the lines. It writes the episodes' own directories (events,
frames, result.json, in the run directory every node sees at the same path), so an episode it
finished but had not reported when it died is adopted from its result.json by the actor that
runs the chunk again.

The process starts with the variables the driver sends it (`environ`): the API keys named by
the config's `api_key_env` (they travel in the actor's creation arguments, in memory, and are
put in this process's environment only), and the environment `sweep.choices` picks for worker
processes (JAX on the CPU unless the physics is MJX on JAX, no GPU memory preallocation).
What it runs on is the driver's decision (`choices.for_engines`), sent with its creation
arguments; the actor only checks that the Warp physics or renderer it was given can run on its
GPU, and refuses to be created when not (the message names what is missing).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from vabench.render.backends import check_renderer
from vabench.run_layout import RunDir
from vabench.sim_mjx.backends import check
from vabench.sweep.cells import WORKER_ENVIRONMENT, KeyTuple, load_document, worker_logging
from vabench.sweep.choices import Choices, configure_jax
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.runner import Engine, LocalSweep, open_engine, start_compiling
from vabench.tuning import gpu_busy, mps, precompile

log = logging.getLogger(__name__)

LINE = "line"
"""A ledger line of `run_chunk`: (LINE, log name, record)."""
DONE = "done"
"""The last item of `run_chunk`: (DONE, summary)."""


class EngineActor:
    """One engine of a Ray sweep (see the module docstring). Created by the driver with
    `ray.remote(...)(EngineActor)`: an async actor, every method runs in its one event loop."""

    def __init__(
        self,
        document: dict[str, Any],
        choices: Choices,
        run_dir: str,
        environ: dict[str, str],
        limiter: Any = None,
        shared: list[str] | None = None,
        holder: str = "",
        capped: bool = False,
    ):
        os.environ.update(environ)
        self.run_dir = Path(run_dir)
        # the engine's lines to its own log in the run directory; on the driver's console (Ray
        # forwards an actor's output) its warnings and the kernels' compilation, minutes on a
        # fresh node that were silent before (measured on a fresh 4 x H100 host, 2026-11-27)
        worker_logging(
            RunDir(self.run_dir),
            f"{socket.gethostname()}-{os.getpid()}",
            console=(precompile.__name__,),
        )
        self.config = load_document(document, self.run_dir)
        self._mps_member = f"{socket.gethostname()}-{os.getpid()}"
        self._mps_sweep = self._join_mps()  # before this process makes its CUDA context
        try:  # in creation, so that a node that cannot run them is not given another engine
            check(choices.physics.kind)
            check_renderer(choices.renderer)
        except BaseException:
            if self._mps_sweep:
                mps.leave_node_daemon(self._mps_sweep, self._mps_member)
            raise
        self.choices = choices
        self.limiter = limiter
        self.shared = list(shared or [])
        self.holder = holder
        self.capped = capped
        """Whether the limit board keeps the spend caps (`sweep.limiter.BoardSpend`)."""
        self.engine: Engine | None = None
        self._stack: contextlib.AsyncExitStack | None = None
        self._sweeps: dict[str, LocalSweep] = {}
        self._gpus: gpu_busy.GpuBusy | None = None
        self._gpu_start: gpu_busy.Totals | None = None

    async def start(self, tasks: list[str] | None = None) -> dict[str, Any]:
        """Open the engine and, with Warp physics on a GPU, start compiling the Warp kernels of
        `tasks` (the sweep's families) side by side in the background (`runner.start_compiling`:
        a chunk's family waits for its own kernels, not for every family's); returns where and
        how it runs, for the driver's log. Compiling here, before any chunk: each chunk compiled
        its own family when it came, one after another (a fresh 4 x H100 host took 372 s for 14
        families). A failure to compile ahead is logged; each chunk then compiles its own."""
        cfg = self.config
        configure_jax(self.choices.physics)
        import jax
        import ray

        stack = contextlib.AsyncExitStack()
        try:
            # the busy share of the GPU this engine was given, for the driver's report of where
            # each engine's time went; only where Ray gave it one (an actor without a GPU keeps
            # the node's CUDA_VISIBLE_DEVICES: it would read every GPU of the node)
            if ray.get_gpu_ids():
                self._gpus = stack.enter_context(gpu_busy.sampling())
            self._gpu_start = self._gpus.totals() if self._gpus is not None else None
            limits = None
            if self.limiter is not None and (self.shared or self.capped):
                from vabench.sweep.limiter import BoardLimits, RayChannel

                channel = RayChannel(self.limiter)
                limits = BoardLimits(channel, self.holder, self.shared, self.capped)
                stack.push_async_callback(limits.close)  # after the pool has closed
            opened = open_engine(
                cfg,
                self.choices,
                self.run_dir,
                shared_limits=limits,
                spend_caps=limits.spend if limits is not None else None,
            )
            self.engine = await stack.enter_async_context(opened)
        except BaseException:
            await stack.aclose()
            raise
        self._stack = stack
        try:
            first = self.choices.executor.critical_path or ()
            await start_compiling(self.engine, self.choices, tasks or [], first)
        except Exception as err:  # each chunk compiles its own families anyway
            log.warning("compiling the sweep's Warp kernels ahead failed (%r); chunks will", err)
        return {
            "host": socket.gethostname(),
            "node": ray.get_runtime_context().get_node_id(),
            "pid": os.getpid(),
            "gpus": [str(g) for g in ray.get_gpu_ids()],  # where critical chunks spread
            "physics": self.engine.physics.label,
            "jax": jax.default_backend(),
            "limit": self.engine.gate.limit,
            "environment": {k: os.environ.get(k) for k in WORKER_ENVIRONMENT},
        }

    async def run_chunk(self, name: str, keys: list[KeyTuple]) -> AsyncIterator[tuple[Any, ...]]:
        """Run the episodes `keys` in this engine; yields (LINE, log, record) as each ledger
        line is written, then (DONE, summary). An error of the chunk itself is raised after its
        lines."""
        assert self.engine is not None, "start() first"
        lines: asyncio.Queue[tuple[str, dict[str, Any]]] = asyncio.Queue()
        sweep = LocalSweep(
            self.config,
            [EpisodeKey(*k) for k in keys],
            self.run_dir,
            self.choices,
            ledger_sink=lambda log, record: lines.put_nowait((log, record)),
        )
        self._sweeps[name] = sweep
        running = asyncio.create_task(sweep.run(self.engine))
        try:
            while not running.done():
                line = asyncio.ensure_future(lines.get())
                await asyncio.wait({line, running}, return_when=asyncio.FIRST_COMPLETED)
                if line.done():
                    yield (LINE, *line.result())
                else:
                    line.cancel()
            while not lines.empty():
                yield (LINE, *lines.get_nowait())
            progress = running.result()  # raises the chunk's error
            records = [sweep.ledger.records.get(k) for k in keys]
            yield (
                DONE,
                {
                    "episodes": len(keys),
                    "recorded": sum(r is not None for r in records),
                    "unscored": sum(
                        r is not None and r["status"] not in ("success", "failure") for r in records
                    ),
                    "retried": progress.total().retried,
                    "stopped": sweep.stopped,
                },
            )
        finally:
            self._sweeps.pop(name, None)
            if not running.done():
                running.cancel()

    async def status(self) -> dict[str, Any]:
        """The engine's state for the driver's display: episodes running per model/track,
        the in-flight gate, and the model calls, tokens and cost of its pool so far."""
        running: dict[str, int] = {}
        for sweep in list(self._sweeps.values()):
            for (model, track, _task), counts in sweep.progress.cells.items():
                if counts.running:
                    key = f"{model}/{track}"
                    running[key] = running.get(key, 0) + counts.running
        out: dict[str, Any] = {"running": running, "chunks": len(self._sweeps), **self._gpu()}
        if self.engine is not None:
            stats = list(self.engine.llm.stats().values())
            gate = self.engine.gate
            out |= {
                "in_flight": gate.in_flight,
                "limit": gate.limit,
                "reason": gate.reason,
                "calls": sum(s.succeeded for s in stats),
                "tokens": sum(s.usage.total_tokens for s in stats),
                "cost": sum(s.cost_usd for s in stats),
                "calls_in_flight": sum(s.in_flight for s in stats),
            }
        return out

    def _gpu(self) -> dict[str, Any]:
        """Its GPU's mean busy share since the engine started and the most memory used."""
        if self._gpus is None:
            return {}
        totals = self._gpus.totals()
        return {
            "gpu_busy": totals.mean_since(self._gpu_start),
            "gpu_memory_mib": totals.memory_max_mib,
        }

    async def close(self) -> dict[str, Any]:
        """Close the engine (the driver calls this once no chunk is left); returns its GPU's
        figures over its life (empty without a GPU). The last engine of the sweep on its node
        tells the node's MPS daemon to quit."""
        figures = self._gpu()
        if self._stack is not None:  # (stopping the GPU sampler waits for its last reading)
            stack, self._stack = self._stack, None
            await stack.aclose()
        if self._mps_sweep:  # (a `quit` may take a moment: off the event loop)
            sweep, self._mps_sweep = self._mps_sweep, ""
            await asyncio.to_thread(mps.leave_node_daemon, sweep, self._mps_member)
        return figures

    def _join_mps(self) -> str:
        """With `mps.NODE_SWEEP` set (engines sharing GPUs): this process made a client of its
        node's daemon of the sweep (with `mps.NODE_RANKED`, at its GPU's normal priority if it
        is the GPU's first engine, else below: its start reply's environment says which); the
        sweep's id, or "" where MPS cannot run here (then the engines sharing a GPU take turns
        on it, said once in the log)."""
        sweep = os.environ.get(mps.NODE_SWEEP, "")
        if not sweep:
            return ""
        try:
            ranked = bool(os.environ.get(mps.NODE_RANKED))
            joined = mps.join_node_daemon(sweep, self._mps_member, ranked=ranked, gpu=_gpu_ids())
            os.environ.update(joined)
        except mps.MpsUnavailable as err:
            log.warning("CUDA MPS: %s; the engines sharing this GPU take turns on it", err)
            return ""
        return sweep


def _gpu_ids() -> str | None:
    """Ray's GPU ids of this actor ("0", "2,3"), the same ids the driver groups engines by
    (`EngineHandle.gpu`); None outside a Ray worker (then CUDA_VISIBLE_DEVICES stands in)."""
    try:
        import ray

        if not ray.is_initialized():
            return None
        return ",".join(str(g) for g in ray.get_gpu_ids())
    except Exception:  # no Ray here, or no worker context: the variable serves
        return None
