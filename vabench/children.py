"""Child processes never see the terminal's Ctrl-C; their parent ends them; and they size
their pools to their share of the cores.

A terminal sends SIGINT to its whole foreground process group: every render worker, cell
worker and policy worker along with the command. One interrupted mid-call prints a traceback
and leaves its parent waiting for an answer, so vabench starts its children with SIGINT blocked
(`children_ignore_sigint`: the mask is inherited through fork and exec, so there is no window
before the child's first line) and each child ignores it from its first line
(`ignore_sigint`). The command decides what Ctrl-C means (`vabench.sweep.interrupt`) and stops
its children itself.

Cores: `usable_cores()` is what a process sizes its thread and process pools for (policy
workers, JPEG threads, worker processes). `VABENCH_CORES` overrides it: the sweep sets it in
each of its worker processes to that worker's share of the host (`executor: processes`), so
that 16 workers on 16 cores do not each start pools sized for all 16 (16 cell workers each
starting 8 policy processes of the embedded server would be 128 processes on 16 cores); the
test suite pins it so that its sweeps run the same way on any machine.

Logs: a child logs to a file of its own, warnings also to the console (`child_logging`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from vabench import switches


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


@contextlib.contextmanager
def started_with(env: Mapping[str, str]) -> Iterator[None]:
    """`env` added to os.environ while child processes are started (they copy it at start:
    spawn, fork and exec alike); the environment as it was afterwards."""
    before = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def ignore_sigint() -> None:
    """In a child's main thread, first: ignore SIGINT from now on (a press that arrived while
    it was blocked is discarded, not delivered)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


CORES_VARIABLE = switches.variable("cores")


def usable_cores(environ: Mapping[str, str] = os.environ) -> int:
    """The cores this process sizes its pools for: `VABENCH_CORES` when set (its share, given by
    the sweep, or pinned by the user), else the CPUs it may run on. Raises
    `switches.SwitchError` for a value that is no whole number >= 1."""
    pinned: int | None = switches.get("cores", environ)
    return len(os.sched_getaffinity(0)) if pinned is None else pinned


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


def process_age_s(pid: int | str = "self") -> float | None:
    """Seconds since process `pid` started (Linux: /proc's start time in clock ticks after boot
    against the uptime); None where /proc does not say. What a start-up line measures from:
    the interpreter's own start and every import are inside it."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()  # the name may hold spaces
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: starttime
    except (OSError, ValueError, IndexError):
        return None


def visible_gpus(environ: Mapping[str, str] = os.environ) -> tuple[str, ...]:
    """The CUDA devices processes started here would see: CUDA_VISIBLE_DEVICES when set (up to
    its first hidden entry, as CUDA reads it), else the GPUs of the NVIDIA driver."""
    listed = environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        out: list[str] = []
        for entry in (x.strip() for x in listed.split(",")):
            if not entry or entry.startswith("-"):
                break
            out.append(entry)
        return tuple(out)
    driver = Path("/proc/driver/nvidia/gpus")
    n = len(list(driver.iterdir())) if driver.is_dir() else 0
    return tuple(str(i) for i in range(n))


def child_logging(path: Path, console: Sequence[str] = ()) -> None:
    """Logging for a process the sweep started (a processes worker, a Ray engine): it starts
    with none, and its INFO lines (stage lines, "host:" lines, what the engine chose, the
    kernels' compilation) go to its own file `path` (in the run directory), its warnings to
    the console, and so do the INFO lines of the loggers named in `console` (a Ray engine's
    console is the driver's, prefixed with the actor)."""
    root = logging.getLogger()
    if any(getattr(h, "baseFilename", None) == os.path.abspath(path) for h in root.handlers):
        return  # set up already (an initializer run twice in one process)
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        to_file = logging.FileHandler(path, encoding="utf-8")
        to_file.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
        root.addHandler(to_file)
    if any(type(h) is logging.StreamHandler for h in root.handlers):
        root.setLevel(logging.INFO)
        return  # a console set up already (e.g. Ray's `logging_config`): lines once, not twice
    shown = tuple(console)

    def on_console(record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or record.name.startswith(shown or "\0")

    to_console = logging.StreamHandler()
    to_console.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
    to_console.addFilter(on_console)
    root.addHandler(to_console)
    root.setLevel(logging.INFO)
