"""The model-facing texts: system prompt per arms and protocol, the observation's exact fields,
the passive bundle's order, the privilege-boundary checker, and the two inspection tools."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from vabench.agent.observation import (
    INITIAL_VIEW,
    PASSIVE_VIEWS,
    SELF_GEOMETRY_HEADER,
    ActionFeedback,
    build_observation,
    observation_turn,
    render_observation,
    self_geometry,
)
from vabench.agent.prompt_rules import GENERIC_RULES, HELDOUT_RULES, TASK_PROFILES
from vabench.agent.prompts import TOOL_DOCS, system_prompt
from vabench.agent.tools import camera_history, geometry_result, geometry_verify
from vabench.agent.visibility import (
    OBSERVATION_FIELDS,
    PROPRIO_FIELDS,
    PrivilegeLeak,
    VisibilityError,
    assert_model_visible,
    episode_secrets,
    filter_proprio,
    find_leaks,
)
from vabench.llm_pool import ChatRequest, GenerationOptions, Image, ModelEndpoint, Turn
from vabench.llm_pool.apis import ADAPTERS
from vabench.llm_pool.apis.base import encode_body
from vabench.llm_pool.testing import synthetic_image
from vabench.sim_mjx.layout import Proprio, proprio_fields

SINGLE, DUAL = ("right",), ("left", "right")
ALL_TOOLS = list(TOOL_DOCS)
ACTIVE_TOOLS = ["geometry.verify", "camera.history"]
CAMERA_NAMES = [f"camera.view_{v}" for v in PASSIVE_VIEWS] + [
    f"camera.{n}"
    for n in (
        "move_left",
        "move_right",
        "move_up",
        "move_down",
        "zoom_in",
        "zoom_out",
        "yaw_left",
        "yaw_right",
        "pitch_up",
        "pitch_down",
    )
]
CUBE_POS = (0.1234, 0.0567, 0.766)


# -- system prompt ---------------------------------------------------------------------------


def test_active_single_arm_prompt_states_the_metric_and_camera_interface():
    text = system_prompt(SINGLE, "active", ACTIVE_TOOLS)
    for required in (
        "x points to the robot's right",
        "y points away from the robot",
        "z points up",
        "N from 1 to 100",
        "A from 1 to 90",
        "rx = approach",
        "ry = finger-closing",
        "rz = palm-side",
        "right-hand rotation",
        "GC is held in place",
        "refused as a whole",
        "5 cm",
        "8 cm",
        "10 deg",
        "turns in place",
        "tilts the view downwards",
        "at most 5 camera actions in a row",
        "costs one step",
        "does not name the current\nview",
        INITIAL_VIEW,
        '"reason"',
        '{"stop": true',
        '"tool"',
        "exactly one JSON command",
        *CAMERA_NAMES,
        *(TOOL_DOCS[t] for t in ACTIVE_TOOLS),
    ):
        assert required in text, required
    assert '"arm"' not in text and "dual_gripper" not in text and "view_left_" not in text
    assert "expert." not in text  # only the offered tools
    assert "budget" not in text.replace("[camera_action_budget]", "")  # no step budget stated
    assert "lift a little" not in text  # the completion lift replaces a test lift


def test_generic_rules_come_in_order_under_their_ids_in_both_protocols():
    for protocol in ("active", "passive"):
        text = system_prompt(SINGLE, protocol, ["geometry.verify"])
        positions = [text.index(f"- [{rule_id}] ") for rule_id, _ in GENERIC_RULES]
        assert positions == sorted(positions)
    assert len(GENERIC_RULES) == 18


@pytest.mark.parametrize(
    "task, arms, profile",
    [
        ("lift_pot", DUAL, "one_side_handle_per_arm"),
        ("handover_horizontal_block", DUAL, "verticalize_before_handover"),
        ("put_everything_in_basket", SINGLE, "basket_capacity_management"),
    ],
)
def test_task_profiles_go_only_to_their_task(task, arms, profile):
    text = system_prompt(arms, "active", ACTIVE_TOOLS, task=task)
    assert f"# Task profile: {task}" in text
    for rule_id, _ in TASK_PROFILES[task]:
        assert f"- [{rule_id}] " in text
    others = [t for t in TASK_PROFILES if t != task]
    for other in others:
        assert f"Task profile: {other}" not in text
    for plain in ("place_shoe", "grasp_single_cube", None):
        bare = system_prompt(arms, "active", ACTIVE_TOOLS, task=plain)
        assert "Task profile" not in bare and profile not in bare


def test_heldout_policy_goes_only_to_heldout_tasks():
    held = system_prompt(SINGLE, "active", ACTIVE_TOOLS, task="grasp_single_cube_heldout")
    base = system_prompt(SINGLE, "active", ACTIVE_TOOLS, task="grasp_single_cube")
    for rule_id, _ in HELDOUT_RULES:
        assert f"- [{rule_id}] " in held and rule_id not in base
    assert "Task profile" not in held


def test_dual_arm_prompt_requires_the_arm_and_adds_dual_actions_and_view_targets():
    text = system_prompt(DUAL, "active", ACTIVE_TOOLS)
    for required in (
        '"arm": "left"|"right"',
        'require\n  "arm": "left" or "right"',
        "dual_gripper.move_world",
        "dual_gripper.open",
        "left_gripper.close",
        "camera.view_left_<view>",
        "camera.view_both_<view>",
    ):
        assert required in text, required
    single = system_prompt(SINGLE, "active", ACTIVE_TOOLS)
    assert len(text) > len(single)


@pytest.mark.parametrize("arms", [SINGLE, DUAL])
def test_passive_prompt_has_the_five_views_in_order_and_no_camera_interface(arms):
    text = system_prompt(arms, "passive", ["geometry.verify"])
    # the generic rules keep their words on views (as the reference's passive prompt does),
    # but no camera action is named or described
    for word in (*CAMERA_NAMES, "zoom", "yaw_", "pitch_", "5 cm", "8 cm", INITIAL_VIEW, "# Camera"):
        assert word not in text, word
    positions = [text.index(f"{i}. {v}:") for i, v in enumerate(PASSIVE_VIEWS, 1)]
    assert positions == sorted(positions)
    assert "no labels" in text and "Issue no camera.* action" in text


def test_prompt_arguments_are_checked_by_name():
    with pytest.raises(ValueError, match=r"tools: camera\.history"):
        system_prompt(SINGLE, "passive", ["camera.history"])
    with pytest.raises(ValueError, match=r"tools: unknown tool 'camera\.peek'"):
        system_prompt(SINGLE, "active", ["camera.peek"])
    with pytest.raises(ValueError, match="protocol"):
        system_prompt(SINGLE, "semi", [])
    with pytest.raises(ValueError, match="arms"):
        system_prompt(("middle",), "active", [])


@pytest.mark.parametrize("arms", [SINGLE, DUAL])
@pytest.mark.parametrize("protocol", ["active", "passive"])
def test_system_prompt_passes_the_leak_checker(arms, protocol):
    tools = [t for t in ALL_TOOLS if protocol == "active" or t != "camera.history"]
    for task in (None, *TASK_PROFILES, "place_cube_on_cube_heldout"):
        text = system_prompt(arms, protocol, tools, task=task)
        assert find_leaks(text) == [], task
    assert "table top" not in text.lower() and "0.741" not in text  # no scene coordinates


# -- observation ------------------------------------------------------------------------------


def sim_proprio(arms, gc=(0.28, -0.2, 0.95)):
    """Proprioception made by the simulator's own formatter (`proprio_fields`)."""
    a = len(arms)
    rot = np.tile(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), (1, a, 1, 1))
    p = Proprio(
        gc=np.tile(np.array(gc), (1, a, 1)),
        ee=np.tile(np.array([0.28, -0.25, 0.95]), (1, a, 1)),
        rot=rot,
        quat=np.tile(np.array([0.0, 0.7071, 0.7071, 0.0]), (1, a, 1)),
        rpy=np.tile(np.array([np.pi, 0.0, np.pi / 2]), (1, a, 1)),
        fingers=np.full((1, a, 2), 0.045),
        is_open=np.ones((1, a), bool),
    )
    return proprio_fields(p, 0, arms)


