"""The engine actor of a Ray sweep: a `chunk_engine.ChunkEngine` as a long-lived Ray actor, one
per GPU (or share of one, or of the CPUs). Its `run_chunk` streams ledger lines to the driver,
the one writer; episode directories go to the run directory every node mounts at one path. It
starts with the variables the driver sends (`environ`: the API keys, kept in memory and this
process's environment, and the engine environment), runs what the driver chose for it
(`config.choices.for_engines`), and refuses to be created where that cannot run (naming what is
missing), so that a node that cannot run it is given no other engine.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from vabench import switches
from vabench.children import child_logging
from vabench.config import SweepConfig
from vabench.config.choices import Choices
from vabench.render.backends import check_renderer
from vabench.run_layout import RunDir
from vabench.sim_mjx.backends import check
from vabench.sweep.chunk_engine import BoardLink, ChunkEngine
from vabench.tuning import mps, precompile

log = logging.getLogger(__name__)


class EngineActor(ChunkEngine):
    """One engine of a Ray sweep (see the module docstring). Created by the driver with
    `ray.remote(EngineActor)`: an async actor, every method runs in its one event loop."""

    def __init__(
        self,
        config: SweepConfig,
        choices: Choices,
        run_dir: str,
        environ: Mapping[str, str],
        board: BoardLink | None = None,
        holder: str = "",
    ):
        os.environ.update(environ)
        # its lines to its own log in the run directory, and on the driver's console (Ray
        # forwards an actor's output) its warnings and the kernels' compilation
        member = f"{socket.gethostname()}-{os.getpid()}"
        child_logging(RunDir(Path(run_dir)).worker_log(member), console=(precompile.__name__,))
        self._mps_member = member
        self._mps_sweep = self._join_mps()  # before this process makes its CUDA context
        try:  # in creation, so that a node that cannot run them is not given another engine
            check(choices.physics.kind)
            check_renderer(choices.renderer)
            super().__init__(config, choices, Path(run_dir))
        except BaseException:
            if self._mps_sweep:
                mps.leave_node_daemon(self._mps_sweep, self._mps_member)
            raise
        self.board = board
        self.holder = holder

    async def start(  # type: ignore[override]
        self, tasks: Sequence[str] = ()
    ) -> dict[str, Any]:
        """The engine opened, compiling the kernels of `tasks` (the sweep's families) ahead;
        where it runs (its node and GPU ids, by which critical chunks spread), for the driver."""
        import ray

        gpus = [str(g) for g in ray.get_gpu_ids()]
        # a GPU's busy share only where Ray gave it one (an actor without a GPU keeps the
        # node's CUDA_VISIBLE_DEVICES: it would read every GPU of the node)
        info = await super().start(tasks, self.board, self.holder, sample_gpu=bool(gpus))
        return info | {"node": ray.get_runtime_context().get_node_id(), "gpus": gpus}

    async def engine_status(self) -> dict[str, Any]:
        """`status()` for the driver (an actor's method runs in the actor's loop)."""
        return self.status()

    async def close(self) -> dict[str, Any]:
        """Close the engine: its GPU's figures; the node's last engine quits the MPS daemon."""
        figures = await super().close()
        if self._mps_sweep:  # (a `quit` may take a moment: off the event loop)
            sweep, self._mps_sweep = self._mps_sweep, ""
            await asyncio.to_thread(mps.leave_node_daemon, sweep, self._mps_member)
        return figures

    def _join_mps(self) -> str:
        """With `mps.NODE_SWEEP` set (engines sharing GPUs): this process made a client of its
        node's MPS daemon of the sweep (`mps.NODE_RANKED`: normal priority for its GPU's first
        engine, else below); the sweep's id, or "" where MPS cannot run (the engines take turns)."""
        sweep = switches.get("ray_mps") or ""
        if not sweep:
            return ""
        try:
            ranked = bool(switches.get("ray_mps_ranked"))
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
