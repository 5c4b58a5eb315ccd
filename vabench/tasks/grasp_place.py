"""The shapes of family that several families share (the grasp and the place families). No TASK
here: not a family, so not in `families/`.

- `GraspFamily`: one object picked up by the right arm (tab:seed-spec-grasp: grasp_single_*,
  grasp_pen_leaning_cube and their held-out variants): the grasp predicate on `target` (the
  first of `objects`; `common.grasp_evaluation`), the checkpoints reached, grasped, lifted,
  completed; the expert is the family's `grasp` followed by a lift of 100 mm.
- `PlaceFamily`: one object carried by the right arm onto or into a support (tab:seed-spec-place:
  place_single_cube, place_single_bottle_upright, place_cube_in_bowl, place_cube_on_cube and
  their held-out variants): `obj`, the first of `objects`, goes onto or into `target`, the
  second; the shared place predicate (`common.place_evaluation`) over the family's own
  `placement` checks, the latch "was_lifted", the six place checkpoints.
- `PadPlaceFamily`: a `PlaceFamily` whose support is a flat pad: the pad-placement predicate of
  the paper (_single_right_arm_place_target_task) with the family's tolerances.

Each family module keeps its spec (docstring), ranges, sampler and the parts of its predicate
and expert that are its own; the watched contact pairs follow from `target` / `obj`.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from vabench.tasks import common
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task
from vabench.tasks.expert import ExpertContext

Check = tuple[str, jax.Array]  # a named predicate check


@dataclass(frozen=True)
class GraspFamily(Task):
    """A one-object grasp family (see the module docstring); the family defines `grasp`, and
    `sample` unless `on_table` places its objects."""

    checkpoints: tuple[str, ...] = common.GRASP_CHECKPOINTS

    @property
    def target(self) -> str:
        """The object to pick up: the first of `objects`."""
        return self.objects[0][0]

    def __post_init__(self) -> None:
        if not self.contact_pairs:
            object.__setattr__(self, "contact_pairs", ((self.target, "right_gripper"),))

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return common.grasp_evaluation(self, ix, s, latched, self.target)

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        yield from self.grasp(ctx)
        yield from common.lift(ctx, "right", 0.10)

    def grasp(self, ctx: ExpertContext) -> Script:
        """The expert's grasp of `target` (the lift follows)."""
        raise NotImplementedError


@dataclass(frozen=True)
class PlaceFamily(Task):
    """A right-arm place family (see the module docstring); the family defines `placement`
    and `expert` (and `on_table` places the objects)."""

    checkpoints: tuple[str, ...] = common.PLACE_CHECKPOINTS
    latches: tuple[str, ...] = ("was_lifted",)

    @property
    def obj(self) -> str:
        """The object carried: the first of `objects`."""
        return self.objects[0][0]

    @property
    def target(self) -> str:
        """The support it goes onto or into: the second of `objects`."""
        return self.objects[1][0]

    def __post_init__(self) -> None:
        if not self.contact_pairs:
            pairs = ((self.obj, "right_gripper"), (self.obj, self.target))
            object.__setattr__(self, "contact_pairs", pairs)

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        placement, still = self.placement(ix, s)
        return common.place_evaluation(
            self, ix, s, latched, self.obj, self.target, placement, still
        )

    def placement(self, ix: ObjectIndex, s: SlotState) -> tuple[dict[str, jax.Array], Check]:
        """The family's placement checks (the first one horizontal) and its check that the
        support did not move (name, flag)."""
        raise NotImplementedError


@dataclass(frozen=True)
class PadPlaceFamily(PlaceFamily):
    """A place family onto a flat pad: x and y errors of `obj` to the pad centre each within
    `xy_tol`, height error within `height_tol` of `rest_height` (the object's origin above the
    pad's when it rests on it), the pad displaced at most `pad_move_tol`."""

    rest_height: float = 0.0
    xy_tol: float = 0.0
    height_tol: float = 0.0
    pad_move_tol: float = 0.0

    def placement(self, ix: ObjectIndex, s: SlotState) -> tuple[dict[str, jax.Array], Check]:
        p, t = ix.pos(s.qpos, self.obj), ix.pos(s.qpos, self.target)
        placement = {
            "xy_within_tolerance": jnp.all(jnp.abs(p[:2] - t[:2]) <= self.xy_tol),
            "height_within_tolerance": jnp.abs(p[2] - (t[2] + self.rest_height)) <= self.height_tol,
        }
        still = ix.displacement(s, self.target) <= self.pad_move_tol
        return placement, ("target_not_displaced", still)
