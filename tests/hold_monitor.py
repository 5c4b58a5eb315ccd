"""Watching grasps during expert runs: does a held object stay in the fingers, and does any
object move faster than the robot could move it (a launch)?

`HoldMonitor(tb)` wraps `tb.step` of a `TaskBatch` (the runner is not touched). When an arm's
gripper goes from open to closed, every object touching that gripper after the closing action
is "held"; the point of the object that sat at the finger centre (GC, the pads' midpoint) at
that moment is remembered in the object's frame. Until the action that opens that gripper, the
monitor measures how far that point is from GC and how fast the object moves:

- on C MuJoCo at every physics substep (the batch's `capture_every` = 1 records each substep's
  qpos; capture reads state and changes no result), speeds by finite differences;
- on the other backends after every action, speeds from the state's qvel.

It also records the fastest any free object moved during the whole episode (C only), so that a
launched object that nobody holds is seen too. Everything is computed from qpos with C MuJoCo's
kinematics on a scratch MjData, independently of the backend under test.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from vabench.tasks.task_batch import TaskBatch


@dataclass
class Hold:
    """One arm's grasp of one object in one slot, from closing to release."""

    slot: int
    arm: str
    obj: str
    local: np.ndarray  # the grasped point in the object's frame
    start_step: int
    end_step: int | None = None
    worst_mm: float = 0.0  # largest distance of the grasped point from GC
    worst_speed: float = 0.0  # largest linear speed of the object, m/s
    samples: int = 0
    per_step: dict[int, float] = field(default_factory=dict)  # action -> largest distance, mm

    def describe(self, seed: int | None = None) -> str:
        return (
            f"seed {seed} {self.arm} arm holding {self.obj} (steps {self.start_step}-"
            f"{self.end_step}): grasped point up to {self.worst_mm:.1f} mm from GC, "
            f"speed up to {self.worst_speed:.2f} m/s"
        )


@dataclass
class SlotTrace:
    holds: list[Hold] = field(default_factory=list)
    max_speed: dict[str, float] = field(default_factory=dict)  # every free object, C only
    steps: int = 0


def _subtree(model: mujoco.MjModel, body: str) -> np.ndarray:
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    inside = np.zeros(model.nbody, bool)
    inside[bid] = True
    for b in range(bid + 1, model.nbody):
        inside[b] |= inside[model.body_parentid[b]]
    return inside


