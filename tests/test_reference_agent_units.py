"""The reference agent's parts on hand-made inputs: segmentation, the dual-arm perception on a
drawn topdown image whose geometry is known, and the executor's multi-arm steps.

Expected values come from how the inputs were drawn (pixel geometry of the topdown camera,
FACTS.md: camera 0.68 m above the view's centre, vertical FOV 55 deg), not from the code under
test.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image, ImageDraw

from vabench.reference_agent import geometry as g
from vabench.reference_agent.executor import decide
from vabench.reference_agent.grasp_check import in_hand
from vabench.reference_agent.perception_dual import locate_block, locate_pot
from vabench.reference_agent.perception_generic import largest_object, upright_axis
from vabench.reference_agent.request import Arm, Observation
from vabench.reference_agent.segment import components

TABLE_RGB = (164, 150, 126)  # the table's beige (hue ~26, saturation ~47, value ~160)
W, H = 640, 480
PARK = {"left": np.array([-0.38, -0.25, 1.05]), "right": np.array([0.38, -0.25, 1.05])}


def _jpeg(im: Image.Image) -> bytes:
    buf = io.BytesIO()
    im.save(buf, "JPEG", quality=95)
    return buf.getvalue()


def _hsv(im: Image.Image) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(_jpeg(im))).convert("RGB").convert("HSV"))


def _camera() -> g.TopdownCamera:
    centre = (PARK["left"] + PARK["right"]) / 2
    return g.topdown_camera(tuple(centre), W, H)  # type: ignore[arg-type]


def _pixel(cam: g.TopdownCamera, x: float, y: float, z: float) -> tuple[float, float]:
    """Where the world point (x, y, z) appears: the pinhole model written out by hand."""
    f = (H / 2) / math.tan(math.radians(55 / 2))
    s = f / (cam.z - z)
    return W / 2 + (x - cam.x) * s, H / 2 - (y - cam.y) * s


def _polygon(cam, pts, z):
    return [_pixel(cam, x, y, z) for x, y in pts]


def _rect(cx, cy, half_len, half_wid, heading_deg):
    a = math.radians(heading_deg)
    u, v = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    c = np.array([cx, cy])
    return [
        tuple(c + su * half_len * u + sv * half_wid * v)
        for su, sv in ((1, 1), (-1, 1), (-1, -1), (1, -1))
    ]


def test_components_are_8_connected_and_sorted_by_size():
    m = np.zeros((10, 12), bool)
    m[1:4, 1:4] = True  # 9 pixels
    m[4, 4] = True  # touches the first block diagonally: same piece
    m[6:9, 7:11] = True  # 12 pixels, apart
    m[0, 11] = True  # a speck
    pieces = components(m)
    assert [len(r) for r, _ in pieces] == [12, 10, 1]
    assert [len(r) for r, _ in components(m, min_pixels=2)] == [12, 10]
    rows, cols = pieces[1]
    assert (4, 4) in set(zip(rows.tolist(), cols.tolist(), strict=True))


@pytest.mark.parametrize("heading", [-20.0, 0.0, 15.0])
def test_pot_centre_and_handle_axis_from_a_drawn_view(heading):
    cam = _camera()
    cx, cy, top = 0.03, -0.02, 0.741 + 0.105
    im = Image.new("RGB", (W, H), TABLE_RGB)
    d = ImageDraw.Draw(im)
    a = math.radians(heading)
    for sign in (-1, 1):  # dark handles 112.5 mm out along the pot's axis
        hx, hy = cx + sign * 0.1125 * math.cos(a), cy + sign * 0.1125 * math.sin(a)
        d.polygon(_polygon(cam, _rect(hx, hy, 0.0325, 0.012, heading), 0.741 + 0.093), (30, 30, 30))
    for r, colour in ((0.088, (200, 40, 30)), (0.078, (38, 38, 38))):  # red rim, dark inside
        u0, v0 = _pixel(cam, cx - r, cy + r, top)
        u1, v1 = _pixel(cam, cx + r, cy - r, top)
        d.ellipse([u0, v0, u1, v1], fill=colour)
    scene = locate_pot(_hsv(im), cam, PARK)
    assert scene is not None
    pot = scene["pot"]
    assert math.hypot(pot.x - cx, pot.y - cy) < 0.003
    assert abs(g.wrap(pot.heading - heading, 180.0)) < 3.0


def test_block_centre_and_heading_and_the_parked_fingers_are_ignored():
    cam = _camera()
    im = Image.new("RGB", (W, H), TABLE_RGB)
    d = ImageDraw.Draw(im)
    d.polygon(_polygon(cam, _rect(-0.17, -0.03, 0.10, 0.015, 90.0), 0.771), (242, 115, 20))
    for gc in PARK.values():  # orange finger pads under each parked gripper, larger than the block
        u, v = _pixel(cam, gc[0], gc[1], gc[2])
        d.rectangle([u - 30, v - 30, u + 30, v + 30], fill=(242, 140, 38))
    scene = locate_block(_hsv(im), cam, PARK)
    assert scene is not None
    b = scene["block"]
    assert math.hypot(b.x + 0.17, b.y + 0.03) < 0.003
    assert abs(g.wrap(b.heading - 90.0, 180.0)) < 2.0


def _arm(gc, rx, ry, is_open=True) -> Arm:
    rx, ry = np.array(rx, float), np.array(ry, float)
    return Arm(np.array(gc, float), rx, ry, np.cross(rx, ry), is_open, True, True)


def _obs(arms: dict[str, Arm], memo: dict) -> Observation:
    image = _jpeg(Image.new("RGB", (W, H), TABLE_RGB))
    return Observation(1, "Lift the pot.", "both_topdown", arms, 0, image, memo, (image,))


DOWN_X = {"rx": (0, 0, -1), "ry": (1, 0, 0)}  # fingers down, closing along x


def test_dual_move_sends_both_arms_and_one_arm_alone_when_the_other_is_there():
    arms = {"left": _arm((-0.2, 0, 1.0), **DOWN_X), "right": _arm((0.2, 0, 1.0), **DOWN_X)}
    memo = {"f": "pot", "plan": [["dgo", [-0.2, 0, 0.9], [0.2, 0, 0.95], "z"]], "i": 0}
    action, _, _ = decide(_obs(arms, memo), "pot")
    assert action == {
        "action": "dual_gripper.move_world",
        "left": {"axis": "z", "sign": "-", "distance_mm": 100.0},
        "right": {"axis": "z", "sign": "-", "distance_mm": 50.0},
    }
    arms["right"] = _arm((0.2, 0, 0.95), **DOWN_X)
    action, _, _ = decide(_obs(arms, memo), "pot")
    assert action == {
        "action": "gripper.move_world",
        "axis": "z",
        "sign": "-",
        "distance_mm": 100.0,
        "arm": "left",
    }


def test_standing_up_turns_about_the_closing_axis():
    """Fingers down and closing along x: only a turn about ry brings the approach to +y (a
    turn about rz, which points along y, cannot), in steps of at most 45 deg."""
    arms = {"left": _arm((-0.2, 0, 1.0), **DOWN_X), "right": _arm((0.2, 0, 1.0), **DOWN_X)}
    memo = {"f": "handover", "plan": [["fwd:left", 45]], "i": 0}
    action, _, _ = decide(_obs(arms, memo), "handover")
    assert action is not None
    assert (action["action"], action["axis"], action["angle_deg"], action["arm"]) == (
        "gripper.rotate_local",
        "ry",
        45.0,
        "left",
    )


def test_a_relative_turn_becomes_an_absolute_heading_once():
    arms = {"left": _arm((-0.2, 0, 1.0), **DOWN_X), "right": _arm((0.2, 0, 1.0), **DOWN_X)}
    memo = {"f": "shoe", "plan": [["turn:right", 90.0]], "i": 0}
    action, _, memo = decide(_obs(arms, memo), "shoe")
    assert memo["plan"][0] == ["yaw:right", 90.0, 360.0]  # ry heading 0 + 90
    # rx points down: a right-hand turn about rx turns ry clockwise seen from above, so a
    # counter-clockwise quarter turn is -90 about rx
    assert action is not None
    assert (action["axis"], action["sign"], action["angle_deg"]) == ("rx", "-", 90.0)


def _side_view(object_below_gc_m: float | None) -> np.ndarray:
    """A drawn side view centred on GC (camera 0.58 m out, 0.06 m up: ~0.58 m away) with a
    50 mm red cube whose centre is `object_below_gc_m` below GC, or no object."""
    im = Image.new("RGB", (W, H), TABLE_RGB)
    if object_below_gc_m is not None:
        s = (H / 2) / math.tan(math.radians(55 / 2)) / math.hypot(0.58, 0.02, 0.06)
        v = H / 2 + object_below_gc_m * s
        ImageDraw.Draw(im).rectangle(
            [W / 2 - 0.025 * s, v - 0.025 * s, W / 2 + 0.025 * s, v + 0.025 * s], fill=(200, 30, 25)
        )
    return _hsv(im)


def test_grasp_check_sees_a_held_object_and_not_one_left_below():
    gc = np.array([0.2, -0.1, 0.85])
    assert in_hand(_side_view(0.005), gc)  # held, GC 5 mm above the cube's centre
    assert not in_hand(_side_view(0.06 + 0.005), gc)  # left on the table, the gripper rose 60 mm
    assert not in_hand(_side_view(None), gc)


def test_an_empty_grasp_opens_and_starts_over():
    right = _arm((0.2, -0.1, 0.85), **DOWN_X, is_open=False)
    image = _jpeg(Image.fromarray(np.asarray(Image.new("RGB", (W, H), TABLE_RGB))))
    memo = {"f": "cube", "plan": [["hold", [["retry"]]], ["go", 0.2, -0.1, 0.9, "z"]], "i": 0}
    obs = Observation(
        9, "Pick up the red cube.", "side", {"right": right}, 8, image, memo, (image,)
    )
    action, _, memo = decide(obs, "cube")
    assert action == {"action": "gripper.open"}
    assert memo["plan"] == [["open"], ["retry"]]


def _hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Convex hull (Andrew's monotone chain), for drawing a prism's silhouette."""
    pts = sorted(set(points))

    def half(seq):
        out: list[tuple[float, float]] = []
        for p in seq:
            while (
                len(out) >= 2
                and (
                    (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                    - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])
                )
                <= 0
            ):
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(reversed(pts))
    return lower[:-1] + upper[:-1]


