"""The Warp modules a family launches, compiled side by side in threads before it launches them.

Warp compiles a module when a kernel of it is first launched, so one process running a family
compiles its ~45 modules one after another. `load_ahead` names them first without running
anything: while `Module.load` answers None, `wp.launch` returns before launching (Warp's own
path for a module without code), so a batch's build, one physics step and one render pass of
the family, on the family's real models and arrays, record every module (and block size) they
would launch. Those then load in a thread pool: Warp's compilers (clang for the CPU,
NVRTC for CUDA) run outside the GIL, so two threads compile about twice as fast as one, and a
family's real run after it compiles nothing (docs/PERFORMANCE.md, "Start-up and compile").

Only ever an optimisation: a module it misses, or a call that fails (logged), is compiled by
the family's real run after it, as before. The batch built for it has CUDA graphs off (a graph
captured while launches are skipped would be empty) and is thrown away; the step goes through
MuJoCo Warp's functions, not the batch's methods.

Several processes loading ahead at once (one per family, `precompile`) share the work through
claims: a file lock per module in a folder they are given. A thread compiles a module only
while it holds its claim; a module another process holds is set aside and, once every module
this process could claim is done, waited for and then read from Warp's cache. So each module
found ahead and shared by families is compiled once, by whichever process reached it first,
while the others compile the rest. (A module the dry calls miss is compiled by each run that
launches it. Warp itself has no lock between processes: children started together from an
empty cache each compiled every shared module, the last rename winning.)

`compile_log` records which modules a process compiled (those not found in Warp's cache): the
precompile's children report them (`precompile.STATS_ENV`), so that a benchmark or a test can
see that a module shared by families was compiled once.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

log = logging.getLogger(__name__)

OWN_MODULES = "vabench."
"""vabench's own Warp modules (control, rows, the render pass's, the JPEG encoder's): loaded
ahead whole (`own_modules`)."""

Found = dict[tuple[int, str, Any], tuple[Any, Any, Any]]
BLOCKS_PER_SM = 8
"""Resident 256-thread blocks per SM (2,048 threads on a Hopper GPU): the recorded occupancy."""


class Ahead(NamedTuple):
    """What `load_ahead` did: modules loaded, how many of them it waited for (another process
    held their claim), its seconds, and when it ended (`time.monotonic()`)."""

    modules: int = 0
    waited: int = 0
    s: float = 0.0
    ended: float = 0.0
    failed: tuple[str, ...] = ()
    """The dry calls that raised ("physics: ..."): their modules were not found."""


@contextlib.contextmanager
def recording(found: Found) -> Iterator[None]:
    """Within: a launch records (module, device, block size) in `found` and launches nothing;
    a conditional loop runs its body once and a conditional both branches (outside a graph
    capture Warp runs them on the host while a flag on the device says so, and no launch
    changes the flag); an occupancy query on a CUDA device (`wp.get_suggested_block_size`,
    which MuJoCo Warp makes before its broadphase, convex collision and solver launches)
    records its kernel's module at the block size the query loads and answers a plausible
    size (a whole large GPU's worth of 256-thread blocks; where the answer shapes a kernel,
    e.g. under `deterministic`, the real run compiles its own variant). Warp's own query raises
    on CUDA when the module does not load: the dry physics step would end at the broadphase,
    and a fresh machine's precompile would find almost none of the modules ahead. On the CPU
    Warp answers (1, 1) without loading anything, and so does the recording."""
    import warp as wp
    from warp._src import context  # the loader; no public hook exists

    load, loop, branch = context.Module.load, wp.capture_while, wp.capture_if
    occupancy = wp.get_suggested_block_size

    def record(module: Any, device: Any = None, block_dim: Any = None, *_: Any, **__: Any) -> None:
        found.setdefault((id(module), str(device), block_dim), (module, device, block_dim))

    def suggested(kernel: Any, device: Any = None) -> tuple[int, int]:
        on = device if hasattr(device, "is_cuda") else wp.get_device(device)  # a Device or name
        if not on.is_cuda:
            return occupancy(kernel, on)
        record(kernel.module, on, kernel.module.options["block_dim"])  # what the query loads
        return 256, BLOCKS_PER_SM * max(1, int(getattr(on, "sm_count", 0) or 1))

    def once(condition: Any, while_body: Any, stream: Any = None, **kwargs: Any) -> None:
        if callable(while_body):
            while_body(**kwargs)

    def both(
        condition: Any, on_true: Any = None, on_false: Any = None, stream: Any = None, **kwargs: Any
    ) -> None:
        for body in (on_true, on_false):
            if callable(body):
                body(**kwargs)

    context.Module.load = record  # type: ignore[method-assign,assignment]
    wp.capture_while, wp.capture_if = once, both
    wp.get_suggested_block_size = suggested
    try:
        yield
    finally:
        context.Module.load = load  # type: ignore[method-assign]
        wp.capture_while, wp.capture_if = loop, branch
        wp.get_suggested_block_size = occupancy


def load_ahead(
    task: Any, size: tuple[int, int] | None, threads: int, claims: Path | None = None
) -> Ahead:
    """Compile (or load from the cache) in `threads` threads every module that building a
    Warp batch of `task`, one physics step of it and, with `size`, one render pass of it would
    launch, and vabench's own; with `claims`, a folder shared by processes doing the same for
    other families, each module compiled by one of them (`claimed`)."""
    import warp as wp
    from warp._src import context

    from vabench.sim_mjx.warp.device import warp_device, warp_problem

    # Warp set up as the batch sets it up, its loader patched (`modules.keep_loaded`) before
    # `recording` patches it in turn: that patch wraps Warp's loader, not the recorder.
    if problem := warp_problem():
        log.info("load ahead: %s", problem)
        return Ahead()
    device = wp.get_device(warp_device())
    started = time.monotonic()
    found: Found = {}
    failed: list[str] = []
    with recording(found), wp.ScopedDevice(device):
        for name, call in _dry_calls(task, size):
            try:
                call()
            except Exception as err:  # only an optimisation: the real run compiles it
                log.info("load ahead: %s failed (%s); the run compiles what it needs", name, err)
                failed.append(f"{name}: {type(err).__name__}: {str(err)[:300]}")
    launched = list(found.values())
    seen = {id(module) for module, _, _ in launched}
    own = [m for m in own_modules(list(context.user_modules.values())) if id(m) not in seen]

    def load(job: tuple[Any, Any, Any] | Any) -> None:
        if isinstance(job, tuple):
            module, on, block_dim = job
            module.load(on, block_dim)
        else:  # a whole module at the block size a plain launch uses (Warp's rule)
            wp.force_load(device, modules=[job], max_workers=0)

    def claim(job: tuple[Any, Any, Any] | Any) -> str:
        module, block_dim = (job[0], job[2]) if isinstance(job, tuple) else (job, None)
        return f"{module.get_module_identifier(block_dim)}.{device.arch}"

    jobs = [*launched, *own]
    waited = claimed(jobs, load, claim, claims, threads)
    ended = time.monotonic()
    ahead = Ahead(len(jobs), waited, ended - started, ended, tuple(failed))
    log.info(
        "loaded %d Warp modules ahead in %d threads in %.1f s (%d of them held by another "
        "process, waited for)",
        *(ahead.modules, threads, ahead.s, ahead.waited),
    )
    return ahead


def own_modules(modules: Iterable[Any]) -> list[Any]:
    """The Warp modules of `modules` that are vabench's own: one named after a Python module of
    vabench, and one holding a kernel of vabench in a module of its own
    (`module="unique"`, which Warp names after the kernel and its hash: warp_jpeg's
    `_transform`). The renderer loads its JPEG modules when it starts, and no dry call launches
    them (the dry pass encodes nothing): a module left out here is compiled by every process
    that starts a renderer, side by side, from an empty cache."""
    return [
        m
        for m in modules
        if m.kernels
        and (
            m.name.startswith(OWN_MODULES)
            or any(
                getattr(getattr(k, "func", None), "__module__", "").startswith(OWN_MODULES)
                for k in m.kernels.values()
            )
        )
    ]


def claimed(
    jobs: list[Any],
    load: Callable[[Any], None],
    claim: Callable[[Any], str],
    claims: Path | None,
    threads: int,
) -> int:
    """Run `load(job)` for every job in `threads` threads, each while holding the file lock
    named `claim(job)` in `claims` (None: no locks): first every job whose lock is free (the
    others set aside), then the set-aside ones, each after waiting for its lock (its holder,
    another process, is compiling it: the load then finds it in Warp's cache). A job whose claim
    cannot be named or locked loads without one. A failed load is logged (only an
    optimisation: the real run compiles it). Returns how many jobs waited."""

    def attempt(job: Any, wait: bool) -> bool:
        name = getattr(job[0] if isinstance(job, tuple) else job, "name", str(job))
        with contextlib.ExitStack() as stack:
            try:
                held = stack.enter_context(_holding(claims, claim(job) if claims else "", wait))
            except Exception as err:  # no claim (its hash, the folder, the lock): unclaimed
                log.info("load ahead: no claim for module %s (%s)", name, err)
                held = True
            if held:
                try:
                    load(job)
                except Exception as err:
                    log.info("load ahead: module %s failed (%s)", name, err)
            return held

    with ThreadPoolExecutor(max(1, threads)) as pool:
        done = list(pool.map(lambda job: attempt(job, False), jobs))
        later = [job for job, ok in zip(jobs, done, strict=True) if not ok]
        list(pool.map(lambda job: attempt(job, True), later))
    return len(later)


@contextlib.contextmanager
def _holding(claims: Path | None, name: str, wait: bool) -> Iterator[bool]:
    """Within: True while this thread holds the lock `name` in `claims` (always, without
    `claims`); False at once if another holds it and not `wait`."""
    if claims is None:
        yield True
        return
    # A fixed-length file name: module identifiers can be long (Warp's "__locals__" names).
    path = claims / (hashlib.sha256(name.encode()).hexdigest()[:32] + ".lock")
    with open(path, "a") as handle:  # its own open file: flock excludes other threads too
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            got = True
        except BlockingIOError:
            got = False
        if not got:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _dry_calls(task: Any, size: tuple[int, int] | None) -> list[tuple[str, Callable[[], None]]]:
    """What a family launches: a Warp batch's build (its first reset and observation), MuJoCo
    Warp's step, and the render pass's build and draw. The batch is built without CUDA graphs
    (a graph captured here would be empty) and thrown away."""
    import mujoco_warp as mjw

    from vabench.sim_mjx.backends import Physics, make_batch

    built: list[Any] = []

    def batch() -> None:
        built.append(make_batch(task.build_models(), 1, Physics.WARP, graphs=False))

    def physics() -> None:
        m, d = built[0]._m, built[0]._d  # the batch's MuJoCo Warp model and data
        mjw.kinematics(m, d)
        mjw.collision(m, d)
        mjw.step(m, d)

    def render() -> None:
        from vabench.render.camera import CameraPose
        from vabench.render.images import RenderItem
        from vabench.render.warp_pass import RenderPass, pass_size, render_models

        assert size is not None
        models = render_models(task, *size)  # as the renderer's pool makes them
        drawn = RenderPass(models, pass_size(1), size[0], size[1], device_jpeg=False)
        camera = CameraPose(np.array([0.0, -1.0, 1.0]), np.eye(3), 1.0, 45.0, "head")
        drawn.draw([RenderItem(np.zeros(models[0].nq), 0, camera)], None)

    calls = [("batch", batch), ("physics", physics)]
    return calls + ([("render", render)] if size is not None else [])


@contextlib.contextmanager
def compile_log(compiled: list[tuple[str, float, float]]) -> Iterator[None]:
    """Within: (cache directory name, seconds, `time.monotonic()` at its end) of each module
    this process compiles is appended to `compiled` (a module found in Warp's cache is not)."""
    import os

    from warp._src import context

    compile_ = context.Module._compile

    def logged(module: Any, *args: Any, **kwargs: Any) -> bool:
        started = time.monotonic()
        done = bool(compile_(module, *args, **kwargs))
        if done:
            out = kwargs.get("output_dir", args[1] if len(args) > 1 else None)
            name = os.path.basename(str(out)) if out else module.name
            ended = time.monotonic()
            compiled.append((name, ended - started, ended))
        return done

    context.Module._compile = logged  # type: ignore[method-assign,assignment]
    try:
        yield
    finally:
        context.Module._compile = compile_  # type: ignore[method-assign]
