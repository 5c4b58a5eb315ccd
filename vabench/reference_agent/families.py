"""The task families the agent knows, each as (start plan, locate, manipulation plan).

`family_of(instruction, arms)` names the family from the instruction (held-out variants keep
their base family's instruction, so they run its plan with perception that does not depend on
the base objects' colours and sizes). The executor calls the rest:
- `start_plan(family)`: park where the arms hide little, look from above, see;
- `look_again(family, looks)`: the objects were not found: observe from higher up;
- `locate(family, hsv, cam, gcs, memo)`: the objects in the topdown image, or None;
- `manipulation_plan(family, scene, memo)`: the steps that do the task.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from vabench.reference_agent import (
    perception,
    perception_basket,
    perception_dual,
    plans,
    plans_basket,
    plans_dual,
)
from vabench.reference_agent.geometry import TopdownCamera
from vabench.reference_agent.perception import Scene

Step = list[Any]


DUAL_FAMILY_WORDS = (
    (("pot",), "pot"),
    (("shoe",), "shoe"),
    (("hand it over",), "handover"),
    (("handover",), "handover"),
)
"""The dual-arm families by the words of their instruction (as `plans.FAMILY_WORDS`)."""


def family_of(instruction: str, arms: tuple[str, ...]) -> str | None:
    """The family an instruction names for a task with `arms`, or None (no plan)."""
    if set(arms) == {"right"}:
        return plans.named_family(instruction, ((("basket",), "basket"), *plans.FAMILY_WORDS))
    if set(arms) == {"left", "right"}:
        return plans.named_family(instruction, DUAL_FAMILY_WORDS)
    return None


def start_plan(family: str) -> list[Step]:
    if family == "basket":
        return plans_basket.start_plan()
    return plans_dual.start_plan() if family in DUAL else plans.start_plan()


def look_again(family: str, looks: int) -> list[Step]:
    """From higher up, the topdown view covers more of the table (and the arm hides less)."""
    if family in DUAL:
        return plans_dual.look_again(looks)
    if family == "basket":
        return plans_basket.look_again(looks)
    x, y, z = plans.PARK
    return [["go", x, y, round(z + 0.06 * looks, 4), "zxy"], ["look", "topdown"], ["see"]]


def locate(
    family: str,
    hsv: np.ndarray,
    cam: TopdownCamera,
    gcs: dict[str, np.ndarray],
    memo: dict[str, Any],
) -> Scene | None:
    if family in DUAL or family == "basket":
        if not perception.looks_like_scene(hsv):
            return None
        if family == "basket":
            return perception_basket.locate(hsv, cam, gcs)
        return DUAL[family][0](hsv, cam, gcs)
    return perception.locate(family, hsv, cam)


def manipulation_plan(family: str, scene: Scene, memo: dict[str, Any]) -> list[Step] | None:
    if family in DUAL:
        return DUAL[family][1](scene)
    if family == "basket":
        return plans_basket.basket_plan(scene, memo)
    return plans.manipulation_plan(family, scene)


DUAL = {
    "pot": (perception_dual.locate_pot, plans_dual.pot_plan),
    "shoe": (perception_dual.locate_shoe, plans_dual.shoe_plan),
    "handover": (perception_dual.locate_block, plans_dual.block_plan),
}
