"""A world whose physics diverges is the simulator's failure, never the model's: the acting
slot's result carries an infrastructure error (the sweep re-runs the episode, FACTS: "failed-
for-infrastructure episodes re-run"), its neighbours go on untouched.

On a GPU a diverged world carries NaN into its pose (seen once in 2,160 episodes on an H200,
2026-11-29: the episode ended as a harness error on a non-finite observation); C MuJoCo resets
it to the model's default pose instead and counts a warning, which the C backend reads. The
Warp backend's case is in test_warp_batch.py.
"""

from __future__ import annotations

import numpy as np

from vabench.sim_mjx.cpu import CpuBatch
from vabench.sim_mjx.interface import DIVERGED

DOWN = {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 20}


def _blown_up(batch, slot: int, qvel: float) -> None:
    """Give `slot` a velocity no physics can integrate (C MuJoCo's limit is 1e10)."""
    state = batch.get_state([slot])
    state["qvel"][:] = qvel
    batch.set_state([slot], state, batch.variant()[[slot]])


def test_c_mujoco_resetting_a_world_is_an_infrastructure_error(probe_task, probe_model):
    batch = CpuBatch(probe_model, 2)
    q = probe_task.initial_qpos(probe_model, 0)
    batch.reset([0, 1], np.broadcast_to(q, (2, probe_model.nq)), settle_steps=10)
    _blown_up(batch, 0, 1e12)
    fine, blown = batch.step([DOWN, DOWN])[::-1]
    assert blown is not None and blown.executed and blown.infrastructure_error == DIVERGED
    assert fine is not None and fine.executed and fine.infrastructure_error is None
    assert np.isfinite(batch.qpos()[0]).all()  # C MuJoCo's reset: finite, and wrong
    # the next action of the reset world is judged by its own physics again
    again = batch.step([DOWN, None])[0]
    assert again is not None and again.infrastructure_error is None


def test_every_diverging_slot_is_caught_each_time(probe_task, probe_model):
    """C MuJoCo's reset zeroes its warning counters and counts one: two slots diverging in one
    step (one MjData serves every slot of a model), and the same slot diverging again later,
    are each an infrastructure error."""
    batch = CpuBatch(probe_model, 3)
    q = probe_task.initial_qpos(probe_model, 0)
    batch.reset([0, 1, 2], np.broadcast_to(q, (3, probe_model.nq)), settle_steps=10)
    _blown_up(batch, 0, 1e12)
    _blown_up(batch, 2, 1e12)
    errors = [r.infrastructure_error for r in batch.step([DOWN, DOWN, DOWN])]
    assert errors == [DIVERGED, None, DIVERGED]
    _blown_up(batch, 0, 1e12)  # again, without a reset in between
    errors = [r.infrastructure_error if r else None for r in batch.step([DOWN, DOWN, None])]
    assert errors == [DIVERGED, None, None]


def test_a_non_finite_pose_is_an_infrastructure_error(probe_task, probe_model):
    """The check every backend shares: a pose that is not finite after the action."""
    batch = CpuBatch(probe_model, 2)
    q = probe_task.initial_qpos(probe_model, 0)
    batch.reset([0, 1], np.broadcast_to(q, (2, probe_model.nq)), settle_steps=10)
    assert not batch._diverged([0, 1]).any()
    batch._state[1, 1] = np.nan  # qpos[0] of slot 1 (the full-physics layout: time, qpos, ...)
    assert batch._diverged([0, 1]).tolist() == [False, True]
    assert batch._diverged([]).shape == (0,)


def test_a_world_c_mujoco_reset_while_settling_fails_its_reset(probe_task, probe_model):
    """Settling from a pose C MuJoCo cannot integrate: it resets the world to the model's
    default pose, which then settles finite and still; the batch says so
    (`diverged_since_written`), a new reset clears it, and the task batch's reset gate counts
    it a non-finite settle (deterministic on C MuJoCo: `reset_failed`, never a re-run)."""
    batch = CpuBatch(probe_model, 2)
    q = np.array(probe_task.initial_qpos(probe_model, 0), float)
    bad = q.copy()
    bad[np.flatnonzero(np.abs(q) > 0)[-1]] = 1e12  # far beyond C MuJoCo's 1e10
    batch.reset([0, 1], np.stack([bad, q]), settle_steps=10)
    assert np.isfinite(batch.qpos()).all()  # reset by C MuJoCo: nothing non-finite to see
    assert batch.diverged_since_written([0, 1]).tolist() == [True, False]
    assert batch.failures() == [None, None]
    batch.reset([0], q[None], settle_steps=10)
    assert batch.diverged_since_written([0, 1]).tolist() == [False, False]


def test_the_reset_gate_fails_a_world_c_mujoco_reset(probe_task, monkeypatch, tmp_path):
    from vabench.sim_mjx.reset_cache import SettledCache
    from vabench.tasks.task_batch import TaskBatch

    tb = TaskBatch(probe_task, 2, backend="c", cache=SettledCache(tmp_path))
    monkeypatch.setattr(
        tb.batch, "diverged_since_written", lambda slots: np.array([s == 0 for s in slots])
    )
    seed = 0
    report = tb.reset([0, 1], [seed, seed + 1])
    assert not report[0].ok and report[0].reason == "non-finite pose after settling"
    assert report[0].infrastructure_error is None  # deterministic: not an infrastructure error
    assert report[1].ok
