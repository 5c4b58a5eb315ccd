"""put_everything_in_basket: put all five objects on the table into the basket, right arm.

The long-horizon track (paper sections 3.1 and 5; FACTS "Held-out variants and the long-horizon
track"): five objects drawn from the four atomic skills of its demonstrations (place_single_cube,
grasp_single_bottle, grasp_single_bottle_upright, grasp_single_pen), each its own colour:
- cube: the 5 cm red cube (cube_red_50.xml), yaw in [-45, 45] deg;
- small_cube: a 4 cm yellow cube (cube_yellow_40.xml), yaw in [-45, 45] deg;
- bottle: the blue water bottle (bottle_water.xml: body centre 60 mm from its bottom and 105 mm
  from the end of its neck) lying on a flat face, yaw (of its axis, from world +x) in
  [-22.5, 22.5] deg;
- upright_bottle: a green bottle of the same shape (bottle_green.xml) standing upright;
- pen: the purple marker of grasp_single_pen, colliding as a 140 x 14 x 14 mm box
  (pen_marker_flat.xml: MuJoCo 4.0.0's capsule-box contact throws a capsule dropped onto a box),
  lying flat, yaw in [-30, 30] deg;
and a brown basket (basket_brown.xml: an open box, interior 260 x 200 mm, walls 12 mm thick and
55 mm above its 24 mm floor, rim 79 mm above the table, 4 kg), axis-aligned, its centre at
x in [0.10, 0.14], y in [0.03, 0.05] (the far half of the right arm's workspace). The
composition is fixed; the poses vary by seed. The object centres are drawn, in the order
upright_bottle, bottle, cube, small_cube, pen, uniformly from x in [0.02, 0.40],
y in [-0.28, -0.10] (the near half), with rejection: each object's footprint (the rectangle
along its yaw that holds its collision hull: cubes 50 and 40 mm square, the lying bottle
165 x 63 mm, the pen 140 x 14 mm, the upright bottle 64 mm square) keeps at least 40 mm from
every other footprint and from the basket's outer rectangle, and the open fingers of a grasp
across the pen's centre (a 114 x 24 mm rectangle) keep 5 mm from every other footprint and the
basket (every grasp of the expert has room for its fingers). No object starts inside the basket.

Predicate (all now, no latch). An object is *inside* when its whole footprint lies inside the
basket's interior in x and y: every point of its collision hull (box corners; the 32 vertices of
a bottle's 16-gon body and the end of its neck, widened by the neck's 11 mm radius), expressed in
the basket's frame, lies within the 260 x 200 mm interior up to a 2 mm contact tolerance (an
object resting against a wall sinks into it a little). It is *released* when the right gripper
does not hold it (the gripper is open, or it does not touch the object). It is *supported* when
it touches the basket (the floor or the inner side of a wall: with its footprint inside the
interior that means below the rim) or another object that is itself inside and released (a
stack inside the basket counts; an object above the basket touching nothing does not). An
object is *placed* when it is inside, released and supported. Success: all five placed at once.
Budget 250 steps (five placements at place_cube_in_bowl's 50 each; the expert needs about 115).
Checkpoints: placed_1 .. placed_4, completed: subgoal k is "at least k objects placed now"
(order-independent, no per-object latch). Progress only moves forward (`advance_progress`), so
the checkpoint progress of an episode is the largest number of objects that lay placed in the
basket together at some step (5 exactly on success): it is the episode's "objects placed out of
five" of the paper's long-horizon table. `checks` holds `<object>_inside` and `<object>_placed`.
Expert: the objects in turn (EXPERT_ORDER: upright bottle, pen, lying bottle, red cube, yellow
cube): rise above everything, travel over the object, a top-down grasp as in its atomic family
(the upright bottle across two flat faces at the top of its body, GC 53 mm above its centre so
the palm clears the neck; the red cube with GC 5 mm below its centre, so the pads squeeze
across its centre of mass and do not tip it up out of the grasp; the small cube 5 mm above, as
place_cube_in_bowl), lift above the rim and above the standing bottle, turn the gripper so the
object lines up with the basket (long objects along its y), carry it over its own slot (SLOTS),
then: the upright bottle is lowered onto the floor (far left corner) and the pen to 3 mm above
it, and let go; the others are let go with the fingertips 8 mm above the rim and drop in.
Seeds are verified on C MuJoCo. Open issue: on MJX (4.0.0, CPU) the scene does not survive the
reset's settling (seed 1000: 163 deg drift; the bottles start to creep after ~200 steps and the
scene flies apart by ~800), while C MuJoCo holds it within 0.1 mm. Bisected: the two bottles
together with the arm (two bottles alone, or one bottle with the arm and the other objects, stay
still); excluding the bottle pair's contact made it worse (NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import BASKET_DEMONSTRATIONS, common
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import (
    TIP_BEYOND_GC,
    Evaluation,
    ObjectIndex,
    Sample,
    Script,
    SlotState,
    Task,
    yaw_quat,
)
from vabench.tasks.expert import ExpertContext, nearest, topdown

OBJECTS = ("upright_bottle", "bottle", "cube", "small_cube", "pen")
"""The five objects, in sampling order."""
EXPERT_ORDER = ("upright_bottle", "pen", "bottle", "cube", "small_cube")
"""The expert's order: the tall bottle first (then nothing on the table is taller than the
gripper's palm above a low grasp), the pen while its fingers still have room to reach down into
the basket, then the objects that are dropped in from the rim."""
FILES = {
    "cube": "cube_red_50.xml",
    "small_cube": "cube_yellow_40.xml",
    "bottle": "bottle_water.xml",
    "upright_bottle": "bottle_green.xml",
    "pen": "pen_marker_flat.xml",
}
CUBE_HALF = {"cube": 0.025, "small_cube": 0.02}
PEN_HALF_LEN = 0.07  # pen_marker_flat.xml: a 140 x 14 x 14 mm box collider

# Basket (basket_brown.xml): interior half-sizes, floor and rim heights above its origin.
INNER_HX, INNER_HY = 0.13, 0.10
INSIDE_TOL = 0.002  # soft contacts: an object resting against a wall sinks into it a little
OUTER_HX, OUTER_HY = 0.142, 0.112
FLOOR_TOP = 0.024
RIM = 0.079
BASKET_X, BASKET_Y = (0.10, 0.14), (0.03, 0.05)

# Objects on the table.
OBJ_X, OBJ_Y = (0.02, 0.40), (-0.28, -0.10)
YAW_DEG = {
    "cube": (-45.0, 45.0),
    "small_cube": (-45.0, 45.0),
    "bottle": (-22.5, 22.5),
    "upright_bottle": (0.0, 0.0),
    "pen": (-30.0, 30.0),
}
MIN_GAP = 0.04  # between footprints, and from the basket's outer rectangle
FINGERS_HALF = (0.012, 0.057)  # open fingers of a top-down grasp: along, across the object
FINGER_GAP = 0.005
MAX_TRIES = 100  # draws per object before the layout starts over
MAX_LAYOUTS = 1000


# -- footprint geometry (sampler) ------------------------------------------------------------
def rectangle(centre: np.ndarray, half: tuple[float, float], yaw: float) -> np.ndarray:
    """Corners (4, 2) of a rectangle with half-extents `half` along (yaw, yaw + 90 deg)."""
    c, s = np.cos(yaw), np.sin(yaw)
    u, v = np.array([c, s]) * half[0], np.array([-s, c]) * half[1]
    return np.array([centre + u + v, centre - u + v, centre - u - v, centre + u - v])


def _separated(a: np.ndarray, b: np.ndarray) -> bool:
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            normal = np.array([-edge[1], edge[0]])
            pa, pb = a @ normal, b @ normal
            if pa.max() < pb.min() or pb.max() < pa.min():
                return True
    return False


def _point_segments(p: np.ndarray, q: np.ndarray) -> float:
    """Smallest distance from the points p (n, 2) to the edges of the polygon q (4, 2)."""
    a, b = q, np.roll(q, -1, axis=0)
    ab = b - a
    t = np.einsum("nkd,kd->nk", p[:, None] - a[None], ab) / np.einsum("kd,kd->k", ab, ab)
    nearest_pt = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    return float(np.min(np.linalg.norm(p[:, None] - nearest_pt, axis=-1)))


def gap(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two convex quadrilaterals (0 when they overlap)."""
    if not _separated(a, b):
        return 0.0
    return min(_point_segments(a, b), _point_segments(b, a))


