"""MuJoCo Warp's kernels for a sweep's families, compiled in parallel before the sweep needs them.

Warp compiles a module's kernels on first use (MuJoCo Warp specialises some on the scene) and
caches them (`~/.cache/warp`); met one family after another in a sweep, with the device's lock
held, a fresh machine's first episodes would wait minutes. `ensure_compiled` compiles, at the
sweep's start, every family not yet compiled for this code on this machine: a child process a
family, all at once, each loading its family's modules ahead (`warp_ahead.load_ahead`), then
stepping its expert a few actions and rendering one image to compile whatever that missed. Most
modules are shared by every family, so the children claim modules through a folder of file
locks: the first to reach one compiles it, the others read it from the cache. The critical
path's families start first, the others at a lower CPU priority (`BEHIND_NICE`).

A marker per family (keyed by the Warp, MuJoCo Warp and vabench code, the GPU's architecture
and the image size) says it is done; a file lock keeps one machine's processes from compiling a
family twice; a child's failure costs only time (the sweep compiles that family itself). The
sweep does not wait for the whole compile (`Compiling`): a family's episodes start once its own
marker is written. `VABENCH_WARP_PRECOMPILE=0` turns it off, `=first` waits for all of it. The
figures: docs/PERFORMANCE.md, "Start-up and compile".
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Collection, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from vabench import switches
from vabench.tuning.warp_ahead import Ahead, compile_log, load_ahead

log = logging.getLogger(__name__)

ENV = switches.variable("warp_precompile")
STATS_ENV = switches.variable("precompile_stats")
"""A folder: each child writes <family>.json there (the modules it compiled, the seconds spent
compiling them, summed over its threads, and its wall seconds)."""
CHILD_TIMEOUT_S = 900
POLL_S = 0.5
"""How often a family waiting for its kernels looks for its marker."""
REPORT_KEYS = {"task", "compiled", "compile_s", "s"}
"""What every child's report has (`main`); the summary reads nothing else without a default."""
CHILDREN_PER_CORE = 2
"""The most children a core: enough for the 22 families of `configs/all.yaml` at once on a
16-core host (a child mostly waits for modules others hold; one a core ran them in two waves,
the second one slower); a 2-core machine runs 4."""
BEHIND_NICE = 5
"""The CPU priority (nice) of the other families' children while a critical one compiles: at
5 a thread gets about a third of the CPU share of one at 0 when they share a core, so the
critical child's threads run whenever they are ready and the others take the rest (a child
at 5 that holds a shared module the critical child waits for compiles it slower; measured the
better of the two: docs/PERFORMANCE.md, "Start-up and compile")."""
EXPERT_STEPS = 3
"""The expert's actions a child runs: the first reset and actions launch every kernel an
episode does (the kernels a step launches depend on the scene, not on the state); a whole
episode only costs time (the basket's whole episode kept its child running on one core long
after the others had ended)."""


def marker_dir() -> Path:
    return Path(switches.get("cache") or Path.home() / ".cache" / "vabench") / "warp_compiled"


def code_key(arch: str, width: int, height: int) -> str:
    """What a compiled family depends on: the packages' versions, vabench's Warp code (its
    kernels and how it calls MuJoCo Warp), the GPU architecture and the image size."""
    import mujoco_warp
    import warp

    import vabench

    digest = hashlib.sha256()
    for part in (warp.__version__, mujoco_warp.__version__, arch, f"{width}x{height}"):
        digest.update(part.encode() + b"\0")
    root = Path(vabench.__file__).parent
    for path in sorted([*root.glob("sim_mjx/warp/*.py"), *root.glob("render/warp*.py")]):
        digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()[:16]


def missing(tasks: Sequence[str], key: str, markers: Path) -> list[str]:
    """The families of `tasks` without a marker for `key`, in order."""
    return [t for t in dict.fromkeys(tasks) if not (markers / f"{t}.{key}").exists()]


