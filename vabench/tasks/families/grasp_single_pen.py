"""grasp_single_pen: pick up a marker pen lying on the table with the right arm.

Scene (paper Table tab:seed-spec-grasp): one marker pen (pen_marker.xml: 14 mm thick, 140 mm
long, purple barrel, red cap, black tip; a capsule collider) lying on the table, its centre at
x in [0.18, 0.26], y in [-0.20, -0.10], resting height 7 mm (z = table + 0.007), yaw in
[-30, 30] deg. Yaw is the heading of the pen's long axis measured from world +x: at yaw 0 the
pen lies left-right in front of the robot (cap to the right), so a top-down grasp closes the
fingers across it along world y.
Success: the pen lifted more than 50 mm above its settled height and the right gripper closed
(both now, not latched). Budget 50 steps.
Checkpoints: reached (GC within 30 mm of the pen's centre), grasped (closed and touching),
lifted (> 50 mm), completed (success).
Expert: fingers straight down and closing across the pen, GC 11 mm above the pen's axis (1 mm
above the lowest GC the planner allows: the fingertips stay 2 mm above the table), close, lift
100 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

from vabench.sim_mjx import robot_constants as rc
from vabench.tasks import skills_pens_bottles as sk
from vabench.tasks.base import OnTable, Script
from vabench.tasks.expert import ExpertContext
from vabench.tasks.grasp_place import GraspFamily

# yaw: the heading of the pen's long axis (its local x)
PEN_AT = OnTable(x=(0.18, 0.26), y=(-0.20, -0.10), half_h=sk.PEN_RADIUS, yaw_deg=(-30.0, 30.0))
# GC above the pen's axis: 1 mm above the lowest GC the planner allows (11 mm; the fingertips
# then reach 4 mm below the axis)
GRASP_DZ = sk.TOPDOWN_MIN_GC_Z + 0.001 - (rc.TABLE_Z + sk.PEN_RADIUS)


@dataclass(frozen=True)
class GraspSinglePen(GraspFamily):
    def grasp(self, ctx: ExpertContext) -> Script:
        yield from sk.grasp_across(ctx, "right", "pen", long_axis=0, dz=GRASP_DZ)


TASK = GraspSinglePen(
    name="grasp_single_pen",
    instruction="Pick up the pen lying on the table and lift it off the table.",
    objects=(("pen", "pen_marker.xml"),),
    on_table=(("pen", PEN_AT),),
)
