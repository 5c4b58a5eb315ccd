"""The sweep's own CUDA MPS daemon (vabench.tuning.mps): started with a private pipe folder, its
clients' variables handed out, told to quit when the block ends (errors too), a start that
fails said in one line, a daemon the user runs left alone. NVIDIA's control program cannot
run here (no driver): a real executable of that name on PATH stands in, answering `-d` by
opening a control pipe in CUDA_MPS_PIPE_DIRECTORY and `quit` on its standard input as the
real one does, and writing what it was asked to a log."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from vabench.tuning import mps

FAKE_CONTROL = """\
#!{python}
import os, sys
log = open(os.environ["FAKE_MPS_LOG"], "a")
pipe = os.environ.get("CUDA_MPS_PIPE_DIRECTORY", "")
if sys.argv[1:] == ["-d"]:
    if os.environ.get("FAKE_MPS_FAIL"):
        print("An instance of this daemon is already running", file=sys.stderr)
        sys.exit(1)
    log.write(f"start {{pipe}}\\n")
    if os.environ.get("CUDA_VISIBLE_DEVICES") is not None:
        log.write(f"visible {{os.environ['CUDA_VISIBLE_DEVICES']}}\\n")
    if not os.environ.get("FAKE_MPS_NO_PIPE"):
        open(os.path.join(pipe, "control"), "w").close()
else:
    log.write(f"{{sys.stdin.read().strip()}} {{pipe}}\\n")
    log.flush()
    release = os.environ.get("FAKE_MPS_QUIT_UNTIL")
    if release:  # as the real one: `quit` returns once the daemon's last client is gone
        import time
        deadline = time.monotonic() + 60
        while not os.path.exists(release) and time.monotonic() < deadline:
            time.sleep(0.05)
"""


@pytest.fixture
def control(tmp_path, monkeypatch):
    """The stand-in control program on PATH; returns its log."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    program = bin_dir / mps.CONTROL
    program.write_text(FAKE_CONTROL.format(python=sys.executable))
    program.chmod(program.stat().st_mode | stat.S_IXUSR)
    log = tmp_path / "mps.log"
    log.touch()
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_MPS_LOG", str(log))
    monkeypatch.delenv(mps.PIPE_VARIABLE, raising=False)
    monkeypatch.setattr(mps, "DEFAULT_PIPE", tmp_path / "no-default-daemon")
    return log


def test_a_private_daemon_for_the_block_then_quit(control):
    assert mps.control_program() is not None
    with mps.private_daemon() as env:
        pipe = Path(env[mps.PIPE_VARIABLE])
        assert (pipe / "control").exists() and Path(env[mps.LOG_VARIABLE]).is_dir()
        assert pipe.parent.name.startswith("vabench-mps-")
        assert control.read_text().splitlines() == [f"start {pipe}"]
    assert control.read_text().splitlines() == [f"start {pipe}", f"quit {pipe}"]
    assert not pipe.parent.exists()  # its folder removed


def test_the_daemon_quits_when_the_block_fails(control):
    with pytest.raises(RuntimeError, match="a worker failed"), mps.private_daemon() as env:
        raise RuntimeError("a worker failed")
    assert control.read_text().splitlines()[-1] == f"quit {env[mps.PIPE_VARIABLE]}"


