"""Waiting for the GPU blocks instead of spinning (vabench.sim_mjx.warp.cuda_sync): the flag goes to
every GPU's primary context through the driver API, a refusal is reported, the variable is
checked, and a machine without a driver just says so. The driver is a stand-in here (CI has no
GPU); the effect on a GPU host is measured by `benchmarks/gpu_waits.py` (docs/PERFORMANCE.md,
"Engine processes on one GPU")."""

from __future__ import annotations

import ctypes

import pytest

from vabench.sim_mjx.warp import cuda_sync


class FakeDriver:
    """libcuda's four entry points used, recording the flags each device was given."""

    def __init__(self, devices: int, refuse: int | None = None):
        self.devices, self.refuse, self.flags = devices, refuse, {}

    def cuInit(self, flags):
        return 0

    def cuDeviceGetCount(self, ref):
        ref._obj.value = self.devices
        return 0

    def cuDeviceGet(self, ref, ordinal):
        ref._obj.value = 100 + ordinal
        return 0

    def cuDevicePrimaryCtxSetFlags_v2(self, device, flags):
        if device.value == 100 + (self.refuse if self.refuse is not None else -1):
            return 708  # CUDA_ERROR_PRIMARY_CONTEXT_ACTIVE
        self.flags[device.value] = flags
        return 0


@pytest.fixture
def driver(monkeypatch):
    def use(fake):
        monkeypatch.setattr(cuda_sync, "_done", None)
        monkeypatch.setattr(ctypes, "CDLL", lambda name: fake)
        return fake

    return use


def test_every_gpu_gets_blocking_sync(driver, monkeypatch):
    fake = driver(FakeDriver(devices=2))
    monkeypatch.delenv(cuda_sync.SYNC_VARIABLE, raising=False)
    assert "blocking sync on 2 GPU(s)" in cuda_sync.prefer_blocking_sync()
    assert fake.flags == {100: 0x04, 101: 0x04}  # CU_CTX_SCHED_BLOCKING_SYNC
    assert cuda_sync.prefer_blocking_sync() and len(fake.flags) == 2  # once per process


def test_a_refusal_is_reported(driver):
    driver(FakeDriver(devices=2, refuse=1))
    said = cuda_sync.prefer_blocking_sync()
    assert "refused" in said and "GPU 1: CUresult 708" in said


def test_spin_keeps_the_default_and_a_bad_value_names_the_variable(driver, monkeypatch):
    fake = driver(FakeDriver(devices=1))
    monkeypatch.setenv(cuda_sync.SYNC_VARIABLE, "spin")
    assert "default" in cuda_sync.prefer_blocking_sync() and fake.flags == {}
    monkeypatch.setattr(cuda_sync, "_done", None)
    monkeypatch.setenv(cuda_sync.SYNC_VARIABLE, "yield")
    with pytest.raises(ValueError, match="VABENCH_CUDA_SYNC"):
        cuda_sync.prefer_blocking_sync()


def test_no_driver_is_not_an_error(monkeypatch):
    monkeypatch.setattr(cuda_sync, "_done", None)

    def missing(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(ctypes, "CDLL", missing)
    assert cuda_sync.prefer_blocking_sync() == "no CUDA driver here"


class FakeCore:
    """Warp's native event call, recording the flags each event was made with."""

    def __init__(self) -> None:
        self.flags: list[int] = []

    def wp_cuda_event_create(self, context, flags):
        self.flags.append(flags)
        return 1000 + len(self.flags)


class FakeEvent:
    """`wp.Event` as `streams.sleeping_event` calls it."""

    def __init__(self, device, cuda_event=None):
        self.device, self.cuda_event, self.owner = device, cuda_event, cuda_event is None


def test_the_events_a_thread_waits_on_are_made_to_sleep(monkeypatch):
    """`streams.record` makes its events with CU_EVENT_BLOCKING_SYNC (and no timing), owned
    like Warp's own: CUDA's documentation says a thread waiting on an event made without it
    busy-waits, whatever the context's flag. VABENCH_CUDA_SYNC=spin keeps Warp's own events."""
    import types

    from warp._src import context

    from vabench.sim_mjx.warp import streams

    core = FakeCore()
    monkeypatch.setattr(context, "runtime", types.SimpleNamespace(core=core))
    monkeypatch.setattr(streams.wp, "Event", FakeEvent)
    device = types.SimpleNamespace(context=7)
    monkeypatch.delenv(cuda_sync.SYNC_VARIABLE, raising=False)
    event = streams.sleeping_event(device)
    assert core.flags == [0x1 | 0x2]  # CU_EVENT_BLOCKING_SYNC | CU_EVENT_DISABLE_TIMING
    assert event.cuda_event == 1001 and event.owner  # destroyed with the object
    recorded = []
    stream = types.SimpleNamespace(device=device, record_event=lambda e: recorded.append(e) or e)
    assert streams.record(stream) is recorded[0] and core.flags[-1] == 0x3
    monkeypatch.setenv(cuda_sync.SYNC_VARIABLE, "spin")
    plain = streams.sleeping_event(device)
    assert plain.cuda_event is None and len(core.flags) == 2  # Warp's own event


def _cuda() -> bool:
    import warp as wp

    return wp.is_cuda_available()


@pytest.mark.skipif(not _cuda(), reason="event waits are CUDA's (run on the GPU host)")
def test_a_thread_waiting_for_the_gpu_sleeps():
    """A thread waiting (`streams.wait`) on an event `streams.record` made spends a small part
    of the wait on its core (`benchmarks/gpu_waits.py` puts Warp's own events beside it)."""
    import sys
    import time
    from pathlib import Path

    import warp as wp

    from vabench.sim_mjx.warp import streams

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from gpu_waits import _busy

    device = wp.get_device("cuda:0")
    stream = wp.Stream(device)
    out = wp.zeros(1, dtype=float, device=device)
    n = 1 << 20
    for _ in range(6):  # until a launch lasts over 0.1 s
        with wp.ScopedStream(stream):
            wp.launch(_busy, dim=1, inputs=[n], outputs=[out])
        event = streams.record(stream)
        t0, c0 = time.perf_counter(), time.thread_time()
        streams.wait(event)
        wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
        if wall > 0.1:
            break
        n *= 4
    assert wall > 0.1, f"the kernel ran only {wall:.3f} s"
    assert cpu < 0.3 * wall, f"the waiting thread used {cpu:.3f} s of CPU in {wall:.3f} s"