def clear(a: np.ndarray, b: np.ndarray, min_gap: float) -> bool:
    """gap(a, b) >= min_gap, with a cheap test on the enclosing circles first."""
    ca, cb = a.mean(0), b.mean(0)
    d = np.linalg.norm(ca - cb)
    if d - _radius(a, ca, max) - _radius(b, cb, max) >= min_gap:  # enclosing circles apart
        return True
    if d - _radius(a, ca, min) - _radius(b, cb, min) < min_gap:  # inscribed circles too close
        return False
    return gap(a, b) >= min_gap


def _radius(rect: np.ndarray, centre: np.ndarray, pick) -> float:
    """Enclosing (pick=max: the farthest corner) or inscribed (pick=min: half the shorter
    side) circle of a rectangle."""
    if pick is max:
        return float(np.max(np.linalg.norm(rect - centre, axis=1)))
    return float(min(np.linalg.norm(rect[1] - rect[0]), np.linalg.norm(rect[2] - rect[1])) / 2)


def basket_outline(xy: np.ndarray) -> np.ndarray:
    return rectangle(xy, (OUTER_HX, OUTER_HY), 0.0)


def pen_fingers(xy: np.ndarray, yaw: float) -> np.ndarray:
    return rectangle(xy, FINGERS_HALF, yaw)


