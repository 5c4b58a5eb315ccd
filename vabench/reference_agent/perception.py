"""What each task family needs to see in the topdown image, as world coordinates.

`locate(family, hsv, cam)` returns a `Scene` (the objects' positions and headings on the
table) or None when any needed object is not found (the caller looks again or stops; it
never acts on a guess). Heights are not measured: every object rests on the table, so the
height of the surface the camera sees (a cube's top, a pen's upper side) is the table height
plus the object's size named in the task's public description (FACTS.md object facts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vabench.reference_agent import perception_generic as generic
from vabench.reference_agent.geometry import TABLE_Z, TopdownCamera
from vabench.reference_agent.segment import components
from vabench.reference_agent.vision import Blob, colour_mask, find_blob, opened, table_fraction

MIN_TABLE_FRACTION = 0.20  # real views: >= 0.35 (measured); JPEG noise: ~0.05
MIN_SIDE_TABLE_FRACTION = 0.08
MAX_ROUGHNESS = 12.0  # mean |value step| between neighbouring pixels: renders ~2-5, noise ~80
REACH_X = (-0.10, 0.50)  # m: where the right arm can pick and place on the table
REACH_Y = (-0.35, 0.25)
# half-sizes of the cubes (FACTS object facts); the pads are thin: their centroid is fine
SQUARE_HALF = {
    ("cube", "obj"): 0.025,
    ("cube_pad", "obj"): 0.025,
    ("cube_on_cube", "obj"): 0.025,
    ("cube_on_cube", "dest"): 0.025,
    ("cube_bowl", "obj"): 0.02,
    ("hammer", "dest"): 0.025,
}
BELL_TOP_Z = 0.05  # m above the table: the dome's widest visible outline, roughly
BOWL_RIM_Z = 0.052  # m above the table (place_cube_in_bowl: "rim about 72 mm in radius and
# 52 mm high")


@dataclass(frozen=True)
class Seen:
    """One located object: centre (x, y) in metres, heading (deg) of its long axis or of a
    face normal for square objects, and its length along that heading (m)."""

    x: float
    y: float
    heading: float = 0.0
    length: float = 0.0
    offset: float = 0.0
    """Along `heading`: from (x, y) to the middle of the object's extent (a lying bottle is
    grasped at its body, while its footprint reaches further on the neck's side)."""

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y])


Scene = dict[str, Seen]


def square_centre(b: Blob, half: float | None, cam: TopdownCamera) -> Seen:
    """A square top face: its yaw, and its centre from the far edges when the size is known
    (the centroid leans towards the camera by the sides it also sees)."""
    yaw = b.square_yaw()
    if half is None:
        c = b.centre
        return Seen(float(c[0]), float(c[1]), yaw)
    below = np.array([cam.x, cam.y])
    a = b.far_edge_centre(yaw, half, below)
    o = b.far_edge_centre(yaw + 90, half, below)
    r = np.radians(yaw)
    c = a * np.array([np.cos(r), np.sin(r)]) + o * np.array([-np.sin(r), np.cos(r)])
    return Seen(float(c[0]), float(c[1]), yaw)


def _long(b: Blob) -> Seen:
    c = b.centre
    h = b.axis_heading()
    lo, hi = b.extent(h)
    return Seen(float(c[0]), float(c[1]), h, hi - lo)


def _whole_piece(hsv: np.ndarray, cam: TopdownCamera, colour: str, plane_z: float) -> Blob:
    """The largest connected piece of `colour`, on the plane z = plane_z."""
    rows, cols = components(opened(colour_mask(hsv, colour)))[0]
    return Blob(cam.to_world(cols, rows, plane_z), cam.metres_per_pixel(plane_z) ** 2)


def _other_object(family: str, hsv: np.ndarray, cam: TopdownCamera) -> Seen | None:
    """A held-out bottle (`perception_generic`): lying, its centroid and axis on a plane near
    its top (its height unknown: the base bottle's); upright, its axis from its silhouette's
    bottom. The green pad, when the task has one, is not the object."""
    pad = opened(colour_mask(hsv, "green")) if family == "bottle_pad" else None
    piece = generic.largest_object(hsv, cam, pad)
    if piece is None:
        return None
    if family == "bottle_lying":
        centre, heading, length = generic.lying(*piece, cam, TABLE_Z + 0.04)
        return Seen(float(centre[0]), float(centre[1]), heading, length)
    x, y = generic.upright_axis(*piece, cam)
    return Seen(float(x), float(y))