@contextlib.contextmanager
def _machine_lock(markers: Path, on_wait: Callable[[], None] | None = None) -> Iterator[None]:
    """The machine's compile lock (`on_wait()` first where another process holds it)."""
    markers.mkdir(parents=True, exist_ok=True)
    with open(markers / ".lock", "w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait()
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def compiling(markers: Path) -> bool:
    """Whether a compile holds the machine's lock now (in any process, this one included)."""
    markers.mkdir(parents=True, exist_ok=True)
    with open(markers / ".lock", "w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(handle, fcntl.LOCK_UN)
        return False


def family_ready(task: str, key: str, markers: Path) -> bool:
    """Whether `task`'s kernels may be used now: its marker for `key` is there (unless the
    environment says `first`), or no compile is running on the machine (what is missing, the
    sweep compiles itself on first use)."""
    if switches.get("warp_precompile") != "first" and (markers / f"{task}.{key}").exists():
        return True
    return not compiling(markers)


def family_key(width: int, height: int, device: str, images: bool) -> str:
    """The markers' key of families compiled for `device` at this image size (`images`: with
    the Warp renderer's kernels)."""
    import warp as wp

    arch = f"sm{wp.get_device(device).arch}"
    return code_key(arch, width if images else 0, height if images else 0)


def ensure_compiled(
    tasks: Sequence[str],
    width: int,
    height: int,
    device: str,
    images: bool = True,
    processes: int | None = None,
    started: threading.Event | None = None,
    first: Collection[str] = (),
) -> list[str]:
    """Compile the Warp kernels of `tasks` not yet compiled here (blocking; see the module
    docstring); `images`: the Warp renderer's too. Each family is marked as its child ends.
    Returns the families that failed to compile (the sweep compiles those itself). `started`
    is set once this call holds the machine's lock, or waits for another process's, or has
    nothing to do: from then on `family_ready` answers for its families. `first`: the
    families on the sweep's critical path (see the module docstring)."""
    try:
        if switches.get("warp_precompile") == "off":
            return []
        return _compile(tasks, width, height, device, images, processes, started, first)
    finally:
        if started is not None:
            started.set()


def _compile(
    tasks: Sequence[str],
    width: int,
    height: int,
    device: str,
    images: bool,
    processes: int | None,
    announce: threading.Event | None,
    first: Collection[str] = (),
) -> list[str]:
    key = family_key(width, height, device, images)
    markers = marker_dir()
    on_wait = announce.set if announce is not None else None
    with _machine_lock(markers, on_wait):
        if announce is not None:
            announce.set()
        todo = missing(tasks, key, markers)
        if not todo:
            return []
        workers, threads = children(len(todo), max(1, processes or os.cpu_count() or 1))
        plan = child_plan(todo, first)
        todo = list(plan)  # the critical families' children start first
        lead = [t for t in todo if not plan[t]] if any(plan.values()) else []
        log.info(
            "compiling MuJoCo Warp's kernels for %d famil%s in %d processes of %d threads%s "
            "(first run of this code on this machine; cached for the next)",
            len(todo),
            "y" if len(todo) == 1 else "ies",
            workers,
            threads,
            f"; {', '.join(lead)} first, the others at nice {BEHIND_NICE}" if lead else "",
        )
        started = time.monotonic()
        size = (width, height) if images else None
        shared = Path(tempfile.mkdtemp(prefix="vabench-precompile-"))
        claims, stats = (
            shared / "claims",
            Path(switches.get("precompile_stats") or shared / "stats"),
        )
        claims.mkdir()
        stats.mkdir(parents=True, exist_ok=True)

        def one(task: str) -> str | None:
            marker = markers / f"{task}.{key}"  # its episodes may start (`family_ready`) ...
            err = _child(task, size, device, threads, claims, stats, plan[task], ready=marker)
            if not err:  # ... once its modules are loaded ahead (the child's), or now
                marker.touch()
            else:  # compiled by the sweep instead, and again by the next one
                marker.unlink(missing_ok=True)
            return err

        try:
            with ThreadPoolExecutor(workers) as pool:
                errors = dict(zip(todo, pool.map(one, todo), strict=True))
            summary = _summary(todo, stats)
        finally:
            shutil.rmtree(shared, ignore_errors=True)
        failed = [t for t, err in errors.items() if err]
        for task in failed:
            log.warning(
                "precompile of %s failed (compiled by the sweep instead): %s", task, errors[task]
            )
        log.info(
            "compiled %d of %d families in %.0f s%s",
            len(todo) - len(failed),
            len(todo),
            time.monotonic() - started,
            summary,
        )
        return failed


class Compiling:
    """`ensure_compiled` of a sweep's families in a thread of its own (`start`), and the wait of
    each family for its own kernels (`ready`): a family's episodes start while others compile."""

    def __init__(
        self,
        tasks: Sequence[str],
        width: int,
        height: int,
        device: str,
        images: bool,
        first: Collection[str] = (),
    ):
        self.key = family_key(width, height, device, images)
        self.markers = marker_dir()
        self.failed: list[str] = []
        self._started = threading.Event()
        self._thread = threading.Thread(
            target=self._run,
            args=(list(tasks), width, height, device, images, tuple(first)),
            name="precompile",
            daemon=True,
        )

    @classmethod
    def start(
        cls,
        tasks: Sequence[str],
        width: int,
        height: int,
        device: str,
        images: bool,
        first: Collection[str] = (),
    ) -> Compiling:
        """Started, and holding the machine's lock or waiting for another process's (blocks
        until then: seconds at most); `first`: the sweep's critical path (`ensure_compiled`)."""
        self = cls(tasks, width, height, device, images, first)
        self._thread.start()
        self._started.wait()
        return self

    def _run(
        self,
        tasks: list[str],
        width: int,
        height: int,
        device: str,
        images: bool,
        first: tuple[str, ...],
    ) -> None:
        try:
            self.failed = ensure_compiled(
                tasks, width, height, device, images, started=self._started, first=first
            )
        except Exception as err:  # the sweep compiles its families itself, as without this
            log.warning("precompile failed (the sweep compiles its families itself): %s", err)

    def ready(self, task: str) -> bool:
        return family_ready(task, self.key, self.markers)

    async def wait(self, task: str) -> None:
        """Until `task`'s kernels are compiled (or nothing compiles them any more)."""
        if self.ready(task):
            return
        waited = time.monotonic()
        while not self.ready(task):
            await asyncio.sleep(POLL_S)
        log.info("%s: its kernels are compiled (waited %.0f s)", task, time.monotonic() - waited)

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)


def child_plan(todo: Sequence[str], first: Collection[str]) -> dict[str, int]:
    """{family: nice} in the order the children start (so that where there are more families
    than children at once, the critical ones are in the first wave): the critical families
    (`first`, those of `todo`) at the usual priority, then the others at `BEHIND_NICE`; where
    none of `todo` is critical, or all are, every child alike."""
    critical = [t for t in todo if t in first]
    if not critical or len(critical) == len(todo):
        return dict.fromkeys(todo, 0)
    return {**dict.fromkeys(critical, 0), **{t: BEHIND_NICE for t in todo if t not in first}}


def children(families: int, cores: int) -> tuple[int, int]:
    """(child processes, threads each) for `families` on `cores`: every family at once up to
    `CHILDREN_PER_CORE` a core; threads beyond the cores, since a child's threads spend much of
    their time waiting (for Python's lock in Warp's codegen, for a module another child
    holds)."""
    workers = max(1, min(families, CHILDREN_PER_CORE * cores))
    return workers, max(2, -(-2 * cores // workers))


def _summary(families: Sequence[str], stats: Path) -> str:
    """What the children reported (`STATS_ENV`): modules compiled and waited for, and the
    slowest child's time, in words ("" if none reported)."""
    reports = []
    for family in families:
        with contextlib.suppress(OSError, ValueError):
            report = json.loads((stats / f"{family}.json").read_text())
            if isinstance(report, dict) and report.keys() >= REPORT_KEYS:
                reports.append(report)  # else a stale or foreign file: left out
    if not reports:
        return ""
    slowest = max(reports, key=lambda r: r["s"])
    dry = sorted({f for r in reports for f in r.get("dry_failed", [])})
    if dry:  # then the children compiled one module after another, in their runs
        log.warning("precompile: finding the modules ahead failed: %s", "; ".join(dry[:3]))
    parts = ", ".join(f"{k} {v:.0f} s" for k, v in slowest.get("parts_s", {}).items())
    return (
        f": {sum(len(r['compiled']) for r in reports)} modules compiled "
        f"({sum(r['compile_s'] for r in reports):.0f} s of compiling, summed over threads), "
        f"{sum(r.get('waited', 0) for r in reports)} waited for, "
        f"{sum(len(r.get('compiled_after', [])) for r in reports)} compiled only after the "
        "first step; "
        f"slowest {slowest['task']} {slowest['s']:.0f} s ({parts or 'no parts'}; compiling "
        f"{', '.join(slowest.get('compiled_after', [])[:6]) or 'nothing'} after the first step)"
    )


def _child(
    task: str,
    size: tuple[int, int] | None,
    device: str,
    threads: int,
    claims: Path | None = None,
    stats: Path | None = None,
    nice: int = 0,
    ready: Path | None = None,
) -> str | None:
    """Compile one family in a child process (its modules loaded ahead in `threads` threads,
    sharing `claims` with the other children; its report written to `stats`; at CPU priority
    `nice` above this process's; `ready`, its marker, written by the child as soon as its
    modules are in, `compile_family`): None, or the end of its output if it failed."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", switches.variable("warp_device"): device}
    if stats is not None:
        env[STATS_ENV] = str(stats)
    command = [sys.executable, "-m", __name__, task, "--threads", str(threads)]
    if claims is not None:
        command += ["--claims", str(claims)]
    if size is not None:
        command += ["--size", f"{size[0]}x{size[1]}"]
    if nice:
        command += ["--nice", str(nice)]
    if ready is not None:
        command += ["--ready", str(ready)]
    try:
        done = subprocess.run(
            command, env=env, capture_output=True, text=True, timeout=CHILD_TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return f"no end after {CHILD_TIMEOUT_S} s"
    if done.returncode != 0:
        return (done.stderr or done.stdout).strip()[-500:] or f"exit {done.returncode}"
    return None


def compile_family(
    task_name: str,
    size: tuple[int, int] | None,
    threads: int = 1,
    claims: Path | None = None,
    loaded: Callable[[], None] | None = None,
) -> tuple[Ahead, dict[str, float]]:
    """In this process: the family's expert for its first `EXPERT_STEPS` actions of one seed
    on Warp physics and (`size`) one image of its last state through the Warp renderer: every
    kernel a sweep of it launches. `threads` > 1 or `claims`: the modules they launch are
    compiled first, in that many threads, each by one of the processes sharing `claims`
    (`warp_ahead`), and `loaded` is called as soon as they are, where every dry call found its
    modules (and found some): the expert's run after it only checks that nothing was missed
    (it compiles none where loading ahead found every module), and the sweep's episodes need
    not wait for it (seconds of the basket's child, whose episodes are the critical path).
    Returns what loading ahead did and each part's seconds."""
    import numpy as np

    from vabench.render import camera as cam
    from vabench.render.images import ImageSettings, RenderItem
    from vabench.render.warp_renderer import WarpRenderPool
    from vabench.sim_mjx.backends import Physics
    from vabench.tasks import REGISTRY
    from vabench.tasks.manifests import verified_seeds
    from vabench.tasks.task_batch import TaskBatch, run_experts

    seconds: dict[str, float] = {}
    clock = time.monotonic()

    def lap(part: str) -> None:
        nonlocal clock
        seconds[part] = round(time.monotonic() - clock, 2)
        clock = time.monotonic()

    task = REGISTRY[task_name]
    ahead_loaded = threads > 1 or claims is not None
    ahead = load_ahead(task, size, threads, claims) if ahead_loaded else Ahead()
    lap("ahead")
    if loaded is not None and ahead_loaded and ahead.modules and not ahead.failed:
        loaded()
    batch = TaskBatch(task, 1, backend=Physics.WARP)
    lap("batch")
    run_experts(batch, verified_seeds(task_name)[:1], max_steps=EXPERT_STEPS)
    lap("expert")
    if size is None:
        return ahead, seconds
    width, height = size
    view = batch.views([0])[0]
    gcs = {arm: view.arms[arm].gc for arm in task.arms}
    item = RenderItem(
        np.asarray(batch.batch.qpos()[0]),
        int(batch.batch.variant()[0]),
        cam.head_view(gcs, task.arms),
        slot=0,
    )
    with WarpRenderPool(max_size=(width, height)) as pool:
        pool.render(task_name, [item], ImageSettings(width, height), batch.batch)
    lap("image")
    return ahead, seconds


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("task")
    parser.add_argument("--size", help="WxH of the images (none: physics only)")
    parser.add_argument("--threads", type=int, default=1, help="compile its modules ahead")
    parser.add_argument("--claims", type=Path, help="a folder of claims shared by processes")
    parser.add_argument("--nice", type=int, default=0, help="lower this process's CPU priority")
    parser.add_argument(
        "--ready", type=Path, help="a marker to write once the modules are loaded ahead"
    )
    args = parser.parse_args(argv)
    if args.nice:  # before its compile threads start: they take their creator's priority
        try:
            os.nice(args.nice)
        except (OSError, AttributeError) as err:  # a sandbox that refuses: compile anyway
            print(f"precompile: --nice {args.nice} refused ({err}); at the usual priority")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    width, height = (int(v) for v in args.size.split("x")) if args.size else (0, 0)
    compiled: list[tuple[str, float, float]] = []
    started = time.monotonic()
    with compile_log(compiled):
        size = (width, height) if args.size else None
        ready = args.ready
        ahead, seconds = compile_family(
            args.task, size, args.threads, args.claims, ready.touch if ready else None
        )
    if stats := switches.get("precompile_stats"):
        report = {
            "task": args.task,
            "compiled": [name for name, _, _ in compiled],
            "compile_s": sum(s for _, s, _ in compiled),  # compiling, summed over threads
            # compiled by the expert's run: modules the first step's launches did not name
            # (every module it compiled, where nothing was loaded ahead)
            "compiled_after": [name for name, _, end in compiled if end > ahead.ended],
            "waited": ahead.waited,
            "dry_failed": list(ahead.failed),
            "ahead_s": ahead.s,
            "parts_s": seconds,
            "s": time.monotonic() - started,
        }
        (Path(stats) / f"{args.task}.json").write_text(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
