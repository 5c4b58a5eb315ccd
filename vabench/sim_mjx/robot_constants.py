"""Constants of the vabench dual-arm robot and of the VA-Bench world frame.

World frame (spec FACTS.md): z up, x to the robot's right, y away from the robot base; table top
at z = 0.741 m; the right arm works the x > 0 half. Lengths in metres, angles in radians.
The link lengths of the kinematic chain are not repeated here: `kinematics.ArmGeometry` reads
them from the compiled model, so the MJCF stays the single source of truth.
"""

from __future__ import annotations

import math
from pathlib import Path

ASSETS = Path(__file__).resolve().parents[2] / "assets"
ARM_XML = ASSETS / "robot" / "arm.xml"
TABLE_XML = ASSETS / "scene" / "table.xml"

TABLE_Z = 0.741
HEAD_CAMERA_POS = (0.0, -0.58, 1.48)

ARMS = ("left", "right")
# Arm bases sit on the table's near edge, both facing +y (base yaw +90 deg about world z).
ARM_BASE_POS = {"left": (-0.28, -0.48, TABLE_Z), "right": (0.28, -0.48, TABLE_Z)}
ARM_BASE_YAW = math.pi / 2

ARM_JOINTS = ("waist", "shoulder", "elbow", "forearm_roll", "wrist_pitch", "wrist_roll")
FINGER_JOINTS = ("finger_a", "finger_b")

# Home posture: GC at about (+-0.28, -0.20, 0.95), approach axis 50 deg below the horizontal,
# pointing forward, fingers closing along world x.
HOME_Q = (0.0, -0.3874, 0.8114, 0.0, 0.4487, 0.0)

FINGER_OPEN = 0.045  # each finger's travel from the centre line: 90 mm aperture
FINGER_CLOSED = 0.0

# End-effector target bounds of the reference (FACTS.md); vabench reports clipping.
EE_BOUNDS_LO = (-0.55, -0.45, 0.74)
EE_BOUNDS_HI = (0.55, 0.35, 1.35)
ROTATION_WAYPOINT_RAD = math.radians(10.0)  # the reference's bounds check of a rotation
MAX_ROTATION_WAYPOINTS = 9  # ceil(90 deg / 10 deg): the largest rotation's checked waypoints
# A rotation has ceil(angle / 10 deg - slack) waypoints: the angle reaches the planner in float32,
# where 30, 60 and 90 deg come out a hair above 3, 6 and 9 steps (without the slack 90 deg had
# 10 waypoints, of which the checks reached 9, leaving its end pose unchecked).
ROTATION_WAYPOINT_SLACK = 1e-4

# Gripper collision boxes in the gripper frame (origin at the wrist centre, x = approach):
# (centre, half-size). Fingers are given at zero opening; finger a is displaced by +q along y,
# finger b by -q. Used by the planner's table check; must match assets/robot/arm.xml
# (tests/test_kinematics.py checks it against the compiled model).
PALM_BOX = ((0.06, 0.0, 0.0), (0.03, 0.062, 0.022))
FINGER_A_BOX = ((0.125, 0.006, 0.0), (0.035, 0.006, 0.012))
FINGER_B_BOX = ((0.125, -0.006, 0.0), (0.035, 0.006, 0.012))
EE_SITE_X = 0.09  # control end effector ("ee" site) on the palm face
PAD_X = 0.145  # finger pads, 15 mm behind the tips: GC lies on this line

# Planner and trajectory (the fixed, model-agnostic executor).
TABLE_CLEARANCE = 0.002  # the gripper boxes must stay this far above the table top
N_WAYPOINTS = 25  # Cartesian waypoints per move: <= 4.2 mm and <= 3.75 deg apart
MAX_JOINT_STEP = 0.35  # rad between waypoints; more means a wrist flip, not a smooth move
ACTION_SECONDS = 0.8  # simulated time of every action (fixed shape for the batch)
MOVE_FRACTION = 0.7  # the arm reaches its target at 70 % of the action, then settles
GRIP_FRACTION = 0.6  # finger targets ramp over the first 60 % of the action
# An action that ends at rest (`action_end: at_rest`): once its references are final, a slot's
# action ends at the first substep where every dof moves slower than its rest speed, and at
# ACTION_SECONDS at the latest. A joint's rest speed is REST_SPEED (rad/s or m/s); a free body's
# turn is held to the same speed at REST_RADIUS from its centre (no object reaches further), so
# a standing object's float32 contact jitter on Warp (up to 0.019 rad/s) is rest as it is on C.
REST_SPEED = 1.0e-2
REST_RADIUS = 0.2
REST_SPIN = REST_SPEED / REST_RADIUS
# An action paced by its length (`action_end: paced`): the move's minimum-jerk time is
# sqrt(length / the longest move), of MOVE_FRACTION x ACTION_SECONDS, PACE_MIN of it at least,
# with length the executed translation over PACE_FULL_MOVE_M or the turn over PACE_FULL_TURN_RAD
# (the larger). Minimum-jerk's peak acceleration is 5.77 L / T^2: constant in L at this T, so
# no move accelerates harder than the longest move of the fixed timing does. The fingers keep
# their ramp (GRIP_FRACTION) when they move; the action then ends at rest.
PACE_FULL_MOVE_M = 0.1  # MOVE_MM_RANGE's top
PACE_FULL_TURN_RAD = math.pi / 2  # ROTATE_DEG_RANGE's top
PACE_MIN = 0.2

# Action ranges of the model interface.
MOVE_MM_RANGE = (1.0, 100.0)
ROTATE_DEG_RANGE = (1.0, 90.0)
ROTATE_STEP_DEG = 10.0  # the reference splits rotations into steps of at most 10 deg
