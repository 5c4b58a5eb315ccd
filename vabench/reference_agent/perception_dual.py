"""What the dual-arm families need to see in the topdown image, as world coordinates.

The view is the midpoint one (`camera.view_topdown` of a dual-arm task, or the passive bundle's
first image) taken with both arms parked high on their own sides, fingers down, so neither
hides the middle of the table. Objects are segmented without a colour table (`segment`), the
parked grippers' finger pads (orange, like the block) are masked out around their projections.

- lift_pot: the pot is the largest object; its centre is the middle of the dark disc inside its
  rim (a disc on top: nothing occludes it, unlike the outer wall, whose near side the camera
  also sees); its handles are the dark or differently coloured pixels in a ring around it, and
  their principal axis is the pot's handle axis. The grasp points are 112.5 mm from the centre
  along that axis and 85 mm above the table (lift_pot's public description).
- place_shoe: the mat is the large deep-blue patch (the instruction's "blue mat"); the shoe is
  the largest other object, its heading the principal axis of its pixels, its toe the end away
  from the dark collar (the opening of the shoe, near the heel).
- handover_horizontal_block: the block is the largest object, its heading the principal axis.
"""

from __future__ import annotations

import math

import numpy as np

from vabench.reference_agent.geometry import TABLE_Z, TopdownCamera
from vabench.reference_agent.perception import Scene, Seen
from vabench.reference_agent.segment import (
    axis_heading,
    components,
    dark,
    foreground,
    hue_mask,
    without_grippers,
)

POT_RIM_Z = 0.105  # m above the table: between the two pots' rims (100 and 115 mm)
POT_HANDLE_R = 0.1125  # handle centres from the pot's axis (lift_pot description)
POT_HANDLE_Z = 0.085
HANDLE_RING = (0.10, 0.16)  # where the handles show, around the pot's axis
MAT_HUE = (163, 180)  # the mat's deep blue; blue shoes and pots are lighter (hue 145-160)
SHOE_TOP_Z = 0.07  # the upper's visible surface, roughly
BLOCK_TOP_Z = 0.03
MIN_OBJECT_M2 = 2e-3


def _world(cam: TopdownCamera, rc: tuple[np.ndarray, np.ndarray], z: float) -> np.ndarray:
    return cam.to_world(rc[1], rc[0], TABLE_Z + z)


def _objects(
    hsv: np.ndarray, cam: TopdownCamera, gcs: dict[str, np.ndarray], z: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    mask = without_grippers(foreground(hsv), cam, gcs)
    px_area = cam.metres_per_pixel(TABLE_Z + z) ** 2
    return components(mask, int(MIN_OBJECT_M2 / px_area))


def locate_pot(hsv: np.ndarray, cam: TopdownCamera, gcs: dict[str, np.ndarray]) -> Scene | None:
    objects = _objects(hsv, cam, gcs, POT_RIM_Z)
    if not objects:
        return None
    body = objects[0]
    hue = int(np.bincount(hsv[body][:, 0]).argmax())
    centre = _world(cam, body, POT_RIM_Z).mean(axis=0)
    rows, cols = np.nonzero(dark(hsv))
    disc = cam.to_world(cols, rows, TABLE_Z + POT_RIM_Z)
    for _ in range(4):  # mean shift onto the dark disc inside the rim
        near = disc[np.linalg.norm(disc - centre, axis=1) < 0.07]
        if len(near) < 20:
            return None
        centre = near.mean(axis=0)
    # handles: dark, or saturated in another hue than the pot's body, in a ring around it
    diff = np.abs(((hsv[..., 0].astype(int) - hue + 128) % 256) - 128) > 15
    cand = dark(hsv) | (hue_mask(hsv, 0, 255) & diff)
    rows, cols = np.nonzero(without_grippers(cand, cam, gcs))
    pts = cam.to_world(cols, rows, TABLE_Z + POT_HANDLE_Z)
    r = np.linalg.norm(pts - centre, axis=1)
    ring = pts[(r > HANDLE_RING[0]) & (r < HANDLE_RING[1])]
    if len(ring) < 20:
        return None
    heading = axis_heading(ring, centre)
    return {"pot": Seen(float(centre[0]), float(centre[1]), heading, 2 * POT_HANDLE_R)}


def locate_shoe(hsv: np.ndarray, cam: TopdownCamera, gcs: dict[str, np.ndarray]) -> Scene | None:
    mat_mask = hue_mask(hsv, *MAT_HUE, min_s=120) & (hsv[..., 2] < 180)
    mats = components(without_grippers(mat_mask, cam, gcs), 50)
    if not mats:
        return None
    mat_pts = _world(cam, mats[0], 0.001)
    x, y = (float(v) for v in mat_pts.mean(axis=0))  # to_world: (n, 2) points
    mat = Seen(x, y, axis_heading(mat_pts, mat_pts.mean(0)))
    mask = without_grippers(foreground(hsv) & ~mat_mask, cam, gcs)
    px_area = cam.metres_per_pixel(TABLE_Z + SHOE_TOP_Z) ** 2
    shoes = components(mask, int(MIN_OBJECT_M2 / px_area))
    if not shoes:
        return None
    pts = _world(cam, shoes[0], SHOE_TOP_Z)
    centre = pts.mean(axis=0)
    axis = axis_heading(pts, centre)
    u = np.array([math.cos(math.radians(axis)), math.sin(math.radians(axis))])
    along = (pts - centre) @ u
    # the collar: dark pixels inside the shoe's outline, near its axis (the sole's dark rim
    # runs along both long sides, the collar sits on the axis towards the heel)
    rows, cols = np.nonzero(dark(hsv))
    d = cam.to_world(cols, rows, TABLE_Z + SHOE_TOP_Z) - centre
    on_axis = (np.abs(d @ np.array([-u[1], u[0]])) < 0.012) & (np.abs(d @ u) < along.max())
    collar = d[on_axis] @ u
    if len(collar) < 10:
        return None
    toe = axis if float(np.median(collar)) < 0 else axis + 180
    length = float(along.max() - along.min())
    return {"shoe": Seen(float(centre[0]), float(centre[1]), toe, length), "mat": mat}


def locate_block(hsv: np.ndarray, cam: TopdownCamera, gcs: dict[str, np.ndarray]) -> Scene | None:
    objects = _objects(hsv, cam, gcs, BLOCK_TOP_Z)
    if not objects:
        return None
    pts = _world(cam, objects[0], BLOCK_TOP_Z)
    centre = pts.mean(axis=0)
    heading = axis_heading(pts, centre)
    return {"block": Seen(float(centre[0]), float(centre[1]), heading)}
