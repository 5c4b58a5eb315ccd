"""The rules the system prompt carries: the generic manipulation and safety rules, the
held-out policy and the task profiles, each under the reference's id (spec PROTOCOL_FACTS.md
1.2-1.4: the facts carried over, the sentences vabench's own). `prompts` places them.
"""

from __future__ import annotations

from vabench.protocol import MAX_CAMERA_CHAIN

RULE_HANDLING = (
    "Treat the rules below as standing constraints: keep those that evidence confirms, add a "
    "correction when something fails, and revise or drop a rule only when the evidence shows "
    "it wrong, saying which one and why before acting against it. Apply every rule that does "
    "not conflict with another."
)

GENERIC_RULES: tuple[tuple[str, str], ...] = (
    (
        "json_one_step",
        "Each reply is exactly one JSON command. Robot and camera actions advance the episode "
        "by one step; tool calls do not.",
    ),
    (
        "clean_model_image",
        "The images show the scene only: nothing is drawn on them (no gripper or GC marker, no "
        "axes, no target or contact hint). Reason from the pixels and the robot self-geometry "
        "text.",
    ),
    (
        "active_perception",
        "Choose every view to settle one named doubt. topdown settles alignment in world x/y "
        "but never proves height, depth or contact; side settles height, clearance and whether "
        "the fingers straddle the object, and hides offsets along its line of sight; "
        "front_side_45 resolves what front and side views occlude; side_top_45 shows lateral "
        "alignment, height and finger placement together; oblique_45 gives the overall 3D "
        "layout and helps pick the next view, but proves no grasp. Do not rely on topdown and "
        "side alone; one intermediate view is better than a long chain of yaw, pitch or move "
        "adjustments. Camera actions never change what a world-axis gripper command means. "
        "Collect complementary evidence before closing. Once the gripper has moved or turned, "
        "earlier evidence about what it changed is stale. The self-geometry describes the "
        "robot only.",
    ),
    (
        "camera_action_budget",
        f"Take at most {MAX_CAMERA_CHAIN} camera actions in a row (every kind of camera "
        "action counts), each answering a concrete question. After the "
        f"{MAX_CAMERA_CHAIN}th, the next action that changes the episode must be a gripper "
        "action with a reason, or stop and explain why. Tool calls do not reset this count.",
    ),
    (
        "no_hidden_target_coords",
        "No object coordinates are given and none may be assumed: locate objects from the "
        "images, the history and the robot self-geometry (which is about the robot only).",
    ),
    (
        "numeric_gripper_actions",
        "Gripper moves and rotations are written only in the numeric JSON form "
        "(gripper.move_world, gripper.rotate_local); there are no named small/medium/large "
        "gripper steps.",
    ),
    (
        "local_rotation_axes",
        "Change the gripper's posture with gripper.rotate_local about its current axes: rx = "
        "approach (twist about the approach direction), ry = finger-closing, rz = palm-side.",
    ),
    (
        "constraint_lifecycle",
        "After a failed attempt keep what was validated and add the correction; a rule that "
        "proved wrong is named, justified and revised or removed, never quietly ignored.",
    ),
    (
        "expert_grasp_position",
        "When demonstrations are offered, list all their frames first and choose the frames "
        "to look at yourself; then record, as additive rules, which part is grasped, from which "
        "side, at which height or depth, and where the fingers go.",
    ),
    (
        "pre_action_grasp_point_analysis",
        "Before the first robot move of a grasp, state in your reason the grasp point: the "
        "part and region, the regions to avoid (cap, end, edge...), the evidence, the camera "
        "checks planned, the approach and what full enclosure will look like. This is "
        "reasoning, not a gate.",
    ),
    (
        "stable_grasp_region_centering",
        "Region and depth are separate choices. Unless the task needs an end, an edge or a "
        "handle, aim at the middle of a broad, regular region, centring GC both along the "
        "approach and along the object's length. If GC has drifted towards a region to avoid, "
        "stay open and reposition.",
    ),
    (
        "no_single_view_grasp_proof",
        "Overlap in one image is not contact. Before closing, confirm from a view that shows "
        "depth that the object lies between both fingers; touching its top, or touching it "
        "with one fingertip, is no grasp.",
    ),
    (
        "grasp_center_depth_before_close",
        "Check both straddle and insertion depth: the object's centre must be past the "
        "fingertips, deep between the pads and near GC. Keep advancing with the gripper open "
        "until it is, or until the gripper pushes the object, touches the palm or the support, "
        "or stops making progress. Judge from fresh images.",
    ),
    (
        "continuous_insertion_toward_gc",
        "Once the posture is set and the object is inside the open gap, keep inserting towards "
        "GC (world -z for a top-down grasp, the matching x/y direction for a side grasp) until "
        "the object is near GC or the gripper is blocked.",
    ),
    (
        "full_wrap_before_close",
        "Close only when both inner pads are on opposite sides of the object, its centre is "
        "near GC and the pads overlap it substantially; contact at the fingertips means insert "
        "further and check again.",
    ),
    (
        "low_object_support_depth",
        "For a low or lying object, descend open in controlled steps until the fingertips "
        "reach the support, the object reaches GC, or a downward move makes no progress, "
        "keeping the object between the fingers; do not force further after that.",
    ),
    (
        "complete_lift_after_close",
        "After closing, lift along world +z until the task is accomplished or a clear, lasting "
        "gap shows the object was not taken; do not stop after a rise of 20-30 mm while the "
        "episode is still running.",
    ),
    (
        "failed_lift_change_hypothesis",
        "If the object stayed on the support, the grasp missed: open again and change one "
        "geometric hypothesis (region, lateral placement, depth or posture). After touching "
        "the top or missing the straddle, back off upwards and change x/y, not only the depth.",
    ),
)
"""The generic manipulation and safety rules, in the reference's order and under its ids
(PROTOCOL_FACTS.md 1.2), written in vabench's words."""

