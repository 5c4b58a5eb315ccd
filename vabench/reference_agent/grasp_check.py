"""Is the object in the fingers? A look from the side after a short lift.

The robot state says only what the gripper was told (`is_open`), not how far its fingers
closed, so a grasp is verified by a look: `camera.view_side` (or the passive bundle's second
image) puts the camera 0.58 m to the arm's outer side of GC, 0.06 m above it, aimed at GC
(FACTS.md "Semantic camera views"; clamped to the camera workspace, x <= 0.85), so GC is the
middle of the image. After the gripper closed and rose `LIFT` above the grasp, a held object
fills the fingers' gap around GC; one left on the table lies at least `LIFT` minus its upper
half below GC, under the window looked at. A finger in front of the object hides its middle,
not its sides (the object is wider than the 24 mm finger), and the fingers' own orange pads
show only as a sliver, so their hue is not counted.
"""

from __future__ import annotations

import math

import numpy as np

from vabench.reference_agent.geometry import OBSERVER_FOVY_DEG
from vabench.reference_agent.segment import foreground, hue_mask

LIFT = 0.06  # m above the grasp height when the look is taken
SIDE_OFFSET = np.array([0.58, -0.02, 0.06])
CAMERA_X_MAX = 0.85
WINDOW = (-0.02, 0.03, 0.045)  # m: from 20 mm above GC to 30 mm below it, 45 mm either side
PAD_HUE = (13, 27)  # the finger pads' orange
MIN_PIXELS_480 = 60  # object pixels in the window at 480 rows (a pen end-on: ~120)


def in_hand(hsv: np.ndarray, gc: np.ndarray) -> bool:
    """Whether the side view `hsv` (centred on GC `gc`) shows an object between the fingers."""
    cam = np.asarray(gc, float) + SIDE_OFFSET
    cam[0] = min(cam[0], CAMERA_X_MAX)
    rows, cols = hsv.shape[:2]
    px_per_m = (rows / 2) / math.tan(math.radians(OBSERVER_FOVY_DEG) / 2)
    px_per_m /= float(np.linalg.norm(cam - gc))
    top, bottom, half = WINDOW
    r0, r1 = int(rows / 2 + top * px_per_m), int(rows / 2 + bottom * px_per_m)
    c0, c1 = int(cols / 2 - half * px_per_m), int(cols / 2 + half * px_per_m)
    window = (foreground(hsv) & ~hue_mask(hsv, *PAD_HUE))[r0:r1, c0:c1]
    return int(window.sum()) >= MIN_PIXELS_480 * (rows / 480) ** 2