def test_a_refused_start_is_one_line_naming_why(control, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_FAIL", "1")
    monkeypatch.setattr(tempfile, "tempdir", str(control.parent))  # where it would be left
    refused = pytest.raises(mps.MpsUnavailable, match="exited 1: An instance of this daemon")
    with refused, mps.private_daemon():
        pass
    assert not list(control.parent.glob("vabench-mps-*"))


def test_a_daemon_without_a_control_pipe_is_refused_in_time(control, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_NO_PIPE", "1")
    monkeypatch.setattr(mps, "START_WAIT_S", 0.3)
    with pytest.raises(mps.MpsUnavailable, match="no control pipe"), mps.private_daemon():
        pass
    start, quit_ = control.read_text().splitlines()  # whatever ran is told to quit
    assert start.startswith("start ") and quit_ == f"quit {start.split()[1]}"


def test_the_users_daemon_is_used_as_it_is(control, tmp_path, monkeypatch):
    with mps.private_daemon({mps.PIPE_VARIABLE: "/run/their-mps"}) as env:
        assert env == {}
    machine = tmp_path / "nvidia-mps"  # a daemon of the machine's, on the default pipe
    machine.mkdir()
    (machine / "control").touch()
    monkeypatch.setattr(mps, "DEFAULT_PIPE", machine)
    with mps.private_daemon({}) as env:
        assert env == {}
    assert control.read_text() == ""  # neither started nor quit


@pytest.mark.parametrize(
    ("gpus", "variables", "dealt"),
    [
        (("1",), {"CUDA_VISIBLE_DEVICES": "0"}, ("1",)),  # the daemon's only GPU is its 0
        (("2", "3"), {}, ("0", "1")),
        (("GPU-aa", "GPU-bb", "GPU-cc"), {}, ("0", "1", "2")),
    ],
)
def test_clients_of_the_sweeps_daemon_name_its_gpus_from_0(gpus, variables, dealt):
    """The daemon inherits the sweep's CUDA_VISIBLE_DEVICES and numbers what it sees from 0:
    a worker naming the host's id ("3") under it fails (NVIDIA's MPS documentation)."""
    assert mps.client_devices(gpus) == (variables, dealt)


def test_no_control_program_is_said(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv(mps.PIPE_VARIABLE, raising=False)
    assert mps.control_program() is None
    with pytest.raises(mps.MpsUnavailable, match="not on PATH"), mps.private_daemon():
        pass


# -- a Ray sweep's engines that share GPUs: one daemon a node --------------------------------
@pytest.fixture
def engines():
    """Member names of this node's engines: "<host>-<pid>" of living processes (this one and a
    child), and of one that has ended."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    host = socket.gethostname()
    yield f"{host}-{os.getpid()}", f"{host}-{child.pid}", f"{host}-{ended}"
    child.kill()
    child.wait()


def test_a_nodes_engines_share_one_daemon_the_last_one_quits(
    control, engines, tmp_path, monkeypatch
):
    """The first engine of the sweep on a node starts the daemon (seeing every GPU: Ray's
    CUDA_VISIBLE_DEVICES of that engine is not passed on), the others join it, and it is told
    to quit when the last one leaves; another sweep gets a daemon of its own."""
    one, two, _ = engines
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2")
    first = mps.join_node_daemon("sweep1", one)
    second = mps.join_node_daemon("sweep1", two)
    pipe = mps.node_folder("sweep1") / "pipe"
    assert (
        first
        == second
        == {
            mps.PIPE_VARIABLE: str(pipe),
            mps.LOG_VARIABLE: str(mps.node_folder("sweep1") / "log"),
        }
    )
    assert control.read_text().splitlines() == [f"start {pipe}"]  # once, every GPU visible
    mps.leave_node_daemon("sweep1", one)
    assert control.read_text().splitlines() == [f"start {pipe}"]  # one engine still there
    mps.leave_node_daemon("sweep1", two)
    assert control.read_text().splitlines() == [f"start {pipe}", f"quit {pipe}"]
    assert not pipe.exists() and not (mps.node_folder("sweep1") / "members").exists()
    mps.leave_node_daemon("sweep1", two)  # again: nothing to do
    other = mps.join_node_daemon("sweep2", one)
    assert other[mps.PIPE_VARIABLE] != str(pipe)
    assert control.read_text().splitlines()[-1] == f"start {other[mps.PIPE_VARIABLE]}"


def test_engines_that_died_do_not_keep_a_daemon(control, engines, tmp_path, monkeypatch):
    """A member whose process has ended is dropped: the last living one's leaving quits the
    daemon; a daemon left by engines all gone (this sweep's, or an earlier sweep's on this
    node) is told to quit when an engine joins, and this sweep's is started again."""
    one, two, dead = engines
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    mps.join_node_daemon("sweep1", one)
    mps.join_node_daemon("sweep1", dead)  # (as if it had died after joining)
    pipe = mps.node_folder("sweep1") / "pipe"
    mps.leave_node_daemon("sweep1", one)  # the dead one does not hold it up
    assert control.read_text().splitlines() == [f"start {pipe}", f"quit {pipe}"]

    mps.join_node_daemon("sweep1", dead)  # a sweep whose engines all died: its daemon stays
    assert control.read_text().splitlines()[-1] == f"start {pipe}"
    mps.join_node_daemon("sweep1", one)  # ... until an engine joins: quit, started again
    assert control.read_text().splitlines()[-2:] == [f"quit {pipe}", f"start {pipe}"]
    mps.join_node_daemon("sweep2", two)  # another sweep: sweep1 has a living member, kept
    other = mps.node_folder("sweep2") / "pipe"
    assert control.read_text().splitlines()[-1] == f"start {other}"
    (mps.node_folder("sweep1") / "members").write_text(dead + "\n")  # sweep1 interrupted
    mps.join_node_daemon("sweep3", two)
    assert f"quit {pipe}" == control.read_text().splitlines()[-2]  # reaped
    assert not pipe.exists()


def test_the_last_engine_leaving_does_not_wait_for_the_daemon_to_end(
    control, engines, tmp_path, monkeypatch, caplog
):
    """The last engine to leave is itself a client of the daemon (its CUDA context lives until
    its process ends), and `quit` does not return before the daemon ends: leaving tells the
    daemon to quit and returns, the command still running. Waiting for it held every Ray sweep
    sharing GPUs for 30 s at its end (4 x H200, 2026-11-28)."""
    one, _, _ = engines
    release = tmp_path / "last-client-gone"
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("FAKE_MPS_QUIT_UNTIL", str(release))
    mps.join_node_daemon("sweep1", one)
    pipe = mps.node_folder("sweep1") / "pipe"
    caplog.set_level("INFO", logger=mps.__name__)
    mps.leave_node_daemon("sweep1", one)
    assert control.read_text().splitlines() == [f"start {pipe}", f"quit {pipe}"]  # delivered
    assert not release.exists()  # ... and `quit` still waiting when leaving returned
    assert "told to quit; it ends with its last client" in caplog.text
    assert "not told to quit" not in caplog.text
    assert not (mps.node_folder("sweep1") / "members").exists()
    release.touch()


def test_a_nodes_daemon_that_does_not_start_is_said(control, tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("FAKE_MPS_FAIL", "1")
    with pytest.raises(mps.MpsUnavailable, match="exited 1"):
        mps.join_node_daemon("sweep1", f"node-{os.getpid()}")
    monkeypatch.setenv(mps.PIPE_VARIABLE, "/run/their-mps")  # the user's daemon: used as it is
    assert mps.join_node_daemon("sweep1", f"node-{os.getpid()}") == {}


def test_an_engine_joins_its_nodes_daemon_and_leaves_it(control, tmp_path, monkeypatch):
    """`EngineActor` (without Ray: its two MPS steps): the client variables in its process's
    environment before it makes a CUDA context; where MPS cannot run, a warning and none."""
    import asyncio

    from vabench.sweep.ray_engine import EngineActor

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    engine = EngineActor.__new__(EngineActor)
    engine._mps_member, engine._stack, engine._gpus = f"node-{os.getpid()}", None, None
    monkeypatch.setenv(mps.NODE_SWEEP, "sweep9")
    for name in (mps.PIPE_VARIABLE, mps.LOG_VARIABLE):  # unset, and unset again after the
        monkeypatch.setenv(name, "")  # test (the engine sets them in this process)
        monkeypatch.delenv(name)
    engine._mps_sweep = engine._join_mps()
    pipe = str(mps.node_folder("sweep9") / "pipe")
    assert engine._mps_sweep == "sweep9" and os.environ[mps.PIPE_VARIABLE] == pipe
    asyncio.run(engine.close())
    assert control.read_text().splitlines() == [f"start {pipe}", f"quit {pipe}"]
    monkeypatch.delenv(mps.PIPE_VARIABLE)
    monkeypatch.setenv("FAKE_MPS_FAIL", "1")
    assert engine._join_mps() == ""


def test_a_ranked_sweep_makes_each_gpus_first_engine_its_normal_client(
    control, engines, tmp_path, monkeypatch
):
    """With `ranked` (a sweep with a critical path), the first engine to join on a GPU is a
    normal MPS client and later ones on that GPU below normal; another GPU has its own first.
    A lead that left, or whose process ended while other engines still run, leads no more: the
    next engine to join on its GPU does. The GPU is the one given (Ray's ids), else
    CUDA_VISIBLE_DEVICES."""
    one, two, _ = engines
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    priority = mps.PRIORITY_VARIABLE
    lead = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    doomed = f"{socket.gethostname()}-{lead.pid}"

    def join(member: str, gpu: str, ranked: bool = True) -> str | None:
        env = {**os.environ, "CUDA_VISIBLE_DEVICES": gpu}
        return mps.join_node_daemon("sweep1", member, env, ranked=ranked).get(priority)

    try:
        assert join(doomed, "0") == mps.NORMAL
        assert join(one, "0") == mps.BELOW_NORMAL
        assert join(two, "1") == mps.NORMAL
        assert join(two, "1") == mps.NORMAL  # the lead joining again stays the lead
    finally:
        lead.kill()
        lead.wait()
    starts = control.read_text().count("start ")
    assert join(one, "0") == mps.NORMAL  # GPU 0's lead ended; `two` still runs
    assert control.read_text().count("start ") == starts  # the same daemon, not a new one
    mps.leave_node_daemon("sweep1", two)
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": "7"}
    got = mps.join_node_daemon("sweep1", two, env, ranked=True, gpu="1")
    assert got[priority] == mps.NORMAL  # GPU 1's lead left: the next on it leads
    assert join(one, "1") == mps.BELOW_NORMAL  # ... GPU 1 by Ray's id, not the variable's 7
    assert join(one, "3", ranked=False) is None  # a sweep without a critical path
    mps.leave_node_daemon("sweep1", one)
    mps.leave_node_daemon("sweep1", two)
    assert not (mps.node_folder("sweep1") / "leads").exists()  # retired with the daemon
