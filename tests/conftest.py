"""Shared fixtures: one compiled batch per model shape for the whole session (MJX compiles are
the slow part of the suite on a CPU), a repo-local persistent compilation cache so that
subprocesses (the CLI tests) reuse what this process compiled, and the cores the sweep's
automatic choices size for."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault(
    "VABENCH_JAX_CACHE", str(Path(__file__).resolve().parents[1] / ".cache" / "jax")
)
os.environ.setdefault(
    "VABENCH_STATE_CACHE", str(Path(__file__).resolve().parents[1] / ".cache" / "settled")
)
# `executor: auto` sizes itself from the cores (vabench.sweep.choices): the suite's sweeps run
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


@pytest.fixture
def home_batch(mjx_batch, probe_task, probe_model):
    """The 18-slot MJX batch with every slot reset to seed 0 of probe_cube at home."""
    import numpy as np

    q = probe_task.initial_qpos(probe_model, 0)
    mjx_batch.reset(range(N_SLOTS), np.broadcast_to(q, (N_SLOTS, probe_model.nq)), settle_steps=25)
    return mjx_batch


@pytest.fixture(autouse=True)
def _own_pace_file(tmp_path, monkeypatch):
    """Each test's sweeps keep their measured pace in a file of their own, never the user's
    (`vabench.sweep.pace.pace_file`), so a dry run's estimate depends on the test alone."""
    from vabench.sweep import pace

    path = tmp_path / "pace_cache" / "pace.json"
    monkeypatch.setattr(pace, "pace_file", lambda: path)