def looks_like_scene(hsv: np.ndarray, topdown: bool = True) -> bool:
    """Whether an image shows the table (every view of these tasks does): a topdown view
    mostly; a side view, looking along the table at gripper height, partly (the wall and the
    robot fill the rest, ~12 % table measured), and then it must also be smooth, as a render
    is and noise is not."""
    if topdown:
        return table_fraction(hsv) >= MIN_TABLE_FRACTION
    v = hsv[..., 2].astype(np.int16)
    rough = float(np.abs(np.diff(v, axis=1)).mean())
    return table_fraction(hsv) >= MIN_SIDE_TABLE_FRACTION and rough < MAX_ROUGHNESS


def locate(family: str, hsv: np.ndarray, cam: TopdownCamera) -> Scene | None:
    """The objects of `family` in a topdown image; None if the image does not show them."""
    if not looks_like_scene(hsv):
        return None
    t = TABLE_Z
    found: dict[str, Blob | None] = {}
    if family in ("cube", "cube_pad", "cube_on_cube"):
        found["obj"] = find_blob(hsv, cam, ("red",), t + 0.05, 0.05, 8e-4)
    elif family == "cube_bowl":
        found["obj"] = find_blob(hsv, cam, ("red",), t + 0.04, 0.04, 5e-4)
    elif family in ("pen",):
        found["obj"] = find_blob(hsv, cam, ("purple", "red"), t + 0.014, 0.10, 2.5e-4)
    elif family == "pen_leaning":
        found["obj"] = find_blob(hsv, cam, ("purple", "red"), t + 0.042, 0.10, 2.5e-4)
    elif family == "bottle_lying":
        found["obj"] = find_blob(hsv, cam, ("blue", "yellow"), t + 0.063, 0.12, 2e-3)
    elif family in ("bottle_upright", "bottle_pad"):
        found["obj"] = find_blob(hsv, cam, ("red",), t + 0.165, 0.03, 1.5e-4)
    elif family == "bell":
        # a brass (yellow) dome on a black base, or a silver dome on a red base: the coloured
        # part finds the bell, the dome and base together give its centre (the red base shows
        # only as a crescent on the side facing the camera)
        ring = find_blob(hsv, cam, ("red", "yellow", "wood"), t + BELL_TOP_Z, 0.06, 1e-4)
        found["obj"] = ring and find_blob(
            hsv,
            cam,
            ("red", "yellow", "wood", "silver"),
            t + BELL_TOP_Z,
            0.045,
            6e-4,
            start=ring.centre,
        )
    elif family == "hammer":
        # the handle: a blue grip and the wooden shaft, mid-handle is the hammer's origin
        found["obj"] = find_blob(hsv, cam, ("blue", "wood"), t + 0.028, 0.15, 1e-3)
    if family in ("cube_pad", "bottle_pad"):
        found["dest"] = find_blob(hsv, cam, ("green",), t + 0.006, 0.10, 6e-3)
    elif family == "cube_on_cube":
        found["dest"] = find_blob(hsv, cam, ("green",), t + 0.05, 0.05, 8e-4)
    elif family == "cube_bowl":
        found["dest"] = find_blob(hsv, cam, ("blue",), t + BOWL_RIM_Z, 0.10, 4e-3)
        if found["dest"] is not None:
            # the whole connected container, not the pixels within a radius: a larger one
            # than the base's bowl (the held-out basin) is otherwise cut off on one side
            found["dest"] = _whole_piece(hsv, cam, "blue", t + BOWL_RIM_Z)
    elif family == "hammer":
        found["dest"] = find_blob(hsv, cam, ("red",), t + 0.05, 0.05, 8e-4)
    scene: Scene = {}
    if family in ("bottle_lying", "bottle_upright", "bottle_pad") and found["obj"] is None:
        # not the base family's bottle: whatever object is there, by shape alone
        other = _other_object(family, hsv, cam)
        if other is not None:
            del found["obj"]
            scene["obj"] = other
    if not (found or scene) or any(b is None for b in found.values()):
        return None
    for name, b in found.items():
        assert b is not None
        square = family.startswith("cube") or name == "dest"
        if (family == "cube_bowl" and name == "dest") or (family == "hammer" and name == "obj"):
            # the walls flare outwards, so from above the rim is the outline: its box's
            # centre is the bowl's axis (the centroid leans to the wall facing the camera); a
            # container with upright walls shows its near walls' outer faces too, which moves
            # the box's centre 10-15 mm towards the camera, well inside its interior

            lo, hi = b.points.min(axis=0), b.points.max(axis=0)
            seen = Seen(float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2)
        elif square:
            seen = square_centre(b, SQUARE_HALF.get((family, name)), cam)
        else:
            seen = _long(b)
        if not (REACH_X[0] <= seen.x <= REACH_X[1] and REACH_Y[0] <= seen.y <= REACH_Y[1]):
            return None  # not on the right arm's part of the table: not the object
        scene[name] = seen
    return scene
