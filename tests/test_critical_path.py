"""The task that bounds a sweep's wall time gets the GPU first: which task that is, and how the
choice reaches the Warp batch (its CUDA stream's priority is checked on the GPU host, in
tests/test_warp_batch.py)."""

from __future__ import annotations

from vabench.config.schema import SimulatorOptions
from vabench.sim_mjx.backends import Physics
from vabench.sweep.runner import critical_path_tasks


def test_the_longest_budget_is_the_critical_path_only_when_it_stands_out():
    assert critical_path_tasks({"put_everything_in_basket": 250, "a": 50, "b": 50}) == {
        "put_everything_in_basket"
    }
    assert critical_path_tasks({"a": 50, "b": 50}) == set()  # alike: nobody first
    assert critical_path_tasks({"a": 80, "b": 50}) == set()  # not twice as long
    assert critical_path_tasks({"a": 100, "b": 100, "c": 50}) == {"a", "b"}
    assert critical_path_tasks({"only": 250}) == set()
    assert critical_path_tasks({}) == set()


def test_only_the_warp_batch_is_asked_for_a_priority():
    options = SimulatorOptions()
    assert options.batch_kwargs(Physics.WARP, critical_path=True)["critical_path"] is True
    assert "critical_path" not in options.batch_kwargs(Physics.WARP)
    for physics in (Physics.C, Physics.MJX_JAX):  # their batches take no such argument
        assert "critical_path" not in options.batch_kwargs(physics, critical_path=True)
