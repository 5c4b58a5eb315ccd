"""Shared fixtures: one compiled batch per model shape for the whole session (MJX compiles are
the slow part of the suite on a CPU), a repo-local persistent compilation cache so that
subprocesses (the CLI tests) reuse what this process compiled, and the cores the sweep's
automatic choices size for."""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault(
    "VABENCH_JAX_CACHE", str(Path(__file__).resolve().parents[1] / ".cache" / "jax")
)
os.environ.setdefault(
    "VABENCH_STATE_CACHE", str(Path(__file__).resolve().parents[1] / ".cache" / "settled")
)
# `executor: auto` sizes itself from the cores (vabench.config.choices): the suite's sweeps run
# as on the 2-core CI machine wherever it runs; tests of the other choices set their own.
os.environ.setdefault("VABENCH_CORES", "2")

from vabench.sim_mjx.cpu import CpuBatch
from vabench.sim_mjx.mjx_batch import SimBatch
from vabench.tasks import get_task

N_SLOTS = 18  # 3 axes x 2 signs x 3 magnitudes: one batch runs a whole motion table


@pytest.fixture(scope="session")
def probe_task():
    return get_task("probe_cube")


@pytest.fixture(scope="session")
def probe_model(probe_task):
    return probe_task.build_model()


@pytest.fixture(scope="session")
def mjx_batch(probe_model):
    return SimBatch(probe_model, N_SLOTS)


@pytest.fixture(scope="session")
def mjx_single(probe_model):
    return SimBatch(probe_model, 1)


@pytest.fixture(scope="session")
def cpu_batch(probe_model):
    return CpuBatch(probe_model, N_SLOTS)


# Test files that start Ray clusters (in the test process or in a sweep it starts).
RAY_CLUSTER_FILES = {"test_sweep_ray.py", "test_sweep_cluster.py", "test_ray_limiter.py"}


@pytest.fixture(scope="module", autouse=True)
def one_ray_cluster_at_a_time(request):
    """Under pytest-xdist (`-n 2 --dist loadfile`: the README's test command) two of these
    files could run at once on the 2-core machine, each with clusters sized for the machine:
    each holds this machine-wide lock for its whole module, so they take turns. Other files
    pass through."""
    if request.path.name not in RAY_CLUSTER_FILES:
        yield
        return
    with open(Path(tempfile.gettempdir()) / "vabench-tests-ray.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        yield


# The files that hold most of the suite's time (sweeps and Ray clusters started for real, expert
# rollouts, whole engine episodes), in the order a worker should start them.
LONG_FILES_FIRST = (
    "test_sweep_",
    "test_ray_",
    "test_tasks.py",
    "test_family_",
    "test_engine_",
    "test_render_warp.py",
    "test_warp_batch.py",
    "test_gateway_litellm.py",
)


def _long_first(item: pytest.Item) -> int:
    name = item.path.name
    return next((i for i, p in enumerate(LONG_FILES_FIRST) if name.startswith(p)), 99)


def pytest_collection_modifyitems(items):
    """Under pytest-xdist (`--dist loadfile --no-loadscope-reorder`, the README's command) each
    worker takes the next file when it is free: the long files go first, so that short ones
    fill in at the end instead of one worker running a long file while the other idles. A run
    in one process keeps the files' order."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        items.sort(key=_long_first)  # stable: each file's tests keep their order


@pytest.fixture(autouse=True)
def _endpoint_check_only_where_tested(request, monkeypatch):
    """The sweep's first step tries each model's endpoint once (vabench.check). Tests whose
    subject is something else (a fault-injecting server, a rerun, a limit) call the sweep as
    `--no-check` would; the tests of the check itself carry `@pytest.mark.endpoint_check`."""
    if request.node.get_closest_marker("endpoint_check") is None:
        import vabench.sweep.__main__ as sweep_main

        monkeypatch.setattr(sweep_main, "_check_endpoints", lambda config, keys: 0)


@pytest.fixture(autouse=True)
def _own_pace_file(tmp_path, monkeypatch):
    """Each test's sweeps and checks keep their measured pace and latencies in files of their
    own, never the user's (`vabench.check.pace.pace_file`, `vabench.check.latency.latency_file`),
    so a dry run's estimate depends on the test alone."""
    from vabench.check import latency, pace

    path = tmp_path / "pace_cache" / "pace.json"
    monkeypatch.setattr(pace, "pace_file", lambda: path)
    monkeypatch.setattr(latency, "latency_file", lambda: path.with_name("check_latency.json"))


@pytest.fixture(autouse=True)
def _switches_stay_in_their_test():
    """A sweep run in the test's process sets its config's switches in this process's
    environment (`vabench.switches.apply`, for the processes it starts): put the `VABENCH_*`
    variables back as they were, so that no later test runs on another test's switches."""
    before = {k: v for k, v in os.environ.items() if k.startswith("VABENCH_")}
    yield
    for k in [k for k in os.environ if k.startswith("VABENCH_") and k not in before]:
        del os.environ[k]
    os.environ.update(before)
