"""Where a sweep process's time goes while it runs: the event loop's lag and CPU, the CPU of
each group of threads, and of the child processes (the embedded server's, the render workers).

Why: a sweep process can run with the GPU half idle and most cores idle while its decisions
take seconds (docs/PERFORMANCE.md, "Engine processes on one GPU"): something in the process
paces the rest, and the candidates tell apart by these figures:

- the event loop saturated: its thread's CPU near 100 % and its lag large;
- the interpreter lock: the loop's lag large while its CPU is low (it waits for the lock held
  by the batch threads), and the Python threads' CPU summing to about one core;
- the GPU or the model server: the loop mostly idle, its lag small, the children busy;
- the Warp device lock (held while a batch or a render pass queues its work): held most of
  the time, with threads waiting on it.

Two more figures tell apart the causes of a late loop whose own CPU is low: the machine's
runnable threads against its cores (`/proc/loadavg`, read at each probe: above the cores, every
thread waits for one, the loop's too) and the time Python's cyclic garbage collector stopped
the process (`GcPauses`: a collection holds the interpreter lock, so every Python thread waits
it out; a full one walks every object of the heap, ~0.1 s for the ~300,000 of an engine
process after its imports on this project's 2-core CPU).

Each line also gives the GPUs' busy share where the process sees a GPU (`gpu_busy.GpuBusy`:
the driver's utilisation, sampled every second), so a line says at once whether the GPU waits.

`HostLoad` samples every `every_s` (a line each time, and one for the whole run at the end);
it reads /proc (Linux), costs a few milliseconds a sample, and says nothing elsewhere.
`VABENCH_HOSTLOAD_S` sets the period (0: off; default `DEFAULT_EVERY_S`).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import re
import sys
import threading
import time
from collections import defaultdict
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from vabench import switches
from vabench.tuning import gpu_busy
from vabench.tuning.gpu_busy import GpuBusy, Totals

log = logging.getLogger(__name__)

ENV = switches.variable("hostload_s")
DEFAULT_EVERY_S = 60.0
LAG_PROBE_S = 0.1
"""The loop's lag is how late a sleep of this length wakes up."""

_PROC = Path("/proc")


def every_s_from_env() -> float:
    return float(switches.get("hostload_s"))


def runnable_threads() -> int | None:
    """Threads of the whole machine running or waiting for a core now (`/proc/loadavg`'s
    fourth field, "running/total"), or None where it cannot be read."""
    text = _read(_PROC / "loadavg")
    try:
        return int(text.split()[3].split("/")[0]) if text else None
    except (IndexError, ValueError):
        return None


