"""The basket task's topdown view: the basket, and each object still outside it.

The task's public description (paper section 3.1, FACTS "Held-out variants and the long-horizon
track", the task's docstring) names what lies on the table: a red 50 mm cube, a yellow 40 mm
cube, a blue water bottle lying down (yellow label, red cap), a green bottle of the same shape
standing upright (black cap), a purple pen (red cap), and a brown open basket 284 x 224 mm
outside, its rim 79 mm above the table. The agent sorts what it sees into those kinds:

- the basket: the brown pixels; its centre from its far edges (the camera also sees the outer
  faces of the walls that face it, which stretch the outline towards it);
- the objects: everything saturated that is not brown, split into connected pieces, each named
  by the colour most of its pixels have (a piece with some blue is the lying bottle: its label
  and cap are other colours); pieces whose centre lies inside the basket are placed already;
- measures as in the single-arm families: cubes' yaw and far-edge centres, long objects' axis,
  centre and extent, the upright bottle's cap (dark, on top of the green body, seen whole from
  above) for its axis.
"""

from __future__ import annotations

import math

import numpy as np

from vabench.reference_agent.geometry import TABLE_Z, TopdownCamera
from vabench.reference_agent.perception import Scene, Seen, square_centre
from vabench.reference_agent.segment import (
    axis_heading,
    components,
    dark,
    hue_mask,
    without_grippers,
)
from vabench.reference_agent.vision import Blob, opened

BASKET_HALF = (0.142, 0.112)  # outer half-sizes along x and y
BASKET_INNER_HALF = (0.13, 0.10)
RIM_Z = 0.079
HUES = {  # PIL hue ranges of the kinds' colours
    "red": (240, 10),
    "brown": (12, 30),
    "yellow": (31, 55),
    "green": (60, 115),
    "blue": (120, 172),
    "purple": (176, 235),
}
KIND_OF_HUE = {"red": "cube", "yellow": "small_cube", "green": "upright_bottle", "purple": "pen"}
TOP_Z = {  # the height of the surface the camera sees of each kind
    "cube": 0.05,
    "small_cube": 0.04,
    "bottle": 0.063,
    "pen": 0.014,
    "upright_bottle": 0.09,
}
CAP_Z = 0.165  # the upright bottle's cap top (the water bottle's shape: 168 mm tall)
MIN_PIECE_M2 = 1.2e-4
PALM_MASK_M = 0.0  # the gripper seen from straight above: its palm hides its orange finger
# pads, and what it hides of an object is not there to mask


