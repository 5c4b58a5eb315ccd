"""The task that bounds a sweep's wall time gets the GPU first: which task that is, and how the
choice reaches the Warp batch (its CUDA stream's priority is checked on the GPU host, in
tests/test_warp_batch.py)."""

from __future__ import annotations

from vabench.config.schema import SimulatorOptions
from vabench.sim_mjx.backends import Physics
from vabench.sweep.cells import critical_path_tasks, sweep_critical_path


def test_the_longest_budget_is_the_critical_path_only_when_it_stands_out():
    assert critical_path_tasks({"put_everything_in_basket": 250, "a": 50, "b": 50}) == {
        "put_everything_in_basket"
    }
    assert critical_path_tasks({"a": 50, "b": 50}) == set()  # alike: nobody first
    assert critical_path_tasks({"a": 80, "b": 50}) == set()  # not twice as long
    assert critical_path_tasks({"a": 100, "b": 100, "c": 50}) == {"a", "b"}
    assert critical_path_tasks({"only": 250}) == set()
    # against the median of the others, not the largest other (place_cube_on_cube's 200)
    assert critical_path_tasks({"basket": 250, "pile": 200, "a": 50, "b": 50, "c": 100}) == {
        "basket"
    }
    assert critical_path_tasks({}) == set()


def test_only_the_warp_batch_is_asked_for_a_priority():
    options = SimulatorOptions()
    assert options.batch_kwargs(Physics.WARP, critical_path=True)["critical_path"] is True
    assert "critical_path" not in options.batch_kwargs(Physics.WARP)
    for physics in (Physics.C, Physics.MJX_JAX):  # their batches take no such argument
        assert "critical_path" not in options.batch_kwargs(physics, critical_path=True)


def test_the_shipped_config_puts_the_basket_on_the_critical_path():
    """configs/all.yaml's budgets (the basket 250 steps, place_cube_on_cube 200, most 50-100):
    the rule must find the basket there, where it ran ~150 s after everything else (H100,
    2026-11-27), or the executors never give it its own process and priority."""
    from pathlib import Path

    from vabench.config import load_config
    from vabench.sweep.plan import plan

    config = load_config(Path(__file__).parent.parent / "configs" / "all.yaml")
    tasks = {key.task for key in plan(config)}
    assert critical_path_tasks({t: config.budget(t) for t in tasks}) == {"put_everything_in_basket"}


def test_a_worker_keeps_the_critical_path_its_parent_decided_for_the_whole_sweep():
    """A processes worker sees only its chunk's tasks: among place_cube_on_cube's 200 steps and
    others' 50 it would find a critical path of its own. The parent's decision stands, and
    only for the tasks the worker has."""
    chunk = {"place_cube_on_cube": 200, "grasp_single_cube": 50, "lift_pot": 50}
    assert sweep_critical_path(None, chunk) == {"place_cube_on_cube"}  # on its own
    assert sweep_critical_path((), chunk) == set()  # the parent found the basket elsewhere
    assert sweep_critical_path(("put_everything_in_basket",), chunk) == set()
    basket = {"put_everything_in_basket": 250}
    assert sweep_critical_path(None, basket) == set()  # alone, nothing to stand out from
    assert sweep_critical_path(("put_everything_in_basket",), basket) == {
        "put_everything_in_basket"
    }