HELDOUT_RULES: tuple[tuple[str, str], ...] = (
    (
        "mandatory_protocol_and_objective",
        "The object's instance, shape, look, position or orientation may differ from anything "
        "seen before; the rules, the protocol, the goal and what counts as done still hold.",
    ),
    (
        "expert_is_transferable_reference",
        "A demonstration is a reference to adapt (grasp axis, height, approach, distances, "
        "views, placement) to what the current images show, never a motion to replay.",
    ),
    (
        "no_expert_appearance_assumptions",
        "Assume no colour, label, brand, size, fixed coordinate or landmark from a "
        "demonstration; the object and its pose here are not named.",
    ),
    (
        "preserve_transferable_safety",
        "Keep everything that transfers: clearance, checks from several views, alignment, deep "
        "enclosure, a stable close, the completion lift and release checks. Where a habit and "
        "the image disagree, follow the image.",
    ),
)
"""The held-out policy (PROTOCOL_FACTS.md 1.4), for the `<base>_heldout` tasks."""

TASK_PROFILES: dict[str, tuple[tuple[str, str], ...]] = {
    "lift_pot": (
        (
            "one_side_handle_per_arm",
            "The left arm takes the handle on the left, the right arm the handle on the right, "
            "each at the middle of the handle's outer bar, not the lid, knob, body, rail or a "
            "corner. Do not swap sides, and do not push the pot while approaching.",
        ),
        (
            "mirrored_outside_in_grasp_posture",
            "The two grippers mirror each other: each comes from outside towards the pot's "
            "centre with its closing axis across its handle's bar, tilted slightly downwards. "
            "No shared forward approach; this holds over any summary.",
        ),
        (
            "rotate_high_before_handle_approach",
            "Make large rotations high up, clear of the pot, and check each arm's axes on their "
            "own.",
        ),
        (
            "outside_height_then_radial_insertion",
            "Reach the handle's height beside the pot first, then move inwards onto the handle; "
            "never descend over the lid, and never correct both arms with one shared x/y move.",
        ),
        (
            "verify_both_handle_wraps",
            "Verify each handle's enclosure on its own: one arm's grip proves nothing about the "
            "other's.",
        ),
        (
            "synchronized_close_and_level_lift",
            "Close both grippers together and lift both by the same +z steps so the pot stays "
            "level. If the pot stays on the table, open again and change the posture or the "
            "straddle.",
        ),
    ),
    "handover_horizontal_block": (
        (
            "dynamic_giver_selection",
            "The giver is the arm on the side of the table where the block lies in this "
            "episode; roles seen in a demonstration do not carry over.",
        ),
        (
            "opposite_receiver_assignment",
            "The other arm receives. The giver holds one segment of the block and leaves "
            "another exposed for the receiver.",
        ),
        (
            "verticalize_before_handover",
            "With the block held, the giver moves into free space and turns the block's long "
            "axis roughly vertical, checked from complementary views; the receiver waits while "
            "the block is still horizontal or diagonal. This holds over any demonstration.",
        ),
        (
            "opposed_receiver_approach",
            "Route the receiver, while it is clear, to the side opposite the giver's wrist and "
            "path; no parallel approach from the same side. Check with topdown and an oblique "
            "or side view.",
        ),
        (
            "receiver_side_grasp_posture",
            "The receiver grasps from the side with its gripper horizontal: approach axis "
            "towards the block, closing axis across its narrow width; large rotations in free "
            "space; advance along its own approach axis.",
        ),
        (
            "handover_contact_recovery",
            "If the receiver shifts the block or the giver, withdraw, go round and reset its "
            "orientation.",
        ),
        (
            "close_before_release",
            "The giver opens only after the receiver is verified closed on the block; the task "
            "is done when the receiver alone holds the upright block.",
        ),
    ),
    "put_everything_in_basket": (
        (
            "atomic_demos_are_compositional",
            "Demonstrations, where offered, show separate single-object skills. Take the list "
            "of objects, their order, orientations and poses from the live scene, and write no "
            "per-type counts into learned rules.",
        ),
        (
            "five_object_completion_accounting",
            "Keep a visual checklist of the objects. The task is done when every object's "
            "footprint lies inside the basket, resting on it; only the final state counts.",
        ),
        (
            "basket_capacity_management",
            "Place objects in separate free regions of the basket; do not stack on an unstable "
            "object, do not trap objects on the rim, and never move the basket.",
        ),
        (
            "recover_or_defer_failed_objects",
            "An object that failed stays on the checklist: retry it with a real change, or "
            "defer it and come back before ending.",
        ),
    ),
}
"""Task profiles where roles or the completion rule need spelling out (PROTOCOL_FACTS.md 1.3:
the reference profiles exactly these three of vabench's tasks), in vabench's words."""
