"""Perception that does not know the object's colour or size (held-out objects).

When the family's colour model finds nothing (a bottle of another colour than the base
family's), the object is what is neither table nor robot (`segment.foreground`), in the right
arm's part of the table, the largest such piece; a destination the colour model did find (the
green pad) is left out first. Measures that need no size:

- a lying object: the centroid and principal axis of its pixels on a plane near its top;
- an upright object: its axis from the bottom of its silhouette. Seen from above and to one
  side, an upright object leans away from the point below the camera (its top is closer to
  the camera, so it projects farther out); the nearest point of the silhouette to that point
  is where its near side meets the table, at table height, so its world position is exact.
  The axis lies half the object's depth beyond it, and for round or square sections the depth
  seen along that line is the width seen across it at the same place (a square seen along its
  diagonal: the diagonal both ways), measured on the silhouette's near part.
"""

from __future__ import annotations

import numpy as np

from vabench.reference_agent.geometry import TABLE_Z, TopdownCamera
from vabench.reference_agent.segment import axis_heading, components, foreground, without_grippers

REACH_X = (-0.10, 0.50)  # the right arm's part of the table (as perception.REACH_*)
REACH_Y = (-0.35, 0.25)
PALM_MASK_M = 0.06  # around the parked gripper's projection: its palm seen from above
MIN_OBJECT_M2 = 6e-4
NEAR_BAND = 0.045  # m of the silhouette's near end where its width is measured


def largest_object(
    hsv: np.ndarray, cam: TopdownCamera, exclude: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows, cols) of the largest object piece in reach, or None."""
    gc = np.array([cam.x, cam.y, cam.z - 0.68])
    mask = foreground(hsv) if exclude is None else foreground(hsv) & ~exclude
    mask = without_grippers(mask, cam, {"right": gc}, PALM_MASK_M)
    px_area = cam.metres_per_pixel(TABLE_Z) ** 2
    for rows, cols in components(mask, int(MIN_OBJECT_M2 / px_area)):
        x, y = cam.to_world(cols, rows, TABLE_Z).mean(axis=0)
        if REACH_X[0] <= x <= REACH_X[1] and REACH_Y[0] <= y <= REACH_Y[1]:
            return rows, cols
    return None


def lying(rows: np.ndarray, cols: np.ndarray, cam: TopdownCamera, plane_z: float):
    """(centre, heading of the long axis, length) on the plane z = plane_z."""
    pts = cam.to_world(cols, rows, plane_z)
    centre = pts.mean(axis=0)
    heading = axis_heading(pts, centre)
    u = np.array([np.cos(np.radians(heading)), np.sin(np.radians(heading))])
    s = (pts - centre) @ u
    return centre, heading, float(np.percentile(s, 99) - np.percentile(s, 1))


def upright_axis(rows: np.ndarray, cols: np.ndarray, cam: TopdownCamera) -> np.ndarray:
    """The (x, y) of an upright object's axis from its silhouette (see the module docstring)."""
    pts = cam.to_world(cols, rows, TABLE_Z)
    nadir = np.array([cam.x, cam.y])
    u = np.median(pts, axis=0) - nadir
    u /= np.linalg.norm(u)
    v = np.array([-u[1], u[0]])
    s, t = (pts - nadir) @ u, (pts - nadir) @ v
    s0 = float(np.percentile(s, 0.5))
    band = s < s0 + NEAR_BAND
    t_lo, t_hi = (float(x) for x in np.percentile(t[band], [1, 99]))
    return nadir + (s0 + (t_hi - t_lo) / 2) * u + ((t_lo + t_hi) / 2) * v