@dataclass
class GcPauses:
    """The collections of Python's cyclic garbage collector since the last `take`: how many
    walked the whole heap (generation 2), how long all of them stopped the process, the longest.
    `install` hooks it into `gc.callbacks` (a collection runs in whichever thread allocated, with
    the interpreter lock held, so these plain updates do not race)."""

    seconds: float = 0.0
    full: int = 0
    max_s: float = 0.0
    _start: float | None = None

    def callback(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._start = time.perf_counter()
            return
        if self._start is None:  # hooked in during a collection
            return
        took = time.perf_counter() - self._start
        self._start = None
        self.seconds += took
        self.max_s = max(self.max_s, took)
        self.full += info.get("generation") == 2

    def take(self) -> GcPauses:
        """The figures so far; this one starts again from nothing."""
        out = GcPauses(self.seconds, self.full, self.max_s)
        self.seconds, self.full, self.max_s = 0.0, 0, 0.0
        return out

    def add(self, other: GcPauses) -> None:
        self.seconds += other.seconds
        self.full += other.full
        self.max_s = max(self.max_s, other.max_s)

    @contextlib.contextmanager
    def install(self) -> Iterator[GcPauses]:
        gc.callbacks.append(self.callback)
        try:
            yield self
        finally:
            gc.callbacks.remove(self.callback)


def _fields(stat_line: str) -> list[str]:
    """The fields of a /proc stat line after the command name (which may hold spaces and
    parentheses: split after its last ')'); [1] is the parent, [11:13] utime and stime, [13:15]
    the reaped children's, in clock ticks."""
    return stat_line.rsplit(")", 1)[1].split()


def _ticks(stat_line: str) -> int:
    """utime + stime of a /proc stat line, in clock ticks."""
    fields = _fields(stat_line)
    return int(fields[11]) + int(fields[12])


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:  # a thread or process that ended between listing and reading
        return None


def thread_group(name: str) -> str:
    """A thread's group: its name without the task and the pool index ('sim-lift_pot_0' ->
    'sim', 'jpeg_3' -> 'jpeg'); the main thread is the event loop's."""
    if name == "MainThread":
        return "event loop"
    head = re.split(r"[-_:]", name, maxsplit=1)[0]
    return head or name


def thread_ticks(loop_thread: int | None = None) -> dict[str, int]:
    """CPU ticks of this process's threads, by group; threads Python did not start (CUDA's,
    nvImageCodec's, the allocator's) are 'native'. `loop_thread`: the native id of the event
    loop's thread where it is not the main thread (a sweep's in-process engine, a Ray actor's
    loop); the main thread is then 'main'."""
    names = {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}
    if loop_thread is not None and names.get(loop_thread) != "MainThread":
        names = {tid: "main" if n == "MainThread" else n for tid, n in names.items()}
        names[loop_thread] = "MainThread"
    out: dict[str, int] = defaultdict(int)
    for task in (_PROC / "self" / "task").iterdir():
        line = _read(task / "stat")
        if line is None:
            continue
        tid = int(task.name)
        out[thread_group(names[tid]) if tid in names else "native"] += _ticks(line)
    return dict(out)


def children_ticks() -> int:
    """CPU ticks of this process's children: those running (their own and their reaped
    children's) and those that ended and were waited for (`os.times`). A thread's CPU has no
    such account: a thread that ends between two samples takes its share with it (the
    sweep's threads live as long as their task)."""
    parent = os.getpid()
    reaped = os.times()
    total = round((reaped.children_user + reaped.children_system) * os.sysconf("SC_CLK_TCK"))
    for entry in _PROC.iterdir():
        if not entry.name.isdigit():
            continue
        line = _read(entry / "stat")
        if line is None:
            continue
        fields = _fields(line)
        if int(fields[1]) == parent:
            total += sum(int(f) for f in fields[11:15])
    return total


def device_locks() -> dict[str, tuple[float, float, int]]:
    """The Warp device locks' figures (`sim_mjx.warp.device.lock_figures`), where this process
    uses Warp (never imported for it)."""
    device = sys.modules.get("vabench.sim_mjx.warp.device")
    return device.lock_figures() if device is not None else {}


@dataclass
class Sample:
    at: float
    threads: dict[str, int]
    children: int
    locks: dict[str, tuple[float, float, int]] = field(default_factory=dict)
    gpu: Totals | None = None


@dataclass
class Window:
    """The figures between two samples."""

    seconds: float
    cores: dict[str, float]
    """Cores busy on average, by thread group (and 'children')."""
    lag_mean_s: float
    lag_max_s: float
    locks: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    """Per device lock: (share of the time held, thread-seconds waited per second, holds per
    second)."""
    gpu_busy: float | None = None
    """The visible GPUs' mean busy share (None: not sampled)."""
    gpu_memory_mib: float = 0.0
    """The most GPU memory used so far (all processes on the GPUs watched)."""
    runnable_mean: float | None = None
    """The machine's threads running or waiting for a core, on average over the probes (None:
    not read)."""
    runnable_max: int = 0
    machine_cores: int = field(default_factory=lambda: os.cpu_count() or 1)
    gc: GcPauses | None = None
    """The garbage collector's pauses in the window (None: not watched)."""

    def describe(self) -> str:
        loop = self.cores.get("event loop", 0.0)
        rest = sorted(
            ((g, c) for g, c in self.cores.items() if g not in ("event loop", "children")),
            key=lambda gc: -gc[1],
        )
        threads = ", ".join(f"{g} {c:.2f}" for g, c in rest if c >= 0.005) or "none"
        process = sum(c for g, c in self.cores.items() if g != "children")
        locks = "".join(
            f"; {name} lock held {held:.0%} of the time, {waited:.1f} threads waiting on "
            f"average, {holds:.0f} holds/s"
            for name, (held, waited, holds) in sorted(self.locks.items())
        )
        gpu = (
            f"; GPU busy {self.gpu_busy:.0%} (memory {self.gpu_memory_mib / 1024:.1f} GiB at most)"
            if self.gpu_busy is not None
            else ""
        )
        machine = (
            f"; machine: {self.runnable_mean:.1f} threads runnable on average for "
            f"{self.machine_cores} cores (at most {self.runnable_max})"
            if self.runnable_mean is not None
            else ""
        )
        collector = (
            f"; garbage collector {self.gc.seconds / self.seconds:.1%} of the time "
            f"({self.gc.full} full collections, the longest {self.gc.max_s * 1e3:.0f} ms)"
            if self.gc is not None
            else ""
        )
        return (
            f"event loop {loop:.0%} of a core, late {self.lag_mean_s * 1e3:.0f} ms on average "
            f"(at most {self.lag_max_s * 1e3:.0f} ms); this process {process:.1f} cores "
            f"(threads: {threads}); child processes {self.cores.get('children', 0.0):.1f} cores"
            f"{machine}{collector}{locks}{gpu}"
        )


@dataclass
class Lags:
    """How late the loop woke up: running figures (a sweep of hours keeps no list)."""

    total_s: float = 0.0
    n: int = 0
    max_s: float = 0.0
    runnable_total: int = 0
    runnable_n: int = 0
    runnable_max: int = 0

    def add(self, late_s: float, runnable: int | None = None) -> None:
        self.total_s += late_s
        self.n += 1
        self.max_s = max(self.max_s, late_s)
        if runnable is not None:
            self.runnable_total += runnable
            self.runnable_n += 1
            self.runnable_max = max(self.runnable_max, runnable)

    def runnable_mean(self) -> float | None:
        return self.runnable_total / self.runnable_n if self.runnable_n else None


def window(a: Sample, b: Sample, lags: Lags, pauses: GcPauses | None = None) -> Window:
    seconds = max(b.at - a.at, 1e-9)
    hz = os.sysconf("SC_CLK_TCK")
    cores = {
        g: (b.threads.get(g, 0) - a.threads.get(g, 0)) / hz / seconds
        for g in set(a.threads) | set(b.threads)
    }
    # a group whose threads ended in between can read negative: they are gone, not negative
    cores = {g: max(c, 0.0) for g, c in cores.items()}
    cores["children"] = max(b.children - a.children, 0) / hz / seconds
    locks = {}
    for name, (waited, held, holds) in b.locks.items():
        w0, h0, n0 = a.locks.get(name, (0.0, 0.0, 0))
        locks[name] = ((held - h0) / seconds, (waited - w0) / seconds, (holds - n0) / seconds)
    busy = b.gpu.mean_since(a.gpu) if b.gpu is not None else None
    return Window(
        seconds,
        cores,
        lags.total_s / lags.n if lags.n else 0.0,
        lags.max_s,
        locks,
        busy,
        b.gpu.memory_max_mib if b.gpu is not None else 0.0,
        runnable_mean=lags.runnable_mean(),
        runnable_max=lags.runnable_max,
        gc=pauses,
    )


@dataclass
class HostLoad:
    """Samples this process while the sweep runs (see the module docstring)."""

    every_s: float = field(default_factory=every_s_from_env)
    last: Sample | None = None
    lags: Lags = field(default_factory=Lags)
    all_lags: Lags = field(default_factory=Lags)
    # the windows so far, summed (the whole run is their sum, which keeps the CPU of threads
    # that ended in between, a finished task's batch threads, where one window from the first
    # sample to the last would lose it)
    seconds: float = 0.0
    core_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    lock_s: dict[str, list[float]] = field(default_factory=dict)
    gpus: GpuBusy | None = None
    """The GPU sampler `watching` runs where the process sees a GPU."""
    gpu_start: Totals | None = None
    """Its sums at the first sample (the sampler is the process's, shared)."""
    pauses: GcPauses | None = None
    """The garbage collector's pauses since the last sample, where `watching` hooks it in."""
    all_pauses: GcPauses = field(default_factory=GcPauses)
    loop_thread: int | None = None
    """The native id of the event loop's thread (`watching` sets it)."""

    @staticmethod
    def available() -> bool:
        return (_PROC / "self" / "task").is_dir()

    def sample(self) -> Sample:
        gpu = self.gpus.totals() if self.gpus is not None else None
        ticks = thread_ticks(self.loop_thread)
        return Sample(time.monotonic(), ticks, children_ticks(), device_locks(), gpu)

    def tick(self) -> Window | None:
        """A sample; the window since the one before (None for the first)."""
        now = self.sample()
        before, self.last = self.last, now
        if before is None:
            self.gpu_start = now.gpu
            return None
        pauses = self.pauses.take() if self.pauses is not None else None
        w = window(before, now, self.lags, pauses)
        self.lags = Lags()
        if pauses is not None:
            self.all_pauses.add(pauses)
        self.seconds += w.seconds
        for group, cores in w.cores.items():
            self.core_s[group] += cores * w.seconds
        for name, figures in w.locks.items():
            sums = self.lock_s.setdefault(name, [0.0, 0.0, 0.0])
            for k, x in enumerate(figures):
                sums[k] += x * w.seconds
        return w

    def whole_run(self) -> Window | None:
        if not self.seconds:
            return None
        t, lags = self.seconds, self.all_lags
        gpu = self.gpus.totals() if self.gpus is not None else None
        return Window(
            t,
            {g: c / t for g, c in self.core_s.items()},
            lags.total_s / lags.n if lags.n else 0.0,
            lags.max_s,
            {name: (s[0] / t, s[1] / t, s[2] / t) for name, s in self.lock_s.items()},
            gpu.mean_since(self.gpu_start) if gpu is not None else None,
            gpu.memory_max_mib if gpu is not None else 0.0,
            runnable_mean=lags.runnable_mean(),
            runnable_max=lags.runnable_max,
            gc=self.all_pauses if self.pauses is not None else None,
        )

    async def _probe(self) -> None:
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(LAG_PROBE_S)
            late = max(time.monotonic() - t0 - LAG_PROBE_S, 0.0)
            runnable = runnable_threads()
            self.lags.add(late, runnable)
            self.all_lags.add(late, runnable)

    async def _report(self) -> None:
        self.tick()
        while True:
            await asyncio.sleep(self.every_s)
            w = await asyncio.to_thread(self.tick)
            if w is not None:
                log.info("host: %s", w.describe())


@contextlib.asynccontextmanager
async def watching(load: HostLoad | None = None) -> AsyncIterator[HostLoad | None]:
    """`HostLoad` sampling for the block, a line every `every_s` and one for the whole block
    at its end; nothing where it is off or /proc is missing."""
    load = load or HostLoad()
    if load.every_s <= 0 or not load.available():
        yield None
        return
    load.loop_thread = threading.get_native_id()  # this block runs in the loop's thread
    gpus = contextlib.ExitStack()
    if load.gpus is None:
        load.gpus = gpus.enter_context(gpu_busy.sampling())
    hooks = contextlib.ExitStack()
    if load.pauses is None:
        load.pauses = hooks.enter_context(GcPauses().install())
    tasks = [
        asyncio.create_task(load._probe(), name="hostload-lag"),
        asyncio.create_task(load._report(), name="hostload-report"),
    ]
    try:
        yield load
    finally:
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        load.tick()
        hooks.close()
        await asyncio.to_thread(gpus.close)
        whole = load.whole_run()
        if whole is not None:
            log.info("host, whole run (%.0f s): %s", whole.seconds, whole.describe())