class HoldMonitor:
    def __init__(self, tb: TaskBatch):
        self.tb = tb
        self.models = tb.models
        self.datas = [mujoco.MjData(m) for m in self.models]
        m = self.models[0]
        self.arms = tuple(tb.batch.arms)
        self.objects = dict(tb.ix.adr)  # name -> qpos address
        self.pads = {
            arm: [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{arm}_pad_{k}") for k in "ab"]
            for arm in self.arms
        }
        self.body = {o: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, o) for o in self.objects}
        self.gripper_bodies = {arm: _subtree(m, f"{arm}_gripper") for arm in self.arms}
        self.object_bodies = {o: _subtree(m, o) for o in self.objects}
        self.dt = m.opt.timestep
        self.per_substep = hasattr(tb.batch, "capture_every")
        if self.per_substep:
            tb.batch.capture_every = 1
            tb.batch.captured.clear()
        self.traces: dict[int, SlotTrace] = {}
        self.active: dict[int, list[Hold]] = {}
        self._step = tb.step
        tb.step = self.step  # type: ignore[method-assign]

    def close(self) -> None:
        self.tb.step = self._step  # type: ignore[method-assign]
        if self.per_substep:
            self.tb.batch.capture_every = 0
            self.tb.batch.captured.clear()

    # -- geometry ---------------------------------------------------------------------------
    def _kin(self, slot: int, qpos: np.ndarray) -> mujoco.MjData:
        v = int(self.tb.batch.variant()[slot])
        d = self.datas[v]
        d.qpos[:] = qpos
        mujoco.mj_kinematics(self.models[v], d)
        return d

    def _gc(self, d: mujoco.MjData, arm: str) -> np.ndarray:
        a, b = self.pads[arm]
        return 0.5 * (d.site_xpos[a] + d.site_xpos[b])

    def _touching(self, slot: int, qpos: np.ndarray, arm: str) -> list[str]:
        v = int(self.tb.batch.variant()[slot])
        m, d = self.models[v], self.datas[v]
        d.qpos[:] = qpos
        mujoco.mj_forward(m, d)
        grip = self.gripper_bodies[arm]
        found = []
        for i in range(d.ncon):
            c = d.contact[i]
            if c.dist > 0:
                continue
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            for obj, inside in self.object_bodies.items():
                pair = (grip[b1] and inside[b2]) or (grip[b2] and inside[b1])
                if pair and obj not in found:
                    found.append(obj)
        return found

    def _measure(self, slot: int, qpos: np.ndarray, speeds: dict[str, float]) -> None:
        holds = self.active.get(slot, [])
        trace = self.traces[slot]
        for obj, s in speeds.items():
            trace.max_speed[obj] = max(trace.max_speed.get(obj, 0.0), s)
        if not holds:
            return
        d = self._kin(slot, qpos)
        for h in holds:
            b = self.body[h.obj]
            point = d.xpos[b] + d.xmat[b].reshape(3, 3) @ h.local
            mm = 1000.0 * float(np.linalg.norm(point - self._gc(d, h.arm)))
            h.worst_mm = max(h.worst_mm, mm)
            h.per_step[trace.steps] = max(h.per_step.get(trace.steps, 0.0), mm)
            h.worst_speed = max(h.worst_speed, speeds.get(h.obj, 0.0))
            h.samples += 1

    # -- the wrapped step -------------------------------------------------------------------
    def step(self, actions: Sequence[Any]) -> Any:
        batch = self.tb.batch
        n = batch.n_slots
        acting = [s for s, a in enumerate(list(actions) + [None] * n) if a is not None][:n]
        for s in acting:
            if s not in self.traces or (self.tb.steps[s] == 0 and self.traces[s].steps > 0):
                self.traces[s] = SlotTrace()  # a new episode in this slot
                self.active[s] = []
        open_before, qpos_before = batch.grip_open(), batch.qpos()
        out = self._step(actions)
        open_after, qpos_after = batch.grip_open(), batch.qpos()
        qvel = None if self.per_substep else batch.get_state(acting)["qvel"]
        for row, s in enumerate(acting):
            trace = self.traces[s]
            trace.steps += 1
            for i, arm in enumerate(self.arms):  # released: the hold ends before this action
                if not open_before[s, i] and open_after[s, i]:
                    for h in [h for h in self.active[s] if h.arm == arm]:
                        h.end_step = trace.steps - 1
                        self.active[s].remove(h)
            if self.per_substep:
                prev = qpos_before[s]
                for q in batch.captured.pop(s, []):
                    speeds = {
                        o: float(np.linalg.norm(q[a : a + 3] - prev[a : a + 3])) / self.dt
                        for o, a in self.objects.items()
                    }
                    self._measure(s, q, speeds)
                    prev = q
            else:
                m = self.models[int(batch.variant()[s])]
                speeds = {}
                for o in self.objects:
                    dof = m.jnt_dofadr[m.body_jntadr[self.body[o]]]
                    speeds[o] = float(np.linalg.norm(qvel[row][dof : dof + 3]))
                self._measure(s, qpos_after[s], speeds)
            for i, arm in enumerate(self.arms):  # closed: holds start after this action
                if open_before[s, i] and not open_after[s, i]:
                    d = None
                    for obj in self._touching(s, qpos_after[s], arm):
                        d = self._kin(s, qpos_after[s])
                        b = self.body[obj]
                        local = d.xmat[b].reshape(3, 3).T @ (self._gc(d, arm) - d.xpos[b])
                        h = Hold(s, arm, obj, local, trace.steps)
                        trace.holds.append(h)
                        self.active[s].append(h)
        return out


def watch_experts(tb: TaskBatch, seeds: Sequence[int]) -> tuple[list[Any], dict[int, SlotTrace]]:
    """Run the family's expert on `seeds` (slots 0..) under a HoldMonitor; return the
    episodes and each seed's trace."""
    from vabench.tasks.task_batch import run_experts

    mon = HoldMonitor(tb)
    try:
        episodes = run_experts(tb, list(seeds))
    finally:
        mon.close()
    for h in (h for t in mon.traces.values() for h in t.holds):
        if h.end_step is None:
            h.end_step = mon.traces[h.slot].steps
    return episodes, {seeds[s]: mon.traces.get(s, SlotTrace()) for s in range(len(seeds))}
