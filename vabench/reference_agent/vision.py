"""Colour segmentation of the topdown image and the shape measures the plans need.

Colours are thresholds in PIL's HSV (every channel 0-255; hue 0 = red, 43 = yellow,
85 = green, 170 = blue). They separate the objects the instructions name (red cube, blue bowl,
green pad ...) from the beige table (hue ~26, saturation ~47) and the dark grey robot and floor
(saturation < 60 or value < 50). A mask is opened (eroded then dilated) before use, so isolated
pixels (JPEG ringing, an image of noise) never form an object; a blob is then the pixels near
the mask's densest point, so a second patch of the same colour far away does not drag the
centroid.

Measures are taken in world metres on a horizontal plane (`geometry.TopdownCamera.to_world`),
so thresholds on areas and lengths do not depend on the image size.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np
from PIL import Image

from vabench.reference_agent.geometry import TopdownCamera

MAX_WORK_WIDTH = 640  # larger images are decoded at 1/2, 1/4 ... (JPEG DCT scaling: fast)

# (hue ranges, min saturation, min value, max saturation)
COLOURS: dict[str, tuple[tuple[tuple[int, int], ...], int, int, int]] = {
    "red": (((240, 255), (0, 12)), 120, 50, 255),
    "wood": (((13, 27),), 100, 60, 255),
    "yellow": (((28, 52),), 110, 80, 255),
    "green": (((60, 112),), 90, 40, 255),
    "blue": (((120, 172),), 90, 40, 255),
    "purple": (((176, 225),), 70, 40, 255),
    # bright and nearly colourless: polished metal (the table is saturation ~47, the robot
    # and shadows are darker)
    "silver": (((0, 255),), 0, 110, 30),
}


def decode(jpeg: bytes) -> np.ndarray:
    """HSV pixels (rows, cols, 3) of an image, decoded at most `MAX_WORK_WIDTH` wide."""
    im: Image.Image = Image.open(io.BytesIO(jpeg))
    if im.width > MAX_WORK_WIDTH:
        scale = math.ceil(im.width / MAX_WORK_WIDTH)
        im.draft("RGB", (im.width // scale, im.height // scale))
    if im.mode != "RGB":  # a JPEG decodes to RGB: converting it again would only copy it
        im = im.convert("RGB")
    return np.asarray(im.convert("HSV"))


def colour_mask(hsv: np.ndarray, colour: str) -> np.ndarray:
    ranges, min_s, min_v, max_s = COLOURS[colour]
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    hue = np.zeros(h.shape, bool)
    for lo, hi in ranges:
        hue |= (h >= lo) & (h <= hi)
    return hue & (s >= min_s) & (s <= max_s) & (v >= min_v)


def table_fraction(hsv: np.ndarray) -> float:
    """Share of pixels that look like the beige table top: a real topdown image of the scene
    has plenty; noise or a view of something else has almost none."""
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]  # uint8: every bound lies in 0..255
    table = (h >= 14) & (h <= 40) & (s >= 25) & (s <= 85) & (v >= 90) & (v <= 215)
    return float(table.mean())


def _shift_min(m: np.ndarray) -> np.ndarray:
    p = np.pad(m, 1, constant_values=False)
    out = m.copy()
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            out &= p[dr : dr + m.shape[0], dc : dc + m.shape[1]]
    return out


def _shift_max(m: np.ndarray) -> np.ndarray:
    p = np.pad(m, 1, constant_values=False)
    out = m.copy()
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            out |= p[dr : dr + m.shape[0], dc : dc + m.shape[1]]
    return out


def opened(mask: np.ndarray) -> np.ndarray:
    """3x3 morphological opening: removes specks and one-pixel lines, keeps solid patches."""
    return _shift_max(_shift_min(mask))


@dataclass(frozen=True)
class Blob:
    """Pixels of one object projected on a horizontal plane, in world metres."""

    points: np.ndarray  # (n, 2) world x, y
    pixel_area: float  # m^2 one pixel covers on the plane

    @property
    def area(self) -> float:
        return len(self.points) * self.pixel_area

    @property
    def centre(self) -> np.ndarray:
        return self.points.mean(axis=0)

    def axis_heading(self) -> float:
        """Heading (deg, in (-90, 90]) of the principal (long) axis."""
        d = self.points - self.centre
        cov = d.T @ d / len(d)
        _, vecs = np.linalg.eigh(cov)
        major = vecs[:, 1]
        return (
            math.degrees(math.atan2(major[1], major[0]))
            if major[0] >= 0
            else (math.degrees(math.atan2(-major[1], -major[0])))
        )

    def extent(self, heading: float) -> tuple[float, float]:
        """(min, max) of the points projected on the unit vector of `heading` (deg)."""
        u = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
        s = (self.points - self.centre) @ u
        return float(s.min()), float(s.max())

    def far_edge_centre(self, heading: float, half: float, viewpoint: np.ndarray) -> float:
        """Centre, along the unit vector of `heading`, of a box of half-size `half` whose top
        face lies on the blob's plane. The camera also sees the sides that face it, and they
        project between the box and the point below the camera (`viewpoint`), so only the
        outline on the far side is the top face's edge: the centre is half a size in from it.
        """
        u = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
        s = self.points @ u
        if float(np.median(s)) >= float(np.asarray(viewpoint) @ u):
            return float(np.percentile(s, 99.5)) - half
        return float(np.percentile(s, 0.5)) + half

    def square_yaw(self) -> float:
        """Yaw (deg, in [-45, 45)) of the minimal-area bounding rectangle: the face directions
        of a cube seen from above."""
        d = self.points - self.centre
        best, best_area = 0.0, math.inf
        for deg in range(-45, 45):
            a = math.radians(deg)
            u = d @ np.array([math.cos(a), math.sin(a)])
            w = d @ np.array([-math.sin(a), math.cos(a)])
            area = float(np.ptp(u) * np.ptp(w))
            if area < best_area:
                best, best_area = float(deg), area
        return best


def find_blob(
    hsv: np.ndarray,
    cam: TopdownCamera,
    colours: tuple[str, ...],
    plane_z: float,
    radius: float,
    min_area: float,
    start: np.ndarray | None = None,
) -> Blob | None:
    """The object of `colours` on the plane z = `plane_z`: the opened mask's pixels within
    `radius` (m) of its densest point (a few mean-shift rounds from `start`, by default the
    median); None when fewer than `min_area` (m^2) remain."""
    mask = np.zeros(hsv.shape[:2], bool)
    for c in colours:
        mask |= colour_mask(hsv, c)
    rows, cols = np.nonzero(opened(mask))
    if len(rows) == 0:
        return None
    pts = cam.to_world(cols, rows, plane_z)
    pixel_area = cam.metres_per_pixel(plane_z) ** 2
    centre = np.median(pts, axis=0) if start is None else np.asarray(start, float)
    near = pts
    for _ in range(4):
        near = pts[np.linalg.norm(pts - centre, axis=1) <= radius]
        if len(near) == 0:
            return None
        centre = near.mean(axis=0)
    if len(near) * pixel_area < min_area:
        return None
    return Blob(near, pixel_area)