def observation(arms=SINGLE, **overrides):
    fields = dict(
        step=3,
        step_budget=50,
        instruction="Pick up the red cube and lift it off the table.",
        proprio=sim_proprio(arms),
        arms=arms,
        feedback=ActionFeedback(valid=True, planner_success=False),
        executed_actions=["move_world z-30mm", "camera.view_topdown"],
        demonstration_summary={"grasp_region": "middle", "pre_close_checks": ["centred"]},
        available_actions=['{"action": "gripper.close"}', '{"stop": true}'],
        history_steps=[1, 2],
    )
    fields.update(overrides)
    return build_observation(**fields)


@pytest.mark.parametrize("arms", [SINGLE, DUAL])
def test_observation_has_exactly_the_visible_fields(arms):
    obs = observation(arms)
    assert tuple(obs) == OBSERVATION_FIELDS
    state, geometry = obs["gripper_state"], obs["self_geometry"]
    arm_states = [state] if len(arms) == 1 else [state[a] for a in arms]
    for fields in arm_states:
        assert fields["is_open"] is True and fields["is_closed"] is False
        assert "local_axes_world" not in fields  # the axes are in the self-geometry block
    assert state["active_arm"] == (arms[0] if len(arms) == 1 else "both")
    assert state["last_action_valid"] is True and state["last_planner_success"] is False
    if len(arms) > 1:
        assert geometry["active_arm"] == "both" and set(geometry) == {"active_arm", *arms}
    assert set(sim_proprio(arms)[arms[0]]) == set(PROPRIO_FIELDS)  # simulator and list agree


