"""How busy the GPUs this process sees are, sampled by the NVIDIA driver while a sweep runs.

Why: "the GPU is half idle" is otherwise read from `nvidia-smi` run beside the sweep; a Ray
engine on a node of several GPUs, or a user's own run, has no such figure, and the scaling
benchmark (`benchmarks/ray_scaling.py`) reports each engine's GPU busy share. `GpuBusy`
asks `nvidia-smi` every `every_s` in a thread of its own for the utilisation of the GPUs
CUDA_VISIBLE_DEVICES names (by index or UUID, as CUDA reads it; every GPU when unset) and
keeps running sums: the mean busy share between any two readings of `totals()`, and the most
memory used. One sampler serves the whole process (`sampling()`: started by its first user,
stopped by its last), so the chunks of a Ray engine or a sweep's tasks do not each run one.

The utilisation is the driver's: the share of its last sampling period (1/6 s to 1 s) in which
a kernel of any process ran on the GPU, so engines sharing a GPU read the same figure. Where
`nvidia-smi` is missing or keeps failing (`MAX_FAILURES` in a row), the sampler says why once
in the log and stops; its figures are then those read before (or none). MIG instances are not
sampled (the driver reports no utilisation per instance). CUDA_VISIBLE_DEVICES indices are
matched to nvidia-smi's, which number GPUs in PCI order as CUDA does with
CUDA_DEVICE_ORDER=PCI_BUS_ID; on a host of mixed GPUs name them by UUID (Ray does for its
actors when told to, and UUIDs always match).
"""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

from vabench.children import visible_gpus

log = logging.getLogger(__name__)

QUERY = "index,uuid,utilization.gpu,memory.used"
DEFAULT_EVERY_S = 1.0
TIMEOUT_S = 10.0
MAX_FAILURES = 3
"""Failed readings in a row after which the sampler stops (one slow answer is not the end)."""


@dataclass(frozen=True)
class Reading:
    """One answer of the driver for the GPUs watched: their mean busy share (0-1), their
    memory used in MiB (summed)."""

    busy: float
    memory_mib: float


@dataclass(frozen=True)
class Totals:
    """Running sums since the sampler started: readings taken, the sum of their busy shares,
    the most memory seen (MiB)."""

    readings: int = 0
    busy_sum: float = 0.0
    memory_max_mib: float = 0.0

    def mean_since(self, before: Totals | None = None) -> float | None:
        """The mean busy share of the readings since `before` (all of them when None)."""
        n0, s0 = (before.readings, before.busy_sum) if before is not None else (0, 0.0)
        n = self.readings - n0
        return (self.busy_sum - s0) / n if n > 0 else None


def parse(lines: str, watched: Sequence[str]) -> Reading | None:
    """The reading of `nvidia-smi --query-gpu=QUERY --format=csv,noheader,nounits` for the GPUs
    `watched` names (indices or UUIDs, as in CUDA_VISIBLE_DEVICES; empty: every GPU listed).
    None when none of them is listed or a figure is not a number ('[N/A]' on some GPUs)."""
    busy: list[float] = []
    memory = 0.0
    for line in lines.splitlines():
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 4:
            continue
        index, uuid, util, used = fields
        if watched and not any(
            w == index or (w.startswith("GPU-") and uuid.startswith(w)) for w in watched
        ):
            continue
        try:
            busy.append(float(util) / 100.0)
            memory += float(used)
        except ValueError:
            return None
    if not busy:
        return None
    return Reading(sum(busy) / len(busy), memory)


class GpuBusy:
    """Samples the visible GPUs' utilisation in a thread (see the module docstring); use as a
    context manager or `start()` / `stop()`."""

    def __init__(
        self,
        every_s: float = DEFAULT_EVERY_S,
        environ: Mapping[str, str] | None = None,
        command: str = "nvidia-smi",
    ):
        self.every_s = every_s
        env = os.environ if environ is None else environ
        visible = visible_gpus(env)
        self.watched = tuple(g for g in visible if not g.startswith("MIG-"))
        # MIG instances only: the driver gives no utilisation per instance (an empty `watched`
        # would mean every GPU of the node)
        self.mig_only = bool(visible) and not self.watched
        self.command = command
        self._totals = Totals()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.failed: str | None = None
        """Why no reading came (the command missing or failing), once it has failed."""

    def read(self) -> Reading | None:
        """One reading now (None where the driver cannot be asked)."""
        if self.mig_only:
            self.failed = "MIG instances: the driver reports no utilisation per instance"
            return None
        try:
            done = subprocess.run(
                [self.command, f"--query-gpu={QUERY}", "--format=csv,noheader,nounits"],
                capture_output=True,
                text=True,
                timeout=TIMEOUT_S,
            )
        except (OSError, subprocess.SubprocessError) as err:
            self.failed = f"{self.command}: {err}"
            return None
        if done.returncode != 0:
            self.failed = f"{self.command} exited {done.returncode}: {done.stderr.strip()[:200]}"
            return None
        reading = parse(done.stdout, self.watched)
        if reading is None:
            listed = parse(done.stdout.replace("[N/A]", "0"), self.watched) is not None
            self.failed = (
                f"{self.command} reports no utilisation ([N/A]) for the GPUs {list(self.watched)}"
                if listed
                else f"{self.command} listed none of the GPUs {list(self.watched)}"
            )
        return reading

    def totals(self) -> Totals:
        with self._lock:
            return self._totals

    def _run(self) -> None:
        failures = 0
        while not self._stop.is_set():
            reading = self.read()
            if reading is None:
                failures += 1
                if failures >= MAX_FAILURES or self.mig_only:
                    log.info("GPU busy share not sampled: %s", self.failed)
                    return
                self._stop.wait(self.every_s)
                continue
            failures = 0
            with self._lock:
                t = self._totals
                self._totals = Totals(
                    t.readings + 1,
                    t.busy_sum + reading.busy,
                    max(t.memory_max_mib, reading.memory_mib),
                )
            self._stop.wait(self.every_s)

    def start(self) -> GpuBusy:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="gpu-busy", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=TIMEOUT_S + 1)

    def __enter__(self) -> GpuBusy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


_shared: GpuBusy | None = None
_users = 0
_shared_lock = threading.Lock()


@contextlib.contextmanager
def sampling(environ: Mapping[str, str] | None = None) -> Iterator[GpuBusy | None]:
    """The process's sampler for the block (started by the first block, stopped when the last
    ends); None where the process sees no GPU."""
    global _shared, _users
    env = os.environ if environ is None else environ
    if not any(not g.startswith("MIG-") for g in visible_gpus(env)):
        yield None  # no GPU, or only MIG instances (no utilisation per instance)
        return
    with _shared_lock:
        if _shared is None:
            _shared = GpuBusy(environ=env).start()
        _users += 1
        sampler = _shared
    try:
        yield sampler
    finally:
        with _shared_lock:
            _users -= 1
            last = _users == 0
            if last:
                _shared = None
        if last:
            sampler.stop()
