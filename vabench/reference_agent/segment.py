"""Colour-free segmentation of the topdown image: what is neither table nor robot, in pieces.

Held-out objects, shoes and basket objects come in colours the per-family colour table does
not list, so these tools do not ask for a colour. The scene's background is known: the beige
table top (hue ~26, saturation ~47), its shadows (the same hue and saturation, darker), and the
dark grey robot and floor (saturation < 60, value < 60). An object is what differs from all
three: a saturated colour (saturation >= 90, any hue), or a bright near-white part (labels,
caps, trims: value >= 190, saturation < 40). Black object parts look like the robot by colour;
the callers find those by where they are (`dark`).

`components(mask)` splits a mask into connected pieces (8-connectivity) with a run-length
union-find: each row's runs are joined to the overlapping runs of the row above, so the cost
grows with the number of runs, not of pixels, and numpy and the standard library suffice.
"""

from __future__ import annotations

import math

import numpy as np

from vabench.reference_agent.geometry import TopdownCamera
from vabench.reference_agent.vision import opened

MIN_SATURATION = 90  # the table and its shadows: ~47-55; objects: > 100
WHITE_VALUE, WHITE_MAX_SATURATION = 190, 40
DARK_VALUE = 60  # robot, floor, black object parts; table shadows are ~85-95
GRIPPER_MASK_M = 0.10  # around a parked gripper's projection (GC plane): its finger pads are
# orange, like some objects


def saturated(hsv: np.ndarray) -> np.ndarray:
    return hsv[..., 1] >= MIN_SATURATION


def white(hsv: np.ndarray) -> np.ndarray:
    return (hsv[..., 2] >= WHITE_VALUE) & (hsv[..., 1] < WHITE_MAX_SATURATION)


def dark(hsv: np.ndarray) -> np.ndarray:
    return hsv[..., 2] < DARK_VALUE


def foreground(hsv: np.ndarray) -> np.ndarray:
    """Object pixels by colour alone (saturated or white), opened so specks drop out."""
    return opened(saturated(hsv) | white(hsv))


def hue_mask(hsv: np.ndarray, lo: int, hi: int, min_s: int = MIN_SATURATION) -> np.ndarray:
    """Saturated pixels with PIL hue in [lo, hi] (wrapping through 255 when lo > hi)."""
    h = hsv[..., 0]
    hue = (h >= lo) & (h <= hi) if lo <= hi else (h >= lo) | (h <= hi)
    return hue & (hsv[..., 1] >= min_s)


def _runs(row: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) column ranges of the True runs of a boolean row."""
    padded = np.concatenate(([False], row, [False]))
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist(), strict=True))


def components(mask: np.ndarray, min_pixels: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 8-connected pieces of `mask` as (rows, cols) index arrays, largest first; pieces
    smaller than `min_pixels` are dropped."""
    parent: list[int] = []

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    runs: list[tuple[int, int, int]] = []  # (row, start, end)
    above: list[int] = []  # run ids of the previous row
    for r in range(mask.shape[0]):
        here = []
        for start, end in _runs(mask[r]):
            rid = len(runs)
            runs.append((r, start, end))
            parent.append(rid)
            for other in above:
                _, s2, e2 = runs[other]
                if s2 <= end and start <= e2:  # overlap or touch diagonally (8-connected)
                    ra, rb = find(rid), find(other)
                    if ra != rb:
                        parent[max(ra, rb)] = min(ra, rb)
            here.append(rid)
        above = here
    groups: dict[int, list[int]] = {}
    for rid in range(len(runs)):
        groups.setdefault(find(rid), []).append(rid)
    out = []
    for members in groups.values():
        rows = np.concatenate([np.full(runs[m][2] - runs[m][1], runs[m][0]) for m in members])
        cols = np.concatenate([np.arange(runs[m][1], runs[m][2]) for m in members])
        if len(rows) >= min_pixels:
            out.append((rows, cols))
    out.sort(key=lambda rc: -len(rc[0]))
    return out


def without_grippers(
    mask: np.ndarray,
    cam: TopdownCamera,
    gcs: dict[str, np.ndarray],
    radius: float = GRIPPER_MASK_M,
) -> np.ndarray:
    """`mask` with the pixels within `radius` (m, on the GC plane) of each gripper's
    projection cleared."""
    rows, cols = np.indices(mask.shape)
    out = mask.copy()
    for gc in gcs.values():
        scale = cam.focal_px / max(1e-3, cam.z - float(gc[2]))
        u = cam.width / 2 + (float(gc[0]) - cam.x) * scale
        v = cam.height / 2 - (float(gc[1]) - cam.y) * scale
        out &= (cols - u) ** 2 + (rows - v) ** 2 > (radius * scale) ** 2
    return out


def axis_heading(points: np.ndarray, centre: np.ndarray) -> float:
    """Heading (deg, in (-90, 90]) of the principal axis of `points` about `centre`."""
    d = points - centre
    sxx, syy, sxy = (d[:, 0] ** 2).mean(), (d[:, 1] ** 2).mean(), (d[:, 0] * d[:, 1]).mean()
    h = 0.5 * math.degrees(math.atan2(2 * sxy, sxx - syy))
    return h if h > -90 else h + 180