@pytest.mark.parametrize(
    ("half", "height", "yaw"), [(0.025, 0.22, 0.0), (0.032, 0.168, 0.0), (0.025, 0.22, 30.0)]
)
def test_upright_axis_from_the_silhouette_bottom(half, height, yaw):
    """An upright square prism (a held-out bottle's shape) drawn as the parked topdown camera
    sees it: its axis comes back within 6 mm whatever its height (never given)."""
    park = (0.38, -0.25, 1.05)
    cam = g.topdown_camera(park, W, H)
    cx, cy = 0.25, -0.05
    base = _rect(cx, cy, half, half, yaw)
    corners = [_pixel(cam, x, y, z) for x, y in base for z in (0.741, 0.741 + height)]
    im = Image.new("RGB", (W, H), TABLE_RGB)
    ImageDraw.Draw(im).polygon(_hull(corners), fill=(240, 120, 20))
    piece = largest_object(_hsv(im), cam)
    assert piece is not None
    x, y = upright_axis(*piece, cam)
    assert math.hypot(x - cx, y - cy) < 0.006


# -- decoding: libjpeg-turbo and a table of PIL's HSV, the same pixels as PIL ------------------
def test_the_hsv_table_is_pils_conversion_and_kept_in_the_cache(tmp_path, monkeypatch):
    """The table holds PIL's HSV of every colour at R << 16 | G << 8 | B; it is made once,
    written whole to the user's cache and read back memory-mapped by the next process."""
    from vabench.reference_agent import vision

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(vision, "_TABLE", None)
    table = vision.hsv_table()
    assert table.shape == (3, 1 << 24) and isinstance(table, np.memmap)
    (cached,) = (tmp_path / "vabench").glob("hsv-table-*.npy")
    colours = np.random.default_rng(0).integers(0, 256, (100_000, 3), dtype=np.uint8)
    colours[:4] = [(0, 0, 0), (255, 255, 255), (255, 0, 0), (164, 150, 126)]
    expected = np.asarray(Image.fromarray(colours.reshape(1, -1, 3), "RGB").convert("HSV"))[0]
    index = (colours[:, 0].astype(np.uint32) << 16) | (colours[:, 1].astype(np.uint32) << 8)
    index |= colours[:, 2]
    np.testing.assert_array_equal(table[:, index].T, expected)
    monkeypatch.setattr(vision, "_TABLE", None)  # a later process: reads the file
    stamp = cached.stat().st_mtime_ns
    np.testing.assert_array_equal(vision.hsv_table()[:, index].T, expected)
    assert cached.stat().st_mtime_ns == stamp