def test_self_geometry_is_derived_from_the_visible_state():
    geometry = self_geometry(filter_proprio(sim_proprio(SINGLE), SINGLE)["right"])
    # GC lies 5 cm from the control point along +y: 90 deg from the table's downward normal
    assert geometry["grip_center_direction_world"] == [0.0, 1.0, 0.0]
    assert geometry["grip_center_direction_source"] == "finger_center_minus_eepose"
    assert geometry["grip_center_length_m"] == pytest.approx(0.05)
    assert geometry["grip_center_angle_to_world_axes_deg"]["+Y"] == 0.0
    assert geometry["grip_center_angle_to_table_down_deg"] == 90.0
    assert geometry["topdown_posture_ok_30deg"] is False
    assert geometry["topdown_posture_ok_45deg"] is False
    assert geometry["local_axes_world"]["rz"] == [0.0, 0.0, -1.0]
    down = self_geometry(
        filter_proprio(sim_proprio(SINGLE, gc=(0.28, -0.25, 0.90)), SINGLE)["right"]
    )
    assert down["grip_center_angle_to_table_down_deg"] == 0.0
    assert down["topdown_posture_ok_30deg"] and down["topdown_posture_ok_45deg"]
    same = self_geometry(
        filter_proprio(sim_proprio(SINGLE, gc=(0.28, -0.25, 0.95)), SINGLE)["right"]
    )
    assert same["grip_center_direction_source"] == "local_rx_fallback"
    assert same["grip_center_direction_world"] == [0.0, 1.0, 0.0]  # rx, column 0


def test_filter_rejects_any_field_outside_the_visible_set_naming_it():
    proprio = sim_proprio(SINGLE)
    proprio["right"]["object_pos"] = list(CUBE_POS)
    with pytest.raises(VisibilityError, match=r"'robot\.right\.object_pos': not a model-visible"):
        filter_proprio(proprio, SINGLE)
    proprio = sim_proprio(SINGLE)
    proprio["right"]["local_axes_world"]["cube_axis"] = [1.0, 0.0, 0.0]
    with pytest.raises(VisibilityError, match=r"local_axes_world\.cube_axis"):
        filter_proprio(proprio, SINGLE)
    proprio = sim_proprio(SINGLE)
    del proprio["right"]["control_eepose_quat"]
    with pytest.raises(VisibilityError, match=r"control_eepose_quat': missing"):
        filter_proprio(proprio, SINGLE)
    with pytest.raises(VisibilityError, match=r"'robot\.left'"):
        filter_proprio(sim_proprio(DUAL), SINGLE)
    proprio = sim_proprio(SINGLE)
    proprio["right"]["finger_center_xyz"] = [0.1, 0.2]
    with pytest.raises(VisibilityError, match="finger_center_xyz': expected 3 numbers"):
        filter_proprio(proprio, SINGLE)


