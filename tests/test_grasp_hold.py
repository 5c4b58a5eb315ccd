"""Grasps hold and nothing is thrown, on C MuJoCo, MJX and MuJoCo Warp.

For every family whose expert grasps, the expert runs on retained seeds under a `HoldMonitor`
(tests/hold_monitor.py): from the action that closes a gripper on an object to the action that
opens it, the point of the object that sat at the finger centre (GC) when the fingers closed
stays within HOLD_MM of GC, and the held object never moves faster than HELD_SPEED; no object
of the scene ever moves faster than LAUNCH_SPEED. On C MuJoCo this is checked at every physics
substep, on MJX after every action. Default run: two retained seeds per family on C, and the
issue's own grasp plus one expert episode on MJX; `-m slow`: every retained seed of every
family on both, and the issue's grasp plus an expert episode on MuJoCo Warp.

The issue's grasp is what a model would try first: the gripper at its home orientation (fingers
closing along world x, whatever the cube's yaw), closed at the cube's centre, lifted 100 mm.
With the scene's earlier line-search budget (ls_iterations 10) C MuJoCo threw the cube out of
the fingers at about 16 m/s on seeds 1000, 1003, 1005, 1006 of grasp_single_cube while MJX
held it; see assets/scene/table.xml for the cause.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.hold_monitor import HoldMonitor, SlotTrace, watch_experts
from vabench.tasks import benchmark_tasks, get_task
from vabench.tasks.manifests import load_manifest
from vabench.tasks.task_batch import TaskBatch

HOLD_MM = 10.0
# The executor moves the gripper at most 100 mm per 0.8 s action along a minimum-jerk profile
# over 0.56 s: 0.34 m/s at its peak, the fastest any held object was seen to move. A thrown
# object leaves at metres per second.
HELD_SPEED = 1.0
# Objects the experts let go of fall a few centimetres (the basket: 0.2 m, 2 m/s); a free fall
# from 0.46 m reaches 3 m/s.
LAUNCH_SPEED = 3.0

NO_GRASP = {"click_bell_right"}  # presses the bell with closed fingers; holds nothing
GRASP_FAMILIES = [t.name for t in benchmark_tasks() if t.name not in NO_GRASP]

ISSUE_SEEDS = [1000, 1003, 1005, 1006]  # grasp_single_cube seeds the issue saw thrown


def _problems(task: str, traces: dict[int, SlotTrace], per_substep: bool) -> list[str]:
    out = []
    for seed, trace in traces.items():
        holds = trace.holds
        if not holds and task not in NO_GRASP:
            out.append(f"{task} seed {seed}: the expert never closed a gripper on an object")
        for h in holds:
            if h.samples == 0:
                continue
            if h.worst_mm > HOLD_MM or h.worst_speed > HELD_SPEED:
                out.append(f"{task}: " + h.describe(seed))
        if per_substep:
            fast = {o: v for o, v in trace.max_speed.items() if v > LAUNCH_SPEED}
            if fast:
                out.append(f"{task} seed {seed}: objects launched (m/s): {fast}")
    return out


def _check_experts(task_name: str, seeds: list[int], backend: str) -> None:
    task = get_task(task_name)
    tb = TaskBatch(task, len(seeds), backend=backend)
    episodes, traces = watch_experts(tb, seeds)
    assert all(ep.success for ep in episodes), [(ep.seed, ep.end) for ep in episodes]
    problems = _problems(task_name, traces, backend == "c")
    assert not problems, problems


@pytest.mark.parametrize("name", GRASP_FAMILIES)
def test_expert_holds_on_c(name):
    _check_experts(name, load_manifest(name)["retained"][:2], "c")


@pytest.mark.slow
@pytest.mark.parametrize("name", GRASP_FAMILIES)
def test_expert_holds_on_c_every_retained_seed(name):
    _check_experts(name, load_manifest(name)["retained"], "c")


@pytest.mark.slow
@pytest.mark.parametrize("name", GRASP_FAMILIES)
def test_expert_holds_on_mjx_every_retained_seed(name):
    _check_experts(name, load_manifest(name)["retained"], "mjx")


# -- the issue's grasp ---------------------------------------------------------------------
def _move(axis: str, mm: float) -> dict:
    return {
        "action": "gripper.move_world",
        "axis": axis,
        "sign": "+" if mm > 0 else "-",
        "distance_mm": round(min(abs(mm), 100.0), 1),
    }


def home_orientation_grasp(tb: TaskBatch, seeds: list[int], obj: str = "cube"):
    """The issue's grasp on slots 0..: GC above the object's centre (x, y, then z), down to it,
    close, lift 100 mm; the gripper keeps its home orientation throughout. Returns the lift's
    outcomes and the monitor's traces (from the close on)."""
    n = len(seeds)
    assert all(r.ok for r in tb.reset(range(n), seeds))
    for hover, order in ((0.08, "xyz"), (0.0, "zxy")):
        for _ in range(12):
            views, actions = tb.views(range(n)), []
            for s in range(n):
                v = views[s]
                err = (v.pos(obj) + [0.0, 0.0, hover] - v.arms["right"].gc) * 1000.0
                axis = next((a for a in order if abs(err["xyz".index(a)]) >= 1.0), None)
                actions.append(None if axis is None else _move(axis, err["xyz".index(axis)]))
            if all(a is None for a in actions):
                break
            tb.step(actions)
    mon = HoldMonitor(tb)
    try:
        tb.step([{"action": "gripper.close"}] * n)
        lifted = tb.step([_move("z", 100.0)] * n)
    finally:
        mon.close()
    return lifted, {seeds[s]: mon.traces[s] for s in range(n)}


