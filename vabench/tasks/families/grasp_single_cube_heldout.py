"""grasp_single_cube_heldout: the held-out box of grasp_single_cube, among distractor boxes.

Controlled-transfer variant of grasp_single_cube (suite "transfer"; same instruction, arms,
budget and predicate; it reads the base family's summary). What is held out:
- the target is not the base's 50 mm cube but a red box of 40 x 60 x 45 mm (x, y, z; 90 g,
  `box_red_40x60x45.xml`): narrower across one pair of faces, longer across the other, lower;
- it stands among three distractor boxes of other colours and sizes: a blue 55 mm cube, a
  yellow 70 x 35 x 30 mm bar and a green 45 x 45 x 70 mm pillar (`box_*.xml`).
The instruction still names the red one, so only the red box counts.

Scene: the red box resting on the table at x in [0.18, 0.26], y in [-0.16, -0.06] (the base's
ranges), yaw in [-45, 45] deg. Each distractor rests on the table at 110-170 mm from the red
box's centre in a uniformly drawn direction, yaw in [-90, 90] deg, at least 90 mm from every
other distractor (centre to centre): the open fingers (90 mm aperture) fit around the red box
without touching one. Drawn from the seed salted with `SALT`, so a seed gives another scene than
the same seed of the base family.
Success (the base's row, on the red box only, both now): the red box lifted more than 50 mm
above its settled height and the right gripper closed. Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the red box's centre), grasped (closed and touching the
red box), lifted (> 50 mm), completed.
Expert: top-down grasp across the red box's narrow (40 mm) faces (a grasp symmetric every 180
deg), GC at the box centre, close, lift 100 mm.
"""

from __future__ import annotations

import dataclasses

from vabench.tasks.families.grasp_single_cube import CUBE_AT
from vabench.tasks.families.grasp_single_cube import TASK as BASE
from vabench.tasks.heldout import Distractors, salted, variant

SALT = 0x6C5A1  # variant seeds draw from rng([seed, SALT]): other scenes than the base's seeds

TARGET_FILE = "box_red_40x60x45.xml"
TARGET_HALF = (0.02, 0.03, 0.0225)
DISTRACTORS = Distractors(
    boxes=(  # name, file, half-height
        ("distractor_blue", "box_blue_55.xml", 0.0275),
        ("distractor_yellow", "box_yellow_70x35x30.xml", 0.015),
        ("distractor_green", "box_green_45x45x70.xml", 0.035),
    ),
    ring=(0.11, 0.17),  # distractor centre distance from the target centre, m
    min_gap=0.09,  # distractor to distractor, centre to centre, m
    yaw_deg=(-90.0, 90.0),
)

TASK = variant(
    BASE,
    "grasp_single_cube_heldout",
    objects=(("cube", TARGET_FILE), *DISTRACTORS.objects),
    on_table=(("cube", dataclasses.replace(CUBE_AT, half_h=TARGET_HALF[2])),),  # the base's ranges
    # body x is the box's narrow axis; topdown(yaw) closes the fingers along the object's x
    symmetry_deg=180.0,
    distractors=DISTRACTORS,
    seed_stream=salted(SALT),
)