def test_rendered_observation_holds_the_fields_and_nothing_else():
    obs = observation()
    text = render_observation(obs)
    assert text.splitlines() == [
        "Observation step: 3",
        "Task instruction: Pick up the red cube and lift it off the table.",
        f"Gripper state: {json.dumps(obs['gripper_state'])}",
        SELF_GEOMETRY_HEADER,
        json.dumps(obs["self_geometry"]),
        'Executed actions: ["move_world z-30mm", "camera.view_topdown"]',
        "Historical image steps available: [1, 2]",
        "",
        "Available decisions (one JSON form a line; numbers within the ranges shown):",
        '{"action": "gripper.close"}',
        '{"stop": true}',
        "",
        "Reply with exactly one JSON command.",
        "",
        "Demonstration summary (saved for this run; keep it as additive experience unless "
        "later images disprove an item):",
        *json.dumps(obs["demonstration_summary"], indent=2).splitlines(),
    ]
    first = render_observation(
        observation(
            step=1,
            executed_actions=[],
            demonstration_summary=None,
            history_steps=[],
            feedback=ActionFeedback(),
        )
    )
    assert "Executed actions: []" in first and "Demonstration summary" not in first
    assert "Historical image steps available: none" in first
    assert '"last_action_valid": true, "last_planner_success": true' in first  # at reset
    passive = render_observation(observation(history_steps=None))
    assert "Historical image steps" not in passive  # camera.history not offered
    for hidden in ("50", "budget", "Current view", "topdown\n"):
        assert hidden not in text.replace("camera.view_topdown", ""), hidden
    assert render_observation(obs) == text  # stable


def test_step_outside_the_budget_is_rejected():
    with pytest.raises(VisibilityError, match="'step'"):
        observation(step=51)


def test_observation_turn_puts_text_first_and_the_bundle_in_fixed_order_without_labels():
    images = {v: synthetic_image(seed=i) for i, v in enumerate(PASSIVE_VIEWS)}
    shuffled = {v: images[v] for v in reversed(PASSIVE_VIEWS)}
    turn = observation_turn("obs", shuffled)
    assert turn.content == ("obs", *(images[v] for v in PASSIVE_VIEWS))
    single = synthetic_image(seed=9)
    assert observation_turn("obs", single).content == ("obs", single)
    del shuffled["side"]
    with pytest.raises(VisibilityError, match=r"images\.side"):
        observation_turn("obs", shuffled)


# -- leak checker -----------------------------------------------------------------------------


def clean_request(gc=CUBE_POS) -> ChatRequest:
    """A real first request whose gripper sits exactly at the cube (a legitimate grasp)."""
    text = render_observation(observation(proprio=sim_proprio(SINGLE, gc)))
    return ChatRequest(
        (Turn.user(text, Image(b64="seedfovAseedfovA")),),  # base64 that spells privileged words
        system_prompt(SINGLE, "active", ACTIVE_TOOLS),
    )


SECRETS = episode_secrets(
    {"cube": CUBE_POS},
    seed=1003,
    camera_positions={"head": (0.0, -0.58, 1.48)},
    identifiers=["default", "shoe_3", "giver_grasped", "grasped"],
)


@pytest.mark.parametrize("api", ["openai_chat", "openai_responses", "anthropic"])
def test_clean_request_passes_in_every_provider_body(api):
    request = clean_request()
    endpoint = ModelEndpoint(name="m", api=api, model="m")
    body = encode_body(ADAPTERS[api].build_body(endpoint, request, GenerationOptions()))
    assert find_leaks(body, SECRETS) == []
    assert find_leaks(json.loads(body), SECRETS) == []
    assert_model_visible(request, SECRETS)