def _scene_like(width: int, height: int) -> Image.Image:
    """A table, objects of each colour the agent looks for, gradients and noise: every hue."""
    rng = np.random.default_rng(width)
    y, x = np.mgrid[0:height, 0:width]
    rgb = np.empty((height, width, 3), np.uint8)
    rgb[..., 0] = (x * 255 // max(1, width - 1)).astype(np.uint8)
    rgb[..., 1] = (y * 255 // max(1, height - 1)).astype(np.uint8)
    rgb[..., 2] = ((x + y) % 256).astype(np.uint8)
    im = Image.fromarray(rgb, "RGB")
    draw = ImageDraw.Draw(im)
    draw.rectangle((width // 8, height // 8, width * 7 // 8, height * 7 // 8), fill=TABLE_RGB)
    for i, fill in enumerate(((200, 30, 30), (30, 60, 200), (40, 170, 60), (220, 200, 40))):
        x0 = width // 5 + i * width // 7
        draw.ellipse((x0, height // 3, x0 + width // 10, height // 3 + width // 10), fill=fill)
    noisy = np.asarray(im).astype(np.int16) + rng.integers(-6, 7, (height, width, 3))
    return Image.fromarray(np.clip(noisy, 0, 255).astype(np.uint8), "RGB")


@pytest.mark.parametrize("size", [(1280, 960), (1280, 720), (640, 480), (160, 120)])
def test_decode_gives_pils_pixels(size):
    """libjpeg-turbo through simplejpeg (DCT-scaled like PIL's draft) and the table: the very
    pixels of PIL's decode and convert("HSV"), for JPEGs as the engine makes them (q95, 4:2:0)
    and as PIL makes them; anything else goes through PIL."""
    import simplejpeg

    from vabench.reference_agent.vision import decode, decode_with_pil

    im = _scene_like(*size)
    engine_jpeg = simplejpeg.encode_jpeg(np.asarray(im), quality=95, colorsubsampling="420")
    for image in (engine_jpeg, _jpeg(im)):
        fast, reference = decode(image), decode_with_pil(image)
        assert fast.shape == reference.shape and fast.shape[1] == min(size[0], 640)
        np.testing.assert_array_equal(fast, reference)
        assert not fast.flags.writeable  # shared by every look at the image: never changed
    png = io.BytesIO()
    im.save(png, "PNG")
    np.testing.assert_array_equal(decode(png.getvalue()), decode_with_pil(png.getvalue()))
