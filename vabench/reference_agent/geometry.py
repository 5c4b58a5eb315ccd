"""Geometry the reference agent knows from the public interface (spec FACTS.md, the prompt).

- World frame: z up, x to the robot's right, y away from the robot; table top at z = 0.741 m.
- `camera.view_topdown` puts the camera at GC + (0, 0, 0.68) m (clamped to z <= 1.85), looking
  straight down with image-up = world +y, so image-right = world +x; observer cameras have a
  vertical field of view of 55 deg. GC is read from the robot state, so a pixel of the topdown
  image and the height of the surface it shows give a world point: no scale needs calibrating.
- Gripper axes come from `local_axes_world` (rx approach, ry finger-closing, rz palm side);
  `gripper.rotate_local` turns about the current local axis by a right-hand angle, GC fixed.

Everything here is a pure function of numbers; angles in degrees at the edges (the action
interface), headings measured counter-clockwise from world +x seen from above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

TABLE_Z = 0.741
TOPDOWN_OFFSET_Z = 0.68
CAMERA_Z_MAX = 1.85
OBSERVER_FOVY_DEG = 55.0
FINGERTIP_BEYOND_GC = 0.015  # the prompt: fingertips reach 15 mm beyond GC along rx
TABLE_CLEARANCE = 0.003  # keep the fingertips this far above the table top
MIN_TOPDOWN_GC_Z = TABLE_Z + FINGERTIP_BEYOND_GC + TABLE_CLEARANCE


@dataclass(frozen=True)
class TopdownCamera:
    """The topdown view's pinhole camera for an image of `width` x `height` pixels."""

    x: float
    y: float
    z: float
    width: int
    height: int

    @property
    def focal_px(self) -> float:
        return (self.height / 2) / math.tan(math.radians(OBSERVER_FOVY_DEG) / 2)

    def to_world(self, cols: np.ndarray, rows: np.ndarray, plane_z: float) -> np.ndarray:
        """World (x, y) of pixel centres (column, row indexes) seen on the plane z = plane_z;
        shape (n, 2)."""
        scale = (self.z - plane_z) / self.focal_px
        u = np.asarray(cols, float) + 0.5 - self.width / 2
        v = np.asarray(rows, float) + 0.5 - self.height / 2
        return np.stack([self.x + u * scale, self.y - v * scale], axis=-1)

    def metres_per_pixel(self, plane_z: float) -> float:
        return (self.z - plane_z) / self.focal_px


def topdown_camera(gc: tuple[float, float, float], width: int, height: int) -> TopdownCamera:
    """The camera of `camera.view_topdown` chosen while the point it centres on (GC, or the
    midpoint of both GCs) was at `gc`. Only the height can be clamped where the agent looks
    from (a clamp in x or y would tilt the view; the agent never centres a view there)."""
    return TopdownCamera(gc[0], gc[1], min(gc[2] + TOPDOWN_OFFSET_Z, CAMERA_Z_MAX), width, height)


def view_centre(gcs: dict[str, np.ndarray], view: str) -> np.ndarray | None:
    """The point a topdown view label is centred on: "topdown" follows the only arm, or the
    midpoint of both in dual-arm tasks, as "both_topdown" does; "left_topdown" and
    "right_topdown" follow that arm. None for any other view (adjusted views included)."""
    if view == "topdown":
        target = next(iter(gcs)) if len(gcs) == 1 else "both"
    elif view.endswith("_topdown"):
        target = view.removesuffix("_topdown")
    else:
        return None
    if target == "both":
        return (np.asarray(gcs["left"]) + np.asarray(gcs["right"])) / 2
    return np.asarray(gcs[target]) if target in gcs else None


def r4(v: float) -> float:
    """A coordinate as the memo carries it: 0.1 mm."""
    return round(float(v), 4)


def heading_deg(v: np.ndarray) -> float:
    """Heading of a vector's horizontal part, counter-clockwise from +x, in (-180, 180]."""
    return math.degrees(math.atan2(float(v[1]), float(v[0])))


def wrap(angle: float, period: float) -> float:
    """`angle` wrapped into (-period/2, period/2]."""
    a = math.fmod(angle + period / 2, period)
    a = a + period if a <= 0 else a
    return a - period / 2


def rotate(v: np.ndarray, axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """`v` turned by a right-hand rotation of `angle_deg` about the unit vector `axis`
    (Rodrigues)."""
    a = math.radians(angle_deg)
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.asarray(v, float)
    return v * math.cos(a) + np.cross(k, v) * math.sin(a) + k * np.dot(k, v) * (1 - math.cos(a))


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def turn_to_align(moving: np.ndarray, pivot: np.ndarray, goal: np.ndarray) -> float:
    """The signed angle (deg) of a rotation about `pivot` that brings `moving` closest to
    `goal`: the rotation about `pivot` of the components perpendicular to it."""
    k = np.asarray(pivot, float) / np.linalg.norm(pivot)
    m = moving - k * np.dot(k, moving)
    g = goal - k * np.dot(k, goal)
    if np.linalg.norm(m) < 1e-9 or np.linalg.norm(g) < 1e-9:
        return 0.0
    return math.degrees(math.atan2(float(np.dot(k, np.cross(m, g))), float(np.dot(m, g))))


def yaw_turn(rx: np.ndarray, ry: np.ndarray, heading: float, period: float = 180.0) -> float:
    """The rotation about rx (deg, right-hand) that gives ry the world heading `heading`
    modulo `period` (fingers are symmetric: 180 deg; a cube's faces: 90 deg), smallest first."""
    now = heading_deg(ry)
    # rotating about rx = -z turns ry clockwise seen from above; about +z counter-clockwise
    sense = 1.0 if rx[2] > 0 else -1.0
    return sense * wrap(heading - now, period)