def object_pose(name: str, xy: np.ndarray, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    if name == "pen":
        return sk.lying_pen_pose(xy[0], xy[1], yaw)
    if name == "bottle":
        return sk.lying_bottle_pose(xy[0], xy[1], yaw)
    if name == "upright_bottle":
        return sk.upright_bottle_pose(xy[0], xy[1])
    return np.array([xy[0], xy[1], rc.TABLE_Z + CUBE_HALF[name]]), yaw_quat(yaw)


# -- footprint geometry (predicate) ----------------------------------------------------------
def _bottle_hull() -> tuple[np.ndarray, np.ndarray]:
    ang = np.arange(16) * 2 * np.pi / 16
    ring = np.stack([sk.BOTTLE_VERTEX_R * np.cos(ang), sk.BOTTLE_VERTEX_R * np.sin(ang)], 1)
    body = np.concatenate(
        [np.c_[ring, np.full(16, z)] for z in (-sk.BOTTLE_HALF_H, sk.BOTTLE_HALF_H)]
    )
    points = np.concatenate([body, [[0.0, 0.0, 0.094]]])
    return points, np.r_[np.zeros(32), 0.011]


def _box_hull(half: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    hx, hy, hz = half
    corners = np.array([[x, y, z] for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)])
    return corners, np.zeros(8)


HULL = {
    "cube": _box_hull((CUBE_HALF["cube"],) * 3),
    "small_cube": _box_hull((CUBE_HALF["small_cube"],) * 3),
    "bottle": _bottle_hull(),
    "upright_bottle": _bottle_hull(),
    "pen": _box_hull((PEN_HALF_LEN, sk.PEN_RADIUS, sk.PEN_RADIUS)),
}
"""Per object: points of its collision hull in its own frame, and the radius each is widened
by (capsule ends), so that the footprint test is exact for boxes, prisms and capsules."""


def footprint(name: str, pose: tuple[np.ndarray, np.ndarray], yaw: float) -> np.ndarray:
    """The object's footprint on the table: the smallest rectangle along (yaw, yaw + 90 deg)
    that holds its collision hull (a bottle's hull is not centred on its origin: the body's
    centre is 60 mm from its bottom and 105 mm from the end of its neck)."""
    points, radius = HULL[name]
    pos, quat = pose
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.asarray(quat, float))
    world = (pos + points @ rot.reshape(3, 3).T)[:, :2]
    axes = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    local = world @ axes.T
    lo, hi = (local - radius[:, None]).min(0), (local + radius[:, None]).max(0)
    return rectangle((lo + hi) / 2 @ axes, tuple((hi - lo) / 2), yaw)


def inside_basket(ix: ObjectIndex, s: SlotState, obj: str) -> jax.Array:
    """Whether the object's whole footprint lies inside the basket's interior (x and y, in the
    basket's frame)."""
    points, radius = HULL[obj]
    world = ix.pos(s.qpos, obj) + jnp.asarray(points) @ ix.mat(s.qpos, obj).T
    local = (world - ix.pos(s.qpos, "basket")) @ ix.mat(s.qpos, "basket")
    r = jnp.asarray(radius)
    return jnp.all(jnp.abs(local[:, 0]) + r <= INNER_HX + INSIDE_TOL) & jnp.all(
        jnp.abs(local[:, 1]) + r <= INNER_HY + INSIDE_TOL
    )


