"""Constructed predicate inputs for task tests: put objects and grippers where a test wants them
and evaluate a family's predicate on that one slot, without physics."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vabench.sim_mjx import scene
from vabench.tasks.base import Evaluation, ObjectIndex, SlotState, Task


class StateBuilder:
    """A mutable one-slot state of a task: initial poses from a seed, then edits."""

    def __init__(self, task: Task, seed: int = 1000):
        self.task = task
        self.model = task.build_model(task.sample(seed).variant)
        self.ix = ObjectIndex.from_model(self.model)
        self.init = task.initial_qpos(self.model, seed)
        self.qpos = self.init.copy()
        n_arms = len(task.arms)
        self.grip_open = np.ones(n_arms, bool)
        self.contacts = np.zeros(max(len(task.contact_pairs), 1), bool)
        self.gc = np.tile([0.28, -0.2, 0.95], (n_arms, 1))
        self.rot = np.tile(np.eye(3), (n_arms, 1, 1))
        self.fingers = np.full((n_arms, 2), 0.045)
        self.latched = np.zeros(len(task.latches), bool)

    def pos(self, name: str) -> np.ndarray:
        a = self.ix.adr[name]
        return self.qpos[a : a + 3]

    def set_pos(self, name: str, pos: Any) -> StateBuilder:
        a = self.ix.adr[name]
        self.qpos[a : a + 3] = pos
        return self

    def move(self, name: str, delta: Any) -> StateBuilder:
        return self.set_pos(name, self.pos(name) + np.asarray(delta, float))

    def set_quat(self, name: str, quat: Any) -> StateBuilder:
        a = self.ix.adr[name]
        self.qpos[a + 3 : a + 7] = np.asarray(quat, float) / np.linalg.norm(quat)
        return self

    def touch(self, a: str, b: str, value: bool = True) -> StateBuilder:
        self.contacts[self.task.contact_pairs.index((a, b))] = value
        return self

    def grip(self, arm: str, open_: bool) -> StateBuilder:
        self.grip_open[self.task.arm(arm)] = open_
        return self

    def latch(self, name: str, value: bool = True) -> StateBuilder:
        self.latched[self.task.latches.index(name)] = value
        return self

    def slot(self) -> SlotState:
        return SlotState(
            qpos=jnp.asarray(self.qpos),
            init_qpos=jnp.asarray(self.init),
            grip_open=jnp.asarray(self.grip_open),
            contacts=jnp.asarray(self.contacts),
            gc=jnp.asarray(self.gc),
            rot=jnp.asarray(self.rot),
            fingers=jnp.asarray(self.fingers),
        )

    def evaluate(self) -> Evaluation:
        ev = jax.jit(lambda s, l: self.task.evaluate(self.ix, s, l))(
            self.slot(), jnp.asarray(self.latched)
        )
        return jax.device_get(ev)


def free_object_names(task: Task) -> list[str]:
    return [n for n, _ in scene.free_objects(task.build_model(0))]