@pytest.mark.parametrize(
    ("leak", "what"),
    [
        (f"The cube is at {list(CUBE_POS)}.", "object cube position"),
        ("cube centre (123.4, 56.7, 766) mm", "object cube position"),
        ("Scene 1003.", "seed"),
        ('{"seed": 7}', "seed"),
        ("head camera fovy 37", "fovy"),
        ("vertical field of view: 55 deg", "field of view"),
        ("camera at (0.0, -0.58, 1.48)", "camera head position"),
        ('{"success": false}', '"success":'),
        ("latched lift flag", "latched"),
        ("the model is Shoe_3", "identifier shoe_3"),
        ("giver_grasped: true", "identifier giver_grasped"),
    ],
)
def test_leaks_are_caught_in_user_text_and_provider_bodies(leak, what):
    request = clean_request()
    leaky = ChatRequest(
        (*request.turns[:-1], Turn.user(leak, *request.turns[-1].content)), request.system
    )
    found = find_leaks(leaky, SECRETS)
    assert [f.what for f in found] == [what], found
    endpoint = ModelEndpoint(name="m", api="anthropic", model="m")
    body = encode_body(ADAPTERS["anthropic"].build_body(endpoint, leaky, GenerationOptions()))
    assert [f.what for f in find_leaks(body, SECRETS)] == [what]
    with pytest.raises(PrivilegeLeak, match=re.escape(what)):
        assert_model_visible(body, SECRETS)


def test_assistant_turns_and_small_numbers_are_not_leaks():
    request = clean_request()
    reply = Turn.assistant("I must not guess the seed; 37 and 1003 are just numbers to me.")
    convo = ChatRequest((*request.turns, reply, Turn.user("Step 12 of 50. z-37mm")), request.system)
    assert find_leaks(convo, SECRETS) == []
    assert episode_secrets(seed=12) == []  # too short to tell from a step number
    # Plain words are no identifiers to match: "grasped" is prose, and in the instruction.
    assert [s.word for s in SECRETS if s.word] == ["shoe_3", "giver_grasped"]


# -- tools ------------------------------------------------------------------------------------


def test_geometry_verify_gives_robot_geometry_and_nothing_about_the_scene():
    geo = geometry_verify(DUAL)
    g = geo["gripper"]
    assert g["max_aperture_mm"] == 90.0
    assert g["fingertip_beyond_gc_mm"] == 15.0
    assert g["finger_length_mm"] > g["fingertip_beyond_gc_mm"]
    assert set(g["axes"]) == {"rx", "ry", "rz"}
    assert geo["end_effector_bounds_m"] == {
        "x": [-0.55, 0.55],
        "y": [-0.45, 0.35],
        "z": [0.74, 1.35],
    }
    assert set(geo["arm_base_xyz_m"]) == {"left", "right"}
    assert set(geometry_verify(SINGLE)["arm_base_xyz_m"]) == {"right"}
    result = geometry_result(SINGLE)
    assert json.loads(result.text)["tool"] == "geometry.verify" and result.images == ()
    assert find_leaks(result.text, SECRETS) == []
    assert "object" not in result.text.lower() and "camera" not in result.text.lower()
    with pytest.raises(ValueError, match="arms"):
        geometry_verify(("middle",))


def test_camera_history_reattaches_the_image_or_names_the_valid_steps():
    frames = {s: synthetic_image(seed=s) for s in (1, 2, 3, 5)}
    result = camera_history(frames, 2)
    assert result.ok and result.images == (frames[2],) and result.step == 2
    assert json.loads(result.text)["step"] == 2
    missing = camera_history(frames, 4)
    assert not missing.ok and missing.images == ()
    assert json.loads(missing.text)["error"] == (
        "args.step: no image for step 4; valid steps: 1-3, 5"
    )
    assert "expected an integer" in camera_history(frames, True).text
    assert "none yet" in camera_history({}, 1).text


def test_task_instructions_pass_the_leak_checker():
    from vabench.tasks import base_tasks

    tasks = base_tasks()
    assert len(tasks) == 14
    for task in tasks:
        assert find_leaks(task.instruction) == [], task.name