def _hue_class(hsv: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> dict[str, float]:
    """Share of the piece's pixels in each colour class."""
    h = hsv[rows, cols, 0].astype(int)
    out = {}
    for name, (lo, hi) in HUES.items():
        inside = (h >= lo) & (h <= hi) if lo <= hi else (h >= lo) | (h <= hi)
        out[name] = float(inside.mean())
    return out


def locate_basket(hsv: np.ndarray, cam: TopdownCamera, gcs: dict) -> Seen | None:
    mask = without_grippers(opened(hue_mask(hsv, *HUES["brown"])), cam, gcs, PALM_MASK_M)
    pieces = components(mask, 200)
    if not pieces:
        return None
    rows, cols = pieces[0]
    pts = cam.to_world(cols, rows, TABLE_Z + RIM_Z)
    # far edges: on the side away from the point below the camera
    sx = -1.0 if np.median(pts[:, 0]) < cam.x else 1.0
    sy = -1.0 if np.median(pts[:, 1]) < cam.y else 1.0
    far_x = np.percentile(pts[:, 0], 0.5 if sx < 0 else 99.5)
    far_y = np.percentile(pts[:, 1], 0.5 if sy < 0 else 99.5)
    return Seen(float(far_x - sx * BASKET_HALF[0]), float(far_y - sy * BASKET_HALF[1]))


def inside_basket(xy: np.ndarray, basket: Seen) -> bool:
    dx, dy = abs(xy[0] - basket.x), abs(xy[1] - basket.y)
    return bool(dx < BASKET_INNER_HALF[0] and dy < BASKET_INNER_HALF[1])


def _measure(
    kind: str, hsv: np.ndarray, rows: np.ndarray, cols: np.ndarray, cam: TopdownCamera
) -> Seen:
    z = TABLE_Z + TOP_Z[kind]
    pts = cam.to_world(cols, rows, z)
    blob = Blob(pts, cam.metres_per_pixel(z) ** 2)
    if kind in ("cube", "small_cube"):
        half = TOP_Z[kind] / 2
        return square_centre(blob, half, cam)
    centre = pts.mean(axis=0)
    if kind == "bottle":  # grasped at its body: the blue and the label, not the red cap
        h = hsv[rows, cols, 0].astype(int)
        body = ~((h >= HUES["red"][0]) | (h <= HUES["red"][1]))
        if body.sum() > 20:
            centre = pts[body].mean(axis=0)
    if kind == "upright_bottle":
        return _upright_axis(hsv, rows, cols, cam)
    heading = axis_heading(pts, centre)
    u = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
    s = (pts - centre) @ u
    lo, hi = float(np.percentile(s, 1)), float(np.percentile(s, 99))
    # x, y: where to grasp (the centroid); `length` the extent, `mid` offset along the axis
    # of the extent's middle from the centroid (the footprint's centre)
    return Seen(float(centre[0]), float(centre[1]), heading, hi - lo, (lo + hi) / 2)


def _upright_axis(hsv: np.ndarray, rows: np.ndarray, cols: np.ndarray, cam: TopdownCamera) -> Seen:
    """The upright bottle's axis: the middle of its black cap. Seen from the side, the camera
    sees the green body leaning away from the point below it, the shoulder (the farthest
    green) just beyond the cap: the cap is the dark patch in the last few cm of green on the
    line from that point through the bottle (the shaded label is on the near side)."""
    z = TABLE_Z + CAP_Z
    green = cam.to_world(cols, rows, z)
    nadir = np.array([cam.x, cam.y])
    u = green.mean(axis=0) - nadir
    u /= np.linalg.norm(u)
    v = np.array([-u[1], u[0]])
    far = float(np.percentile((green - nadir) @ u, 99))
    t0 = float(np.median((green - nadir) @ v))
    drows, dcols = np.nonzero(dark(hsv))
    d = cam.to_world(dcols, drows, z) - nadir
    s, t = d @ u, d @ v
    cap = d[(s > far - 0.05) & (s < far + 0.01) & (np.abs(t - t0) < 0.02)]
    c = nadir + (cap.mean(axis=0) if len(cap) >= 5 else (far - 0.03) * u + t0 * v)
    return Seen(float(c[0]), float(c[1]))


def locate(hsv: np.ndarray, cam: TopdownCamera, gcs: dict) -> Scene | None:
    """The basket and the objects outside it (by kind), or None without a basket."""
    basket = locate_basket(hsv, cam, gcs)
    if basket is None:
        return None
    saturated = hue_mask(hsv, 0, 255) & ~hue_mask(hsv, *HUES["brown"])
    mask = without_grippers(opened(saturated), cam, gcs, PALM_MASK_M)
    px_area = cam.metres_per_pixel(TABLE_Z + 0.05) ** 2
    scene: Scene = {"basket": basket}
    for rows, cols in components(mask, int(MIN_PIECE_M2 / px_area)):
        share = _hue_class(hsv, rows, cols)
        if share["blue"] >= 0.15:
            kind = "bottle"
        else:
            colour = max(KIND_OF_HUE, key=lambda c: share[c])
            kind = KIND_OF_HUE[colour]
        if kind in scene:
            continue  # a smaller piece of the same colour: a part of an object already seen
        seen = _measure(kind, hsv, rows, cols, cam)
        if inside_basket(seen.xy, basket):
            continue
        scene[kind] = seen
    return scene