def _object_pairs() -> tuple[tuple[str, str], ...]:
    return tuple((a, b) for i, a in enumerate(OBJECTS) for b in OBJECTS[i + 1 :])


# -- expert ----------------------------------------------------------------------------------
SLOTS = {
    "upright_bottle": (-0.085, 0.055),  # far left corner
    "cube": (-0.085, -0.055),  # near left corner
    "small_cube": (-0.02, -0.04),
    "pen": (0.02, 0.01),  # along the basket's y
    "bottle": (0.08, 0.0),  # along the basket's y, right side
}
"""Where the expert drops each object: the centre of its footprint in the basket's frame (the
footprints are at least 15 mm apart and 13 mm inside the walls). Long objects lie along the
basket's y axis, cubes square to it."""
UPRIGHT_GRASP_DZ = 0.053  # GC above the upright bottle's centre: the palm clears its neck
PEN_GRASP_DZ = sk.TOPDOWN_MIN_GC_Z + 0.001 - (rc.TABLE_Z + sk.PEN_RADIUS)
CUBE_GRASP_DZ = {"cube": -0.005, "small_cube": 0.005}  # GC above a cube's centre
PEN_DROP = 0.003  # the pen's bottom above the floor when it is let go
TIPS_ABOVE_RIM = 0.008  # the fingertips when the dropped objects are let go
CARRY_CLEARANCE = 0.03  # the held object's bottom above everything it passes over
UPRIGHT_TOP = 0.108  # the upright bottle's cap above its centre
UPRIGHT_HEIGHT = sk.BOTTLE_HALF_H + UPRIGHT_TOP


