"""place_shoe: put the shoe on the mat with its toe pointing left (-x), the arm on its side.

Scene (paper Table tab:seed-spec-dual): one shoe of ten model ids (`assets/objects/shoe_<k>.xml`,
identical structure: a box sole with rolling friction, a capsule upper along the shoe, a toe box;
visual upper shell, toe cap, heel counter, collar and laces; lengths 0.20-0.26 m, widths
0.070-0.080 m, upper heights, masses 0.22-0.32 kg and colours differ) at x in [-0.25, 0.25],
y in [-0.10, 0.05]; draws with horizontal radius sqrt(x^2 + y^2) < 0.15 m are rejected and
redrawn (deterministically, from the same seed's generator). The table gives no initial yaw:
the shoe always starts with its toe towards +y (yaw +90 deg), so placing it toe towards -x
needs a real 90 deg reorientation. The shoe frame's origin is the bottom centre of the sole,
toe towards +x of the frame: it rests at z = table height.
Target: a mat centred at (0, -0.08), 0.28 x 0.10 m. The mat is purely visual (a 1 mm geom of
the world body, no collision): it marks the target for the camera and cannot be pushed, and a
shoe drawn close to it never starts intersecting it.
Both arms are in the scene; the arm on the shoe's side does the task (x > 0: right, else left),
stored in `Sample.params["arm"]`.
Success (all now, nothing latched): the shoe origin's x error to the target (0, -0.08) < 50 mm
and y error < 20 mm; the shoe quaternion within 0.07 of the target quaternion (toe towards -x:
yaw 180 deg, wxyz (0, 0, 0, 1)) in every component, up to sign (q and -q are one rotation);
both grippers open. Budget 100 steps.
Checkpoints: reached (a GC within 60 mm of the point 50 mm above the shoe origin, i.e. at the
upper), grasped (a closed gripper touching the shoe), lifted (> 50 mm), transported (x, y and
quaternion within tolerance), completed.
Expert: with the arm on the shoe's side, a top-down grasp across the upper (fingers along the
shoe's width, above the centre of mass), lift, turn the gripper about the vertical until the toe
points to -x (+90 deg), carry the shoe origin over the mat centre, lower it to 3 mm above the
table, open and back off upwards; should the shoe have turned on release, grasp and place it
again (at most 3 attempts).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext, ExpertFailed, View, nearest, topdown, yaw_of
from vabench.tasks.objects import attach_object, object_path

N_SHOES = 10
X_RANGE, Y_RANGE, MIN_RADIUS = (-0.25, 0.25), (-0.10, 0.05), 0.15
INIT_YAW = np.pi / 2  # toe towards +y
TARGET_XY = (0.0, -0.08)
TARGET_YAW = np.pi  # toe towards -x
TARGET_QUAT = yaw_quat(TARGET_YAW)
X_TOL, Y_TOL, QUAT_TOL = 0.05, 0.02, 0.07
MAT_HALF = (0.14, 0.05, 0.0005)
REACH_M = 0.06
RELEASE_HEIGHT = 0.003  # the expert opens with the sole this far above the table
MAX_ATTEMPTS = 3  # the expert re-grasps a shoe that turned on release


def shoe_file(variant: int) -> str:
    return f"shoe_{variant}.xml"


@functools.cache
def grasp_point_local(variant: int) -> np.ndarray:
    """The expert's grasp point in the shoe frame: above the centre of mass (so the shoe lifts
    level instead of pivoting on its toe or heel), on the upper's axis (its widest line); read
    from the model file."""
    model = mujoco.MjModel.from_xml_path(str(object_path(shoe_file(variant))))
    upper = model.geom("upper")
    com = model.body("shoe").ipos
    return np.array([com[0], 0.0, upper.pos[2]])


def quat_error(q: jax.Array, target: jax.Array) -> jax.Array:
    """Largest component error between two unit quaternions, up to sign (q = -q)."""
    q = q / jnp.linalg.norm(q)
    return jnp.minimum(jnp.max(jnp.abs(q - target)), jnp.max(jnp.abs(q + target)))


def sample_xy(rng: np.random.Generator) -> tuple[float, float]:
    while True:
        x, y = rng.uniform(*X_RANGE), rng.uniform(*Y_RANGE)
        if np.hypot(x, y) >= MIN_RADIUS:
            return float(x), float(y)


@dataclass(frozen=True)
class PlaceShoe(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, shoe_file(variant), "shoe")
        spec.worldbody.add_geom(
            name="mat",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=list(MAT_HALF),
            pos=[TARGET_XY[0], TARGET_XY[1], rc.TABLE_Z + MAT_HALF[2]],
            rgba=[0.15, 0.15, 0.55, 1.0],
            contype=0,
            conaffinity=0,
            group=2,
        )

    def sample(self, seed: int) -> Sample:
        rng = self.rng(seed)
        x, y = sample_xy(rng)
        variant = int(rng.integers(N_SHOES))
        arm = "right" if x > 0 else "left"
        pose = (np.array([x, y, rc.TABLE_Z]), yaw_quat(INIT_YAW))
        return Sample({"shoe": pose}, variant=variant, params={"arm": arm})

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        p = ix.pos(s.qpos, "shoe")
        x_ok = jnp.abs(p[0] - TARGET_XY[0]) < X_TOL
        y_ok = jnp.abs(p[1] - TARGET_XY[1]) < Y_TOL
        quat_ok = quat_error(ix.quat(s.qpos, "shoe"), jnp.asarray(TARGET_QUAT)) < QUAT_TOL
        both_open = jnp.all(s.grip_open)
        upper = p + ix.mat(s.qpos, "shoe") @ jnp.array([0.0, 0.0, 0.05])
        touching = [self.contact(s, "shoe", f"{a}_gripper") for a in self.arms]
        arms = range(len(self.arms))
        subgoals = jnp.array(
            [
                jnp.any(jnp.array([common.near(s, a, upper, REACH_M) for a in arms])),
                jnp.any(jnp.array([common.holding(s, a, touching[a]) for a in arms])),
                common.lifted(ix, s, "shoe"),
                x_ok & y_ok & quat_ok,
            ]
        )
        return Evaluation(
            checks={"x_ok": x_ok, "y_ok": y_ok, "quat_ok": quat_ok, "grippers_open": both_open},
            latched=latched,
            subgoals=subgoals,
            success=x_ok & y_ok & quat_ok & both_open,
        )

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        arm = sample.params["arm"]
        grasp_local = grasp_point_local(sample.variant)
        for _ in range(MAX_ATTEMPTS):
            yield from place_once(ctx, arm, grasp_local)
            shoe_up = ctx.view.mat("shoe")[2, 2]
            if ctx.view.pos("shoe")[2] > rc.TABLE_Z + 0.01 or shoe_up < 0.95:
                raise ExpertFailed("the shoe fell over or is out of reach")


def place_once(ctx: ExpertContext, arm: str, grasp_local: np.ndarray) -> Script:
    """Grasp the shoe where it lies (top-down across its width, above its centre of mass),
    lift, turn it toe towards -x, lower its origin onto the mat centre, open, back off."""

    def grasp_point(v: View) -> np.ndarray:
        return v.pos("shoe") + v.mat("shoe") @ grasp_local

    shoe_yaw = yaw_of(ctx.view.mat("shoe"))
    goal = nearest(
        ctx.view.arms[arm].rot, [topdown(shoe_yaw + np.pi / 2), topdown(shoe_yaw - np.pi / 2)]
    )
    yield from ctx.rotate_to(arm, goal)
    yield from ctx.move_to(arm, lambda v: grasp_point(v) + [0, 0, 0.08], order="zxy")
    yield from ctx.move_to(arm, lambda v: grasp_point(v) + [0, 0, 0.08], order="xyz")
    yield from ctx.move_to(arm, grasp_point, order="z")
    yield from ctx.grip(arm, close=True)
    yield from common.lift(ctx, arm, 0.08)
    turn = TARGET_YAW - yaw_of(ctx.view.mat("shoe"))
    c, s = np.cos(turn), np.sin(turn)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    yield from ctx.rotate_to(arm, rz @ ctx.view.arms[arm].rot)

    def over_target(height: float):
        def target(v: View) -> np.ndarray:
            offset = v.arms[arm].gc - v.pos("shoe")  # the grasp, as it is now
            return np.r_[TARGET_XY, rc.TABLE_Z + height] + offset

        return target

    yield from ctx.move_to(arm, over_target(0.06), order="xyz")
    yield from ctx.move_to(arm, over_target(RELEASE_HEIGHT), order="z")
    yield from ctx.grip(arm, close=False)
    yield from common.lift(ctx, arm, 0.06)


TASK = PlaceShoe(
    name="place_shoe",
    instruction="Place the shoe on the blue mat with its toe pointing to the left.",
    arms=("left", "right"),
    step_budget=100,
    checkpoints=("reached", "grasped", "lifted", "transported", "completed"),
    contact_pairs=(("shoe", "left_gripper"), ("shoe", "right_gripper")),
    variants=tuple(f"shoe_{k}" for k in range(N_SHOES)),
)
