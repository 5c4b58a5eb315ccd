"""grasp_single_cube_heldout: the held-out box of grasp_single_cube, among distractor boxes.

Controlled-transfer variant of grasp_single_cube (suite "transfer"; same instruction, arms,
budget and predicate; it reads the base family's summary). What is held out:
- the target is not the base's 50 mm cube but a red box of 40 x 60 x 45 mm (x, y, z; 90 g,
  `box_red_40x60x45.xml`): narrower across one pair of faces, longer across the other, lower;
- it stands among three distractor boxes of other colours and sizes: a blue 55 mm cube, a
  yellow 70 x 35 x 30 mm bar and a green 45 x 45 x 70 mm pillar (`box_*.xml`).
The instruction still names the red one, so only the red box counts.

Scene: the red box resting on the table at x in [0.18, 0.26], y in [-0.16, -0.06] (the base's
ranges), yaw in [-45, 45] deg. Each distractor rests on the table at 110-170 mm from the red
box's centre in a uniformly drawn direction, yaw in [-90, 90] deg, at least 90 mm from every
other distractor (centre to centre): the open fingers (90 mm aperture) fit around the red box
without touching one. Drawn from the seed salted with `SALT`, so a seed gives another scene than
the same seed of the base family.
Success (the base's row, on the red box only, both now): the red box lifted more than 50 mm
above its settled height and the right gripper closed. Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the red box's centre), grasped (closed and touching the
red box), lifted (> 50 mm), completed.
Expert: top-down grasp across the red box's narrow (40 mm) faces (a grasp symmetric every 180
deg), GC at the box centre, close, lift 100 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import mujoco
import numpy as np

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import common
from vabench.tasks import grasp_single_cube as base
from vabench.tasks.base import Evaluation, ObjectIndex, Sample, Script, SlotState, Task, yaw_quat
from vabench.tasks.expert import ExpertContext
from vabench.tasks.objects import attach_object

SALT = 0x6C5A1  # variant seeds draw from rng([seed, SALT]): other scenes than the base's seeds

TARGET_FILE = "box_red_40x60x45.xml"
TARGET_HALF = np.array([0.02, 0.03, 0.0225])
X_RANGE, Y_RANGE, YAW_DEG = base.X_RANGE, base.Y_RANGE, base.YAW_DEG

# distractor object name -> (file, half-extents)
DISTRACTORS = {
    "distractor_blue": ("box_blue_55.xml", np.array([0.0275, 0.0275, 0.0275])),
    "distractor_yellow": ("box_yellow_70x35x30.xml", np.array([0.035, 0.0175, 0.015])),
    "distractor_green": ("box_green_45x45x70.xml", np.array([0.0225, 0.0225, 0.035])),
}
RING = (0.11, 0.17)  # distractor centre distance from the target centre, m
MIN_GAP = 0.09  # distractor to distractor, centre to centre, m
DISTRACTOR_YAW_DEG = (-90.0, 90.0)


def salted_rng(seed: int, salt: int) -> np.random.Generator:
    """The variant's own random stream of a seed (not the base family's `default_rng(seed)`)."""
    return np.random.default_rng([seed, salt])


def sample_distractors(
    rng: np.random.Generator, centre: np.ndarray, names: dict[str, tuple[str, np.ndarray]]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Distractor poses on a ring around `centre` (RING), pairwise at least MIN_GAP apart."""
    placed: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, (_, half) in names.items():
        for _ in range(1000):
            r, phi = rng.uniform(*RING), rng.uniform(-np.pi, np.pi)
            xy = centre[:2] + r * np.array([np.cos(phi), np.sin(phi)])
            if all(np.linalg.norm(xy - p[:2]) >= MIN_GAP for p, _ in placed.values()):
                break
        else:  # pragma: no cover - the ring has room for three
            raise RuntimeError("no room for a distractor")
        yaw = np.radians(rng.uniform(*DISTRACTOR_YAW_DEG))
        placed[name] = (np.r_[xy, rc.TABLE_Z + half[2]], yaw_quat(yaw))
    return placed


@dataclass(frozen=True)
class GraspSingleCubeHeldout(Task):
    def populate(self, spec: mujoco.MjSpec, variant: int) -> None:
        attach_object(spec, TARGET_FILE, "cube")
        for name, (file, _) in DISTRACTORS.items():
            attach_object(spec, file, name)

    def sample(self, seed: int) -> Sample:
        rng = salted_rng(seed, SALT)
        pos = np.array([rng.uniform(*X_RANGE), rng.uniform(*Y_RANGE), rc.TABLE_Z + TARGET_HALF[2]])
        yaw = np.radians(rng.uniform(*YAW_DEG))
        poses = {"cube": (pos, yaw_quat(yaw)), **sample_distractors(rng, pos, DISTRACTORS)}
        return Sample(poses)

    def evaluate(self, ix: ObjectIndex, s: SlotState, latched: jax.Array) -> Evaluation:
        return common.grasp_evaluation(self, ix, s, latched, "cube")

    def expert(self, sample: Sample, ctx: ExpertContext) -> Script:
        # body x is the box's narrow axis; topdown(yaw) closes the fingers along the object's x
        yield from common.topdown_grasp(ctx, "right", "cube", symmetry_deg=180.0)
        yield from common.lift(ctx, "right", 0.10)


TASK = GraspSingleCubeHeldout(
    name="grasp_single_cube_heldout",
    instruction=base.TASK.instruction,
    arms=base.TASK.arms,
    step_budget=base.TASK.step_budget,
    checkpoints=base.TASK.checkpoints,
    contact_pairs=base.TASK.contact_pairs,
    suite="transfer",
    base_family=base.TASK.name,
)