def _batch(task_name: str, n: int, backend: str) -> TaskBatch:
    if backend != "warp":
        return TaskBatch(get_task(task_name), n, backend=backend)
    pytest.importorskip("mujoco_warp")
    import warp as wp

    device = "cuda:0" if wp.is_cuda_available() else "cpu"
    return TaskBatch(get_task(task_name), n, backend="mjx", impl="warp", device=device)


# MuJoCo Warp on its CPU device takes 2-3 minutes for the grasp and the expert episode (the
# GPU path runs the same kernels), hence slow: measured on 2026-11-25, grasped point within
# 0.95 mm of GC on seed 1003, expert solved, nothing thrown.
@pytest.mark.parametrize(
    "backend", ["c", *(pytest.param(b, marks=pytest.mark.slow) for b in ("mjx", "warp"))]
)
def test_issue_grasp_holds_the_cube(backend):
    seeds = ISSUE_SEEDS if backend == "c" else ISSUE_SEEDS[1:2]  # MJX: one compile, one seed
    tb = _batch("grasp_single_cube", len(seeds), backend)
    lifted, traces = home_orientation_grasp(tb, seeds)
    problems = _problems("grasp_single_cube", traces, backend == "c")
    assert not problems, problems
    for seed, out in zip(seeds, lifted, strict=True):
        assert out.success, seed  # lifted 100 mm in the fingers
    [hold] = traces[seeds[0]].holds
    assert hold.worst_mm < 3.0  # MJX held it within 1-1.3 mm before the fix, C now as well
    if backend != "c":  # the same batch runs an expert episode too (compiled once)
        episodes, traces = watch_experts(tb, [1000])
        assert episodes[0].success
        assert not _problems("grasp_single_cube", traces, False)


def test_monitor_sees_a_thrown_cube():
    """The monitor itself: a cube given a 16 m/s kick out of a closed grasp is reported."""
    tb = TaskBatch(get_task("grasp_single_cube"), 1, backend="c")
    _, traces = home_orientation_grasp(tb, [1001])
    assert not _problems("grasp_single_cube", traces, True)
    mon = HoldMonitor(tb)
    try:
        mon.traces[0], mon.active[0] = traces[1001], list(traces[1001].holds)
        state = tb.batch.get_state([0])
        adr = tb.ix.adr["cube"]
        m = tb.models[0]
        dof = m.jnt_dofadr[m.body_jntadr[m.body("cube").id]]
        state["qvel"][0, dof : dof + 3] = [-10.0, 12.0, 4.0]
        tb.batch.set_state([0], state, [0])
        tb.step([_move("z", 10.0)])
    finally:
        mon.close()
    problems = _problems("grasp_single_cube", {1001: mon.traces[0]}, True)
    assert any("launched" in p for p in problems) and any("from GC" in p for p in problems)
    gc = tb.views([0])[0].arms["right"].gc
    assert np.linalg.norm(tb.batch.qpos()[0, adr : adr + 3] - gc) > 0.1  # out of the fingers