@dataclass(frozen=True)
class PutEverythingInBasket(Task):
    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        basket_xy = np.array([rng.uniform(*BASKET_X), rng.uniform(*BASKET_Y)])
        for _ in range(MAX_LAYOUTS):  # a crowded partial layout starts over
            poses = self._layout(rng, basket_outline(basket_xy))
            if poses is not None:
                poses["basket"] = (np.r_[basket_xy, rc.TABLE_Z], yaw_quat(0.0))
                return Sample(poses)
        raise RuntimeError(f"seed {seed}: no layout after {MAX_LAYOUTS} attempts")

    @staticmethod
    def _layout(rng: np.random.Generator, basket: np.ndarray) -> dict | None:
        taken = [basket]
        poses = {}
        for name in OBJECTS:
            for _ in range(MAX_TRIES):
                xy = np.array([rng.uniform(*OBJ_X), rng.uniform(*OBJ_Y)])
                yaw = np.radians(rng.uniform(*YAW_DEG[name]))
                pose = object_pose(name, xy, yaw)
                rect = footprint(name, pose, yaw)
                if not all(clear(rect, other, MIN_GAP) for other in taken):
                    continue
                if name == "pen" and any(
                    not clear(pen_fingers(xy, yaw), other, FINGER_GAP) for other in taken
                ):
                    continue
                break
            else:
                return None
            taken.append(rect)
            poses[name] = pose
        return poses

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        r = self.arm("right")
        inside = {o: inside_basket(ix, s, o) for o in OBJECTS}
        released = {o: s.grip_open[r] | ~self.contact(s, o, "right_gripper") for o in OBJECTS}
        placed = {}
        for o in OBJECTS:
            on_other = jnp.array(False)
            for a, b in _object_pairs():
                if o in (a, b):
                    other = b if o == a else a
                    on_other |= self.contact(s, a, b) & inside[other] & released[other]
            supported = self.contact(s, o, "basket") | on_other
            placed[o] = inside[o] & released[o] & supported
        count = jnp.sum(jnp.array([placed[o] for o in OBJECTS]))
        checks = {f"{o}_inside": inside[o] for o in OBJECTS}
        checks |= {f"{o}_placed": placed[o] for o in OBJECTS}
        subgoals = jnp.array([count >= k for k in range(1, len(OBJECTS))])
        return Evaluation(
            checks=checks, latched=latched, subgoals=subgoals, success=count == len(OBJECTS)
        )

    # -- expert -------------------------------------------------------------------------------
    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        travel_z = (
            ctx.view.pos("basket")[2] + FLOOR_TOP + UPRIGHT_HEIGHT + CARRY_CLEARANCE + TIP_BEYOND_GC
        )
        for name in EXPERT_ORDER:
            # above everything, over to the object, then down onto it
            gc = ctx.view.arms["right"].gc
            yield from ctx.move_to("right", np.r_[gc[:2], max(gc[2], travel_z)], order="z")
            over = np.r_[ctx.view.pos(name)[:2], ctx.view.arms["right"].gc[2]]
            yield from ctx.move_to("right", over, order="yx")
            yield from self._grasp(ctx, name)
            yield from self._put_in(ctx, name)

    def _grasp(self, ctx: ExpertContext, name: str) -> Script:
        mat = ctx.view.mat(name)
        if name == "upright_bottle":
            # across two flat faces of the 16-gon (face normals at 11.25 + k 22.5 deg): a pinch
            # on two vertical edges lets the bottle turn in the fingers
            across = sk.axis_heading(mat, 0) + np.pi / 16
            dz = UPRIGHT_GRASP_DZ
        elif name == "bottle":
            across, dz = sk.axis_heading(mat, 2) + np.pi / 2, 0.0
        elif name == "pen":
            across, dz = sk.axis_heading(mat, 0) + np.pi / 2, PEN_GRASP_DZ
        else:
            yield from common.topdown_grasp(ctx, "right", name, grasp_dz=CUBE_GRASP_DZ[name])
            return
        yield from sk.topdown_grasp_at(ctx, "right", lambda v: v.pos(name) + [0.0, 0.0, dz], across)

    def _put_in(self, ctx: ExpertContext, name: str) -> Script:
        basket = ctx.view.pos("basket")
        floor = basket[2] + FLOOR_TOP
        gc = ctx.view.arms["right"].gc
        below = gc[2] - self._hull(ctx, name)[:, 2].min()  # GC above the held object's bottom
        top = basket[2] + RIM
        if name != "upright_bottle":
            top = max(top, ctx.view.pos("upright_bottle")[2] + UPRIGHT_TOP)
        carry_z = top + CARRY_CLEARANCE + below
        yield from ctx.move_to("right", np.r_[gc[:2], carry_z], order="z")
        # line the object up with the basket: long objects along its y (the fingers close
        # along x), cubes square to it
        turns = 4 if name in CUBE_HALF else 2
        goal = [topdown(k * 2 * np.pi / turns) for k in range(turns)]
        yield from ctx.rotate_to("right", nearest(ctx.view.arms["right"].rot, goal))
        hull = self._hull(ctx, name)
        centre = (hull[:, :2].min(0) + hull[:, :2].max(0)) / 2
        slot = basket[:2] + SLOTS[name] + ctx.view.arms["right"].gc[:2] - centre
        yield from ctx.move_to("right", np.r_[slot, carry_z], order="xyz")
        if name == "upright_bottle":
            rest = floor + sk.BOTTLE_HALF_H
            yield from common.lower_until_resting(ctx, "right", name, rest)
        elif name == "pen":  # lowered to just above the floor: the fingers have room there
            release_z = floor + PEN_DROP + below
        else:  # drop it in from just above the rim
            release_z = basket[2] + RIM + TIPS_ABOVE_RIM + TIP_BEYOND_GC
            yield from ctx.move_to("right", np.r_[slot, release_z], order="z")
        yield from ctx.grip("right", close=False)

    @staticmethod
    def _hull(ctx: ExpertContext, name: str) -> np.ndarray:
        """World points of the object's collision hull, widened downwards and sideways by each
        point's radius (a bounding set for heights and footprints)."""
        points, radius = HULL[name]
        world = ctx.view.pos(name) + points @ ctx.view.mat(name).T
        r = radius[:, None]
        return np.concatenate([world - r, world + r])


TASK = PutEverythingInBasket(
    name="put_everything_in_basket",
    instruction="Put every object on the table into the basket.",
    step_budget=250,
    checkpoints=("placed_1", "placed_2", "placed_3", "placed_4", "completed"),
    contact_pairs=(
        *((o, "right_gripper") for o in OBJECTS),
        *((o, "basket") for o in OBJECTS),
        *_object_pairs(),
    ),
    objects=(*((name, FILES[name]) for name in OBJECTS), ("basket", "basket_brown.xml")),
    suite="long_horizon",
    demonstrations=BASKET_DEMONSTRATIONS,
)
