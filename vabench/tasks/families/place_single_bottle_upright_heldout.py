"""place_single_bottle_upright_heldout: the held-out container of place_single_bottle_upright
(transfer track).

What is held out: the container, the same as grasp_single_bottle_upright_heldout's: a tall
square-section bottle (bottle_square.xml: 50 x 50 mm, body 180 mm, 220 mm overall; orange,
purple label, white cap) instead of the round water bottle (64 mm across, 168 mm tall).
Scene: the base's ranges, drawn from the variant's own seed stream (`heldout_rng`): the bottle
upright at x in [0.20, 0.28], y in [-0.16, -0.04] (faces normal to world x and y); the base's
green pad (pad_green_130.xml, half-size 0.065 m, 3 mm half-thick) at x in [0.03, 0.09], y in
[0.07, 0.13], axis-aligned.
Success (the base's predicate and tolerances; only the resting height follows the container):
the bottle was lifted >= 50 mm at some point (latched); the x and y errors of its body centre to
the pad centre each <= 40 mm; its height error to the upright resting height on the pad (pad
half-thickness + 90 mm) <= 35 mm; the pad displaced <= 2 mm; bottle-pad contact; right gripper
open. Instruction, arm and budget (100 steps) are the base's. Unlike the base (where a bottle
lying on the pad passes the height check), this container lying on the pad has its centre 25 mm
above the pad's top, 65 mm below the upright resting height, and fails it.
Checkpoints: reached, grasped, lifted (latched), transported (x/y and height within
tolerance), released (gripper open), completed.
Expert: the base's: side grasp, lift 60 mm, carry over the pad centre, lower until resting,
open, back off upwards.
"""

from __future__ import annotations

import dataclasses

from vabench.tasks import skills_heldout_bottles as hb
from vabench.tasks.families.grasp_single_bottle_upright import BOTTLE_AT
from vabench.tasks.families.place_single_bottle_upright import PAD_AT, PAD_HALF_THICK
from vabench.tasks.families.place_single_bottle_upright import TASK as BASE
from vabench.tasks.heldout import variant

TASK = variant(
    BASE,
    "place_single_bottle_upright_heldout",
    objects=(("bottle", "bottle_square.xml"), ("pad", "pad_green_130.xml")),
    on_table=(("bottle", dataclasses.replace(BOTTLE_AT, half_h=hb.SQUARE_HALF_H)), ("pad", PAD_AT)),
    rest_height=PAD_HALF_THICK + hb.SQUARE_HALF_H,  # bottle origin above the pad centre
    seed_stream=hb.heldout_rng,
)
