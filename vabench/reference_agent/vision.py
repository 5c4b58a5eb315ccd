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

import functools
import io
import math
import os
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import PIL
import simplejpeg
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


@functools.lru_cache(maxsize=4)  # a call that looks again decodes its image once
def decode(jpeg: bytes) -> np.ndarray:
    """HSV pixels (rows, cols, 3) of an image, decoded at most `MAX_WORK_WIDTH` wide (read-only:
    one array serves every look at the same image).

    A JPEG is decoded by libjpeg-turbo through simplejpeg, scaled in the DCT as PIL's draft
    mode does, and converted through PIL's own HSV conversion tabulated (`hsv_table`): the
    same pixels as PIL's decode and `convert("HSV")` (tests/test_reference_agent_units.py), in
    ~4 ms less an image (the embedded server's call cost 12.4-13.7 ms of CPU at 1280x960, ~70 %
    decode and conversion; docs/PERFORMANCE.md, "Embedded server"). Anything else through
    PIL (`decode_with_pil`)."""
    try:
        height, width = simplejpeg.decode_jpeg_header(jpeg)[:2]
    except ValueError:  # not a JPEG
        return decode_with_pil(jpeg)
    scale = math.ceil(width / MAX_WORK_WIDTH) if width > MAX_WORK_WIDTH else 1
    bgrx = simplejpeg.decode_jpeg(
        jpeg, "BGRX", min_width=width // scale, min_height=height // scale
    )
    rgb = bgrx.view(np.uint32)[..., 0] & np.uint32(0xFFFFFF)  # R << 16 | G << 8 | B
    table = hsv_table()
    planes = np.empty((3, *rgb.shape), np.uint8)
    for channel in range(3):
        np.take(table[channel], rgb, out=planes[channel])
    hsv = planes.transpose(1, 2, 0)  # each channel contiguous: the masks read one at a time
    hsv.flags.writeable = False
    return hsv


def decode_with_pil(image: bytes) -> np.ndarray:
    """`decode` by PIL alone (any format): the reference `decode` matches."""
    im: Image.Image = Image.open(io.BytesIO(image))
    if im.width > MAX_WORK_WIDTH:
        scale = math.ceil(im.width / MAX_WORK_WIDTH)
        im.draft("RGB", (im.width // scale, im.height // scale))
    if im.mode != "RGB":  # a JPEG decodes to RGB: converting it again would only copy it
        im = im.convert("RGB")
    hsv = np.asarray(im.convert("HSV"))
    hsv.flags.writeable = False
    return hsv


_TABLE: np.ndarray | None = None
_TABLE_LOCK = threading.Lock()


def hsv_table() -> np.ndarray:
    """(3, 2**24) uint8: PIL's HSV of every RGB colour, indexed R << 16 | G << 8 | B, made by
    PIL's own conversion (so it agrees by construction). 48 MB, made once in ~1 s and kept in
    a file of the user's cache, memory-mapped: the embedded server's policy processes share
    one copy. Where the file cannot be written, kept in memory."""
    global _TABLE
    with _TABLE_LOCK:
        if _TABLE is None:
            _TABLE = _load_or_make_table()
        return _TABLE


def _table_path() -> Path:
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "vabench" / f"hsv-table-pil{PIL.__version__}.npy"


def _load_or_make_table() -> np.ndarray:
    path = _table_path()
    try:
        table = np.load(path, mmap_mode="r")
        if table.shape == (3, 1 << 24) and table.dtype == np.uint8:
            return table
    except (OSError, ValueError):
        pass
    table = _make_table()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".npy", delete=False) as f:
            np.save(f, table)
        os.replace(f.name, path)  # whole or absent: processes may race to make it
        return np.load(path, mmap_mode="r")
    except OSError:
        return table


def _make_table() -> np.ndarray:
    index = np.arange(1 << 24, dtype=np.uint32)
    rgb = np.empty((1 << 24, 3), np.uint8)
    rgb[:, 0], rgb[:, 1], rgb[:, 2] = index >> 16, (index >> 8) & 255, index & 255
    hsv = np.asarray(Image.fromarray(rgb.reshape(4096, 4096, 3), "RGB").convert("HSV"))
    return np.ascontiguousarray(hsv.reshape(-1, 3).T)


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
