"""grasp_single_bottle_upright_heldout: the held-out container of grasp_single_bottle_upright
(transfer track).

What is held out: the container. Instead of the base's round water bottle (bottle_water.xml:
64 mm across, 168 mm tall, body 120 mm; blue, yellow label, red cap) a tall square-section
bottle stands upright (bottle_square.xml: 50 x 50 mm section with 8 mm rounded edges, body
180 mm, 220 mm overall; orange, purple label, white cap). Its origin, the centre of the body,
is 90 mm above the table (the base's: 60 mm).
Scene: the base's ranges, drawn from the variant's own seed stream (`heldout_rng`): x in
[0.20, 0.28], y in [-0.16, -0.04], fixed upright orientation with the faces normal to world x
and y (no yaw, as in the base).
Success (the base's predicate, unchanged): the bottle lifted more than 50 mm above its settled
height and the right gripper closed (both now, not latched). Instruction, arm and budget (50
steps) are the base's.
Checkpoints: reached (GC within 30 mm of the body's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: the base's side grasp (approach along +y, fingers closing along world x on two flat
faces, at the body's centre), close, lift 100 mm.
"""

from __future__ import annotations

import dataclasses

from vabench.tasks import skills_heldout_bottles as hb
from vabench.tasks.families.grasp_single_bottle_upright import BOTTLE_AT
from vabench.tasks.families.grasp_single_bottle_upright import TASK as BASE
from vabench.tasks.heldout import variant

TASK = variant(
    BASE,
    "grasp_single_bottle_upright_heldout",
    objects=(("bottle", "bottle_square.xml"),),
    on_table=(("bottle", dataclasses.replace(BOTTLE_AT, half_h=hb.SQUARE_HALF_H)),),
    seed_stream=hb.heldout_rng,
)
