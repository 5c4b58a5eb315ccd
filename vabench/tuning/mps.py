"""CUDA's multi-process service (MPS) for the engine processes that share one GPU.

Why several engine processes on one GPU: one process is paced by its host side, not by the
GPU: its threads queue their work through one device lock and one interpreter while the GPU
idles; four engine processes (whole task families dealt over them) keep it busy
(docs/PERFORMANCE.md, "Engine processes on one GPU").

Why MPS: without it the CUDA contexts of several processes take turns on the GPU in time
slices (16 worker processes made fewer episodes a second than one process); under MPS their
kernels run side by side as one context's streams would.

The sweep starts a daemon of its own (`private_daemon`): its pipe and log folders in a new
temporary folder, given to the sweep's workers alone (`CUDA_MPS_PIPE_DIRECTORY`), so that no
other process of the machine becomes its client; it is told to quit when the sweep ends, on
errors and Ctrl-C too. A daemon the user runs already (`CUDA_MPS_PIPE_DIRECTORY` set in the
sweep's environment, or one listening on the default `/tmp/nvidia-mps`) is used as it is and
left running. A sweep killed by SIGKILL or SIGTERM leaves its daemon running (idle; `echo quit
| CUDA_MPS_PIPE_DIRECTORY=<its folder>/pipe nvidia-cuda-mps-control` ends it; the folder is
named in the sweep's log).

On Ray (`executor.actors` above the cluster's GPUs) the engines sharing a node's GPUs join one
daemon of the sweep's on that node (`join_node_daemon`, `leave_node_daemon`): the first to
start starts it, the last to close tells it to quit; it sees every GPU of the node, so each
engine's Ray-given CUDA_VISIBLE_DEVICES names its GPU under it.

Under MPS a fatal fault of one client (an illegal memory access) ends the work of every client
on that GPU: the processes executor then starts new workers for the chunks it interrupted
(`process_executor`), and nothing is recorded for their interrupted episodes
(`interface.device_failure`).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

from vabench import switches

log = logging.getLogger(__name__)

CONTROL = "nvidia-cuda-mps-control"
PIPE_VARIABLE = "CUDA_MPS_PIPE_DIRECTORY"
LOG_VARIABLE = "CUDA_MPS_LOG_DIRECTORY"
ENGINES_PER_GPU = 4
"""Engine processes per GPU under MPS with `executor: auto` (4 measured best; 8, each with
fewer cores for its embedded server, were slower)."""
PRIORITY_VARIABLE = "CUDA_MPS_CLIENT_PRIORITY"
"""A client's priority under MPS, read when the process makes its CUDA context: "0" normal (the
default), "1" below normal (NVIDIA's MPS documentation, "CUDA_MPS_CLIENT_PRIORITY"): the GPU
runs a normal client's kernels ahead of those waiting from below-normal ones. The processes
executor puts every engine process below normal but the critical path's
(`engine_env.critical_path_environment`): alone in their process at the default priority,
the basket's decisions waited behind the other processes' kernels (docs/PERFORMANCE.md,
"Critical path: the basket")."""
NORMAL, BELOW_NORMAL = "0", "1"
DEFAULT_PIPE = Path("/tmp/nvidia-mps")
"""Where a daemon started without CUDA_MPS_PIPE_DIRECTORY listens (the machine's own)."""
START_WAIT_S = 10.0
"""How long the daemon may take to open its control pipe after `-d` returns."""
QUIT_WAIT_S = 2.0
"""How long `_quit` waits for `quit` to return (at once where no client is left)."""


class MpsUnavailable(RuntimeError):
    """The MPS daemon could not be started (the message says why)."""


def control_program() -> str | None:
    """The MPS control program on PATH (NVIDIA's driver installs it), or None."""
    return shutil.which(CONTROL)


@contextlib.contextmanager
def private_daemon(environ: Mapping[str, str] = os.environ) -> Iterator[dict[str, str]]:
    """An MPS daemon for the duration of the block; yields the variables that make a process
    its client (empty when the user's daemon is used). Raises `MpsUnavailable`."""
    if environ.get(PIPE_VARIABLE):
        log.info("CUDA MPS: the daemon of %s=%s", PIPE_VARIABLE, environ[PIPE_VARIABLE])
        yield {}
        return
    if (DEFAULT_PIPE / "control").exists():  # a daemon of the machine's, on the default pipe
        log.info("CUDA MPS: the daemon of %s", DEFAULT_PIPE)
        yield {}
        return
    program = _program()
    folder = Path(tempfile.mkdtemp(prefix="vabench-mps-"))
    env = {PIPE_VARIABLE: str(folder / "pipe"), LOG_VARIABLE: str(folder / "log")}
    full = {**environ, **env}
    try:
        _start(program, full)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    log.info("CUDA MPS: a daemon of the sweep's own (%s=%s)", PIPE_VARIABLE, env[PIPE_VARIABLE])
    try:
        yield env
    finally:
        _quit(program, full)
        shutil.rmtree(folder, ignore_errors=True)


NODE_RANKED = switches.variable("ray_mps_ranked")
"""Set beside `NODE_SWEEP` where the sweep has a critical path (the basket) run by engines
that share GPUs: each GPU's first engine to join is a normal MPS client and the others below
normal (`join_node_daemon`), and the driver gives the critical path's chunks to the normal
ones (`sweep.placement.choose_engine`), as the processes executor does with its critical process."""

NODE_SWEEP = switches.variable("ray_mps")
"""Set by the Ray driver in the environment of engines that share GPUs (`executor.actors` above
the GPUs, `executor.mps` auto): the sweep's id, under which each engine joins its node's
daemon (`join_node_daemon`) before it makes its CUDA context."""


def node_folder(sweep: str) -> Path:
    """Where a Ray sweep's daemon of this node keeps its pipe, log and members."""
    return Path(tempfile.gettempdir()) / f"vabench-mps-ray-{sweep}"


def join_node_daemon(
    sweep: str,
    member: str,
    environ: Mapping[str, str] = os.environ,
    ranked: bool = False,
    gpu: str | None = None,
) -> dict[str, str]:
    """The variables that make this process a client of the MPS daemon of Ray sweep `sweep` on
    this node: the first engine of the sweep on the node starts it, the others find it (a file
    lock orders them), and each is listed as a member ("<host>-<pid>") until
    `leave_node_daemon`. The daemon sees every GPU of the node (CUDA_VISIBLE_DEVICES dropped),
    so a client's Ray-given CUDA_VISIBLE_DEVICES names the same GPU under it. A daemon the user
    runs is used as it is (empty variables, as `private_daemon`). Members whose process is gone
    (an engine killed, a sweep interrupted) are dropped as others join or leave: a daemon whose
    members are all gone is told to quit, this sweep's (then started again) and earlier
    sweeps' alike. `ranked`: the variables also give this process its MPS priority
    (`PRIORITY_VARIABLE`): normal for the first living member on its GPU (`gpu`: Ray's GPU ids
    of the engine; else its CUDA_VISIBLE_DEVICES), below normal for the others (see
    `NODE_RANKED`). Raises `MpsUnavailable`."""
    if environ.get(PIPE_VARIABLE) or (DEFAULT_PIPE / "control").exists():
        if ranked:
            log.info("CUDA MPS: the user's daemon: every engine at its own priority (not ranked)")
        return {}
    program = _program()
    _reap_abandoned(sweep, program, environ)
    folder = node_folder(sweep)
    folder.mkdir(exist_ok=True)
    env = {PIPE_VARIABLE: str(folder / "pipe"), LOG_VARIABLE: str(folder / "log")}
    with _locked(folder):
        members = _living_members(folder)
        if not members and (folder / "pipe" / "control").exists():
            _retire(folder, program, environ)  # left by engines all gone: perhaps dead itself
        if not (folder / "pipe" / "control").exists():
            daemon_env = {k: v for k, v in environ.items() if k != "CUDA_VISIBLE_DEVICES"}
            _start(program, {**daemon_env, **env})
            log.info("CUDA MPS: this node's daemon of the sweep (%s)", env[PIPE_VARIABLE])
        _write_members(folder, [*members, member])
        if ranked:
            on = gpu if gpu is not None else environ.get("CUDA_VISIBLE_DEVICES", "")
            env[PRIORITY_VARIABLE] = _take_lead(folder, member, on, [*members, member])
    return env


def _take_lead(folder: Path, member: str, gpu: str, living: list[str]) -> str:
    """`member`'s MPS priority on `gpu`: normal where no living member leads that GPU (it then
    leads it), else below normal. The leads ("<gpu> <member>" lines) live beside the members,
    under the same lock (the caller holds it)."""
    path = folder / "leads"
    leads: dict[str, str] = {}
    for line in path.read_text().splitlines() if path.exists() else []:
        lead_gpu, _, lead = line.partition(" ")
        if lead in living:  # a lead that left or died leads no more
            leads[lead_gpu] = lead
    if leads.get(gpu, member) != member:
        return BELOW_NORMAL
    leads[gpu] = member
    path.write_text("".join(f"{g} {m}\n" for g, m in sorted(leads.items())))
    return NORMAL


def leave_node_daemon(sweep: str, member: str, environ: Mapping[str, str] = os.environ) -> None:
    """`member` leaves the node's daemon of `sweep`; the last living member tells it to quit and
    removes its folder. Engines that all die without leaving keep it up (idle) until an engine
    of a later sweep joins on this node, or `echo quit | CUDA_MPS_PIPE_DIRECTORY=<folder>/pipe
    nvidia-cuda-mps-control` ends it."""
    folder = node_folder(sweep)
    if not (folder / "members").exists():
        return
    with _locked(folder):
        members = [m for m in _living_members(folder) if m != member]
        _write_members(folder, members)
        if not members:
            _retire(folder, control_program(), environ)


def _member_alive(member: str) -> bool:
    """Whether the process of a member "<host>-<pid>" of this node still runs."""
    try:
        os.kill(int(member.rsplit("-", 1)[-1]), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, ValueError):
        return True  # another user's process, or a name not of this form: kept
    return True


def _living_members(folder: Path) -> list[str]:
    path = folder / "members"
    listed = path.read_text().split() if path.exists() else []
    return [m for m in listed if _member_alive(m)]


def _write_members(folder: Path, members: list[str]) -> None:
    (folder / "members").write_text("".join(m + "\n" for m in members))


def _retire(folder: Path, program: str | None, environ: Mapping[str, str]) -> None:
    """Tell a node daemon to quit and remove what it kept (the caller holds its lock)."""
    if program is not None and (folder / "pipe" / "control").exists():
        _quit(program, {**environ, PIPE_VARIABLE: str(folder / "pipe")})
    for part in ("pipe", "log", "members", "leads"):
        path = folder / part
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _reap_abandoned(sweep: str, program: str, environ: Mapping[str, str]) -> None:
    """Earlier sweeps' daemons on this node whose engines are all gone: told to quit (one MPS
    server runs a GPU at a time). A folder another process holds locked is left alone."""
    for folder in Path(tempfile.gettempdir()).glob("vabench-mps-ray-*"):
        if folder == node_folder(sweep) or not folder.is_dir():
            continue
        with _locked(folder, wait=False) as held:
            if held and not _living_members(folder):
                log.info("CUDA MPS: an earlier sweep's daemon left on this node (%s)", folder)
                _retire(folder, program, environ)


@contextlib.contextmanager
def _locked(folder: Path, wait: bool = True) -> Iterator[bool]:
    """Within: True while this process holds the exclusive lock of `folder` (between the
    processes of this node); False at once where another holds it and not `wait`."""
    with open(folder / "lock", "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _program() -> str:
    program = control_program()
    if program is None:
        raise MpsUnavailable(f"{CONTROL} is not on PATH")
    return program


def _start(program: str, env: Mapping[str, str]) -> None:
    """Start a daemon with `env` (its pipe and log folders made) and wait for its control pipe;
    a daemon that may have started is told to quit on any failure (Ctrl-C included)."""
    pipe = Path(env[PIPE_VARIABLE])
    pipe.mkdir(exist_ok=True)
    Path(env[LOG_VARIABLE]).mkdir(exist_ok=True)
    try:
        started = subprocess.run(
            [program, "-d"], env=dict(env), capture_output=True, text=True, timeout=30
        )
    except (OSError, subprocess.TimeoutExpired) as err:
        raise MpsUnavailable(f"`{CONTROL} -d` failed: {err}") from err
    if started.returncode != 0:
        said = (started.stderr or started.stdout).strip()
        raise MpsUnavailable(f"`{CONTROL} -d` exited {started.returncode}: {said}")
    try:
        _wait_for_control(pipe)
    except BaseException:
        _quit(program, env)
        raise


def client_devices(gpus: tuple[str, ...]) -> tuple[dict[str, str], tuple[str, ...]]:
    """How the clients of a daemon the sweep started name their GPUs: the daemon inherits the
    sweep's CUDA_VISIBLE_DEVICES and numbers the devices it sees 0..n-1 for its clients (NVIDIA's
    MPS documentation: a client naming them by the host's ids fails). Returns the variables for
    every worker (one GPU: "0") and the ids to deal over the workers (several: 0..n-1)."""
    if len(gpus) == 1:
        return {"CUDA_VISIBLE_DEVICES": "0"}, gpus
    return {}, tuple(str(i) for i in range(len(gpus)))


def _wait_for_control(pipe: Path) -> None:
    deadline = time.monotonic() + START_WAIT_S
    while not (pipe / "control").exists():
        if time.monotonic() > deadline:
            raise MpsUnavailable(
                f"the daemon opened no control pipe in {pipe} within {START_WAIT_S:.0f} s"
            )
        time.sleep(0.05)


def _quit(program: str, env: Mapping[str, str]) -> None:
    """Tell the daemon to quit, without waiting for it to end: it ends once its last client is
    gone, and the caller is often one (a Ray engine leaving its node's daemon last, its CUDA
    context alive until the process exits). `quit` does not return before the daemon ends, so
    waiting for it held every such engine's close for the full 30 s the call was allowed, and
    each Ray sweep that shared GPUs with it ("the daemon was not told to quit ... timed out
    after 30 seconds" at the end of every count). The
    control program runs in a session of its own, so it delivers the command whatever happens to
    this process; a quick answer (no clients left) is still read and logged."""
    try:
        proc = subprocess.Popen(
            [program],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=dict(env),
            text=True,
            start_new_session=True,
        )
    except OSError as err:
        log.warning("CUDA MPS: the daemon was not told to quit: %s", err)
        return
    try:
        _, said = proc.communicate("quit\n", timeout=QUIT_WAIT_S)
    except subprocess.TimeoutExpired:
        log.info("CUDA MPS: the daemon was told to quit; it ends with its last client")
        threading.Thread(target=_reap, args=(proc,), daemon=True).start()
        return
    if proc.returncode != 0:
        log.warning("CUDA MPS: `quit` exited %d: %s", proc.returncode, (said or "").strip())
    else:
        log.info("CUDA MPS: the sweep's daemon quit")


def _reap(proc: subprocess.Popen[str]) -> None:
    """Wait for a `quit` left running (no zombie, its pipes closed, while this process lives)."""
    with contextlib.suppress(Exception):
        proc.communicate()
