"""The sweep's host-load lines tell apart a busy event loop, busy batch threads and busy child
processes (vabench/sweep/hostload.py): each case is made for real here and read back from
/proc."""

from __future__ import annotations

import asyncio
import logging
import subprocess
import sys
import threading
import time

import pytest

from vabench.sweep import hostload
from vabench.sweep.hostload import HostLoad, thread_group

pytestmark = pytest.mark.skipif(not HostLoad.available(), reason="needs Linux's /proc")


def spin(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
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
    worker = threading.Thread(target=spin, args=(1.5,), name="sim-lift_pot_0")
    worker.start()
    time.sleep(1.0)
    w = load.tick()  # while it runs: an ended thread's CPU leaves /proc with it
    worker.join()
    assert w is not None
    assert w.cores.get("sim", 0.0) > 0.2
    assert w.cores.get("sim", 0.0) > 2 * w.cores.get("event loop", 0.0)
    assert "sim " in w.describe()


def test_child_processes_are_counted_apart():
    load = HostLoad(every_s=1.0)
    load.tick()
    subprocess.run(
        [sys.executable, "-c", "import time\nt=time.time()+1\nwhile time.time()<t: pass"]
    )
    w = load.tick()
    assert w is not None
    assert w.cores["children"] > 0.2
    assert w.cores.get("event loop", 0.0) < w.cores["children"]


def test_a_blocked_loop_shows_late_wake_ups_and_its_own_cpu(caplog):
    load = HostLoad(every_s=0.5)

    async def main() -> None:
        async with hostload.watching(load):
            await asyncio.sleep(0.3)
            spin(0.6)  # the loop itself busy: every callback waits
            await asyncio.sleep(0.8)

    with caplog.at_level(logging.INFO, logger="vabench.sweep.hostload"):
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
    assert whole_window.cores["event loop"] > 0.2  # 0.6 s of ~1.7 s on the loop's thread


def test_off_by_environment(monkeypatch, caplog):
    monkeypatch.setenv(hostload.ENV, "0")

    async def main() -> None:
        async with hostload.watching() as load:
            assert load is None

    with caplog.at_level(logging.INFO, logger="vabench.sweep.hostload"):
        asyncio.run(main())
    assert not caplog.records
