"""The task-family interface: objects, a seeded sampler, a jitted predicate, checkpoints, an expert.

A family is one module of `vabench.tasks` exporting `TASK`, an instance of a `Task` subclass.

- `populate(spec, variant)` adds the family's objects (authored in `assets/objects/`) to the
  scene: by default the `objects` of the task's data, in order; `variants` names the object
  model ids (bell 2, pot 2, shoe 10): every variant has the same structure, so all seeds of a
  family share one batch (see `sim_mjx.variants`).
- `sample(seed)` draws the evaluator-only initial object poses and the model id, from the
  paper's ranges (appendix tables tab:seed-spec-*), deterministically from the seed alone (its
  random stream is `rng(seed)`: `seed_stream`, which a held-out variant replaces by its own).
  By default it draws the objects of `on_table` in order (`OnTable`), then the model id
  uniformly when there are several.
- `evaluate(ix, slot, latched)` is the terminal predicate of the paper's table row for one slot,
  pure and jittable (the batch vmaps it): named checks, the latched flags ("was lifted at some
  point", the handover chain, the bell press) updated from the current state, the subgoal flags
  of the ordered checkpoints, and success.
- `checkpoints` are ordered observable subgoals; the last one, "completed", is success itself.
  Progress only moves forward (see `advance_progress`).
- `expert(sample)` is a generator of model-facing actions (`vabench.tasks.expert`): it reads
  evaluator-only state but acts only through the JSON actions the model gets.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx import scene
from vabench.sim_mjx.pytree import PyTree, pytree_dataclass
from vabench.tasks.objects import attach_object

if TYPE_CHECKING:
    from vabench.tasks.expert import ExpertContext

ObjectPoses = dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (pos (3,), quat wxyz (4,))
Script = Iterator[dict[str, Any]]  # an expert: yields actions, receives a View after each

LIFT_M = 0.05  # "lifted > 50 mm" of every grasp and place predicate
TIP_BEYOND_GC = rc.FINGER_A_BOX[0][0] + rc.FINGER_A_BOX[1][0] - rc.PAD_X  # 15 mm


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrix of a wxyz quaternion (normalised first); works on jnp and np arrays."""
    q = q / jnp.linalg.norm(q)
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class OnTable:
    """Where a sampler puts an object resting on the table: its centre at x and y uniform in
    `x` and `y`, `half_h` above the table top, its yaw uniform in `yaw_deg` (None: 0), drawn in
    that order."""

    x: tuple[float, float]
    y: tuple[float, float]
    half_h: float = 0.0
    yaw_deg: tuple[float, float] | None = None

    def sample(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        pos = np.array([rng.uniform(*self.x), rng.uniform(*self.y), rc.TABLE_Z + self.half_h])
        yaw = 0.0 if self.yaw_deg is None else np.radians(rng.uniform(*self.yaw_deg))
        return pos, yaw_quat(yaw)


@dataclass(frozen=True)
class Sample:
    """One seed's evaluator-only initial state."""

    poses: ObjectPoses
    variant: int = 0  # object model id
    params: dict[str, Any] = field(default_factory=dict)  # e.g. {"giver": "right"}


@pytree_dataclass
class SlotState(PyTree):
    """What a predicate reads of one slot (all evaluator-side)."""

    qpos: jax.Array  # (nq,)
    init_qpos: jax.Array  # (nq,) after the reset's settling
    grip_open: jax.Array  # (A,) bool, last aperture command
    contacts: jax.Array  # (P,) bool, the task's watched contact pairs
    gc: jax.Array  # (A, 3) finger midpoint
    rot: jax.Array  # (A, 3, 3) gripper axes (columns rx, ry, rz)
    fingers: jax.Array  # (A, 2) finger openings, m

    def tip(self, arm: int) -> jax.Array:
        """Midpoint of the fingertips (the TCP of contact-style predicates)."""
        return self.gc[arm] + TIP_BEYOND_GC * self.rot[arm][:, 0]


@pytree_dataclass
class Evaluation(PyTree):
    checks: dict[str, jax.Array]  # named sub-checks of the predicate (bool)
    latched: jax.Array  # (L,) bool
    subgoals: jax.Array  # (K - 1,) bool: checkpoint flags before "completed"
    success: jax.Array  # () bool


@dataclass(frozen=True)
class ObjectIndex:
    """qpos addresses of the free objects (static: resolved once from the model)."""

    adr: dict[str, int]

    @staticmethod
    def from_model(model: mujoco.MjModel) -> ObjectIndex:
        return ObjectIndex(dict(scene.free_objects(model)))

    def pos(self, qpos: jax.Array, name: str) -> jax.Array:
        a = self.adr[name]
        return qpos[a : a + 3]

    def quat(self, qpos: jax.Array, name: str) -> jax.Array:
        a = self.adr[name]
        return qpos[a + 3 : a + 7]

    def mat(self, qpos: jax.Array, name: str) -> jax.Array:
        return quat_to_mat(self.quat(qpos, name))

    def lift(self, s: SlotState, name: str) -> jax.Array:
        a = self.adr[name] + 2
        return s.qpos[a] - s.init_qpos[a]

    def displacement(self, s: SlotState, name: str) -> jax.Array:
        a = self.adr[name]
        return jnp.linalg.norm(s.qpos[a : a + 3] - s.init_qpos[a : a + 3])


def advance_progress(progress: jax.Array, subgoals: jax.Array, success: jax.Array) -> jax.Array:
    """Checkpoint progress (number of checkpoints reached) after one step: it advances through
    consecutive subgoals that hold now, never goes back, and equals K exactly on success."""
    k_total = subgoals.shape[0] + 1
    for k in range(subgoals.shape[0]):
        progress = jnp.where((progress == k) & subgoals[k], k + 1, progress)
    progress = jnp.where(success, k_total, jnp.minimum(progress, k_total - 1))
    return progress


@dataclass(frozen=True)
class Task:
    """Base class of a task family (see the module docstring)."""

    name: str
    instruction: str
    arms: tuple[str, ...] = ("right",)
    step_budget: int = 50
    checkpoints: tuple[str, ...] = ("completed",)
    latches: tuple[str, ...] = ()
    contact_pairs: tuple[tuple[str, str], ...] = ()
    variants: tuple[str, ...] = ("default",)
    settle_steps: int = 2000  # reset: settle, then observe (FACTS: 2,000 + 500 steps)
    observe_steps: int = 500
    suite: str = "base"  # "base" | "transfer" | "long_horizon" | "dev" (simulator tests only)
    base_family: str | None = None  # transfer variants: the base family they are held out from
    demonstrations: tuple[str, ...] = ()
    """Families whose demonstration videos the summary of this task is learned from; empty
    means its own (base families) or its base family's summary (transfer variants, which get no
    video: FACTS "Held-out variants reuse the base task's summary"); the basket names the four
    atomic families of FACTS."""
    objects: tuple[tuple[str, str | tuple[str, ...]], ...] = ()
    """(object name, file in `assets/objects/`) that the default `populate` attaches, in order;
    a tuple of files in place of one names the object's file of each model id."""
    on_table: tuple[tuple[str, OnTable], ...] = ()
    """(object name, where it rests) that the default `sample` draws, in order."""
    seed_stream: Callable[[int], np.random.Generator] = np.random.default_rng
    """A seed's random stream (`rng`); a held-out variant draws from its own, so that its seed s
    is another scene than seed s of its base family (`vabench.tasks.heldout`)."""

    @property
    def summary_family(self) -> str:
        """The family whose learned summary this task's episodes read: a transfer variant reads
        its base family's; everything else reads its own (learned from `demo_families`)."""
        return self.base_family or self.name

    @property
    def demo_families(self) -> tuple[str, ...]:
        """The demonstration videos shown when learning this task's summary."""
        return self.demonstrations or (self.summary_family,)

    # -- scene ------------------------------------------------------------------------------
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        """Add the task's objects to the scene spec (by default `objects`, for every variant)."""
        for name, file in self.objects:
            attach_object(spec, file if isinstance(file, str) else file[variant], name)

    def build_model(self, variant: int = 0) -> mujoco.MjModel:
        return scene.build_model(self.arms, lambda spec: self.populate(spec, variant))

    def build_models(self) -> list[mujoco.MjModel]:
        return [self.build_model(v) for v in range(len(self.variants))]

    def sample(self, seed: int) -> Sample:
        """Evaluator-only initial object poses and model id; deterministic in the seed alone."""
        rng = self.rng(seed)
        poses = self.draw(rng)
        variant = int(rng.integers(len(self.variants))) if len(self.variants) > 1 else 0
        return Sample(poses, variant=variant)

    def draw(self, rng: np.random.Generator) -> ObjectPoses:
        """The poses of `on_table`, in order (a family may add objects drawn after them)."""
        return {name: at.sample(rng) for name, at in self.on_table}

    def initial_qpos(self, model: mujoco.MjModel, sample: Sample | int) -> np.ndarray:
        if isinstance(sample, int):
            sample = self.sample(sample)
        qpos = scene.home_qpos(model)
        adr = dict(scene.free_objects(model))
        for name, (pos, quat) in sample.poses.items():
            qpos[adr[name] : adr[name] + 3] = pos
            qpos[adr[name] + 3 : adr[name] + 7] = np.asarray(quat) / np.linalg.norm(quat)
        return qpos

    # -- evaluation -------------------------------------------------------------------------
    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return Evaluation(
            checks={},
            latched=latched,
            subgoals=jnp.zeros(len(self.checkpoints) - 1, bool),
            success=jnp.array(False),
        )

    def contact(self, s: SlotState, a: str, b: str) -> jax.Array:
        """Whether watched pair (a, b) touches now (declared in `contact_pairs`)."""
        try:
            return s.contacts[self.contact_pairs.index((a, b))]
        except ValueError:
            raise KeyError(f"{self.name}: contact pair {(a, b)} is not declared") from None

    def latch(self, latched: jax.Array, name: str) -> jax.Array:
        return latched[self.latches.index(name)]

    def arm(self, name: str) -> int:
        """Index of an arm in this task's arm axis."""
        return self.arms.index(name)

    # -- expert -----------------------------------------------------------------------------
    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        """Yield model-facing actions until done; `ctx.view` holds the state after each."""
        return iter(())

    def rng(self, seed: int) -> np.random.Generator:
        return self.seed_stream(seed)
