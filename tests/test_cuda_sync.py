"""Waiting for the GPU blocks instead of spinning (vabench.sim_mjx.warp.cuda_sync): the flag goes to
every GPU's primary context through the driver API, a refusal is reported, the variable is
checked, and a machine without a driver just says so. The driver is a stand-in here (CI has no
GPU); the effect on a GPU host is measured by the runbook (docs/PERFORMANCE.md)."""

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
