"""The sweep's host-load lines tell apart a busy event loop, busy batch threads and busy child
processes (vabench/tuning/hostload.py): each case is made for real here and read back from
/proc."""

from __future__ import annotations

import asyncio
import gc
import logging
import os
import subprocess
import sys
import threading
import time

import pytest

from vabench.tuning import hostload
from vabench.tuning.hostload import HostLoad, thread_group

pytestmark = pytest.mark.skipif(not HostLoad.available(), reason="needs Linux's /proc")


def spin(cpu_seconds: float) -> None:
    """Busy for `cpu_seconds` of this thread's CPU time (not wall time: the machine may be
    shared, and the figures checked are CPU)."""
    end = time.thread_time() + cpu_seconds
    while time.thread_time() < end:
        pass


@pytest.mark.parametrize(
    "name, group",
    [
        ("MainThread", "event loop"),
        ("sim-put_everything_in_basket_0", "sim"),
        ("render-lift_pot_0", "render"),
        ("jpeg_3", "jpeg"),
        ("frame-writer", "frame"),
        ("asyncio_7", "asyncio"),
    ],
)
def test_threads_are_grouped_without_their_task_and_index(name, group):
    assert thread_group(name) == group


def test_a_busy_batch_thread_is_counted_to_its_group_not_to_the_loop():
    load = HostLoad(every_s=1.0)
    load.tick()
    spent, stop = threading.Event(), threading.Event()

    def work() -> None:
        spin(0.3)  # CPU time, however long a loaded machine takes to give it
        spent.set()
        stop.wait()

    worker = threading.Thread(target=work, name="sim-lift_pot_0")
    worker.start()
    assert spent.wait(120)
    w = load.tick()  # while it lives: an ended thread's CPU leaves /proc with it
    stop.set()
    worker.join()
    assert w is not None
    # its 0.3 s of CPU (ticks of 10 ms: a little below it at worst), none of it the loop's
    assert w.cores.get("sim", 0.0) * w.seconds > 0.25
    assert w.cores.get("sim", 0.0) > 2 * w.cores.get("event loop", 0.0)
    assert "sim " in w.describe()


def test_child_processes_are_counted_apart():
    load = HostLoad(every_s=1.0)
    load.tick()
    subprocess.run(
        [
            sys.executable,
            "-c",
            "import time\nt=time.process_time()+1\nwhile time.process_time()<t: pass",
        ]
    )
    w = load.tick()
    assert w is not None
    assert w.cores["children"] * w.seconds > 0.8  # its 1 s of CPU
    assert w.cores.get("event loop", 0.0) < w.cores["children"]


def test_a_blocked_loop_shows_late_wake_ups_and_its_own_cpu(caplog):
    load = HostLoad(every_s=0.5)

    async def main() -> None:
        async with hostload.watching(load):
            await asyncio.sleep(0.3)
            spin(0.6)  # the loop itself busy: every callback waits
            await asyncio.sleep(0.8)

    with caplog.at_level(logging.INFO, logger="vabench.tuning.hostload"):
        asyncio.run(main())
    whole = [r.getMessage() for r in caplog.records if "whole run" in r.getMessage()]
    assert len(whole) == 1
    periodic = [r.getMessage() for r in caplog.records if r.getMessage().startswith("host: ")]
    assert periodic, "no line while it ran"
    # the wake-up the spin delayed was at least ~0.5 s late
    late_max_ms = int(whole[0].split("at most ")[1].split(" ms")[0])
    assert late_max_ms >= 400
    whole_window = load.whole_run()
    assert whole_window is not None
    # the loop's thread spent its 0.6 s of CPU (ticks of 10 ms: a little below it at worst)
    assert whole_window.cores["event loop"] * whole_window.seconds > 0.5


def test_off_by_environment(monkeypatch, caplog):
    monkeypatch.setenv(hostload.ENV, "0")

    async def main() -> None:
        async with hostload.watching() as load:
            assert load is None

    with caplog.at_level(logging.INFO, logger="vabench.tuning.hostload"):
        asyncio.run(main())
    assert not caplog.records


def test_the_device_lock_reports_its_holders_and_waiters():
    """The Warp device lock keeps how long it was held (outermost holds only: it is
    re-entrant) and waited for; the host line shows both."""
    from vabench.sim_mjx.warp import device

    lock = device.device_lock("host-load-test")
    load = HostLoad(every_s=1.0)
    load.tick()
    held = threading.Event()

    def holder() -> None:
        with lock, lock:  # re-entered: one hold
            held.set()
            time.sleep(0.6)

    first = threading.Thread(target=holder)
    t0 = time.perf_counter()
    first.start()
    held.wait()
    with lock:  # waits ~0.6 s for the holder
        t1 = time.perf_counter()
    first.join()
    t2 = time.perf_counter()
    w = load.tick()
    assert w is not None
    share, waiting, holds = w.locks["host-load-test"]
    waited_s, held_s, n = device.lock_figures()["host-load-test"]
    assert n == 2
    # the holder's 0.6 s, at least, and no more than the span the waits lay in (each figure
    # is measured inside the span around it here: an order, whatever the machine's load)
    assert 0.4 < waited_s <= t1 - t0
    assert 0.55 <= held_s <= t2 - t0
    # the window's shares are those figures over its seconds (the lock was new at its start)
    assert share * w.seconds == pytest.approx(held_s)
    assert waiting * w.seconds == pytest.approx(waited_s)
    assert holds * w.seconds == pytest.approx(2)
    assert "host-load-test lock held" in w.describe()
    assert not lock._is_owned()


def test_the_garbage_collectors_pauses_are_counted_and_shown(caplog):
    """Full collections stop every Python thread of the process: each is counted with its
    duration, and the whole run's line says so."""
    load = HostLoad(every_s=0.5)

    async def main() -> None:
        async with hostload.watching(load):
            heap = [[i] for i in range(300_000)]  # a heap a full collection must walk
            gc.collect()
            gc.collect()
            await asyncio.sleep(0.6)
            del heap

    with caplog.at_level(logging.INFO, logger="vabench.tuning.hostload"):
        asyncio.run(main())
    whole = load.whole_run()
    assert whole is not None and whole.gc is not None
    assert whole.gc.full >= 2
    assert 0 < whole.gc.max_s <= whole.gc.seconds
    line = next(r.getMessage() for r in caplog.records if "whole run" in r.getMessage())
    assert "garbage collector" in line and "full collections" in line
    # unhooked at the end
    assert not any(getattr(cb, "__self__", None) is load.pauses for cb in gc.callbacks)


def test_the_machines_runnable_threads_show_a_saturated_host():
    """Processes that spin are runnable whether or not they get a core: the probe sees at
    least as many runnable threads as there are spinners (this is what tells a loop that
    waits for a core from one that waits for the interpreter lock)."""
    spinners = (os.cpu_count() or 1) + 2
    code = "import time\nend = time.time() + 1.5\nwhile time.time() < end: pass\n"
    load = HostLoad(every_s=10.0)

    async def main() -> None:
        async with hostload.watching(load):
            procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(spinners)]
            await asyncio.sleep(1.0)
            for p in procs:
                p.wait()

    asyncio.run(main())
    whole = load.whole_run()
    assert whole is not None and whole.runnable_mean is not None
    assert whole.runnable_max >= spinners
    assert f"for {os.cpu_count()} cores" in whole.describe()
