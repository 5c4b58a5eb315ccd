"""The decision layer: robot actions (aliases, ranges, arm rules), camera actions, tools, stop,
reply extraction, rejections naming the field, the camera-chain rule, labels, vocabulary."""

from __future__ import annotations

import json

import pytest

from vabench import protocol as P

DUAL = ("left", "right")
SINGLE = ("right",)


@pytest.mark.parametrize(
    "alias,sign",
    [
        ("+", "+"),
        ("pos", "+"),
        ("positive", "+"),
        ("+1", "+"),
        (1, "+"),
        ("-", "-"),
        ("neg", "-"),
        ("negative", "-"),
        ("-1", "-"),
        (-1, "-"),
    ],
)
def test_sign_aliases(alias, sign):
    a = P.parse_robot_action(
        {"action": "gripper.move_world", "axis": "x", "sign": alias, "distance_mm": 5}, SINGLE
    )
    assert a.sign == sign


def test_arm_required_in_dual_arm_tasks():
    with pytest.raises(P.ActionError) as e:
        P.parse_robot_action(
            {"action": "gripper.rotate_local", "axis": "rz", "sign": "+", "angle_deg": 5}, DUAL
        )
    assert e.value.field == "arm"
    ok = P.parse_robot_action(
        {
            "action": "gripper.rotate_local",
            "axis": "rz",
            "sign": "+",
            "angle_deg": 5,
            "arm": "left",
        },
        DUAL,
    )
    assert ok.arm == "left"


def test_dual_move_each_side_validated():
    with pytest.raises(P.ActionError) as e:
        P.parse_robot_action(
            {
                "action": "dual_gripper.move_world",
                "left": {"axis": "x", "sign": "+", "distance_mm": 10},
                "right": {"axis": "x", "sign": "+", "distance_mm": 101},
            },
            DUAL,
        )
    assert e.value.field == "right.distance_mm"


def test_missing_field_named():
    with pytest.raises(P.ActionError) as e:
        P.parse_robot_action({"action": "gripper.move_world", "axis": "x", "sign": "+"}, SINGLE)
    assert e.value.field == "distance_mm"


def test_not_an_object():
    with pytest.raises(P.ActionError) as e:
        P.parse_robot_action(["gripper.open"], SINGLE)
    assert e.value.field == "action"


# -- the decision layer: parse_decision and friends -------------------------------------------

ACTIVE_SINGLE = P.DecisionContext(SINGLE, "active", P.available_tools(demonstration=True))
ACTIVE_DUAL = P.DecisionContext(DUAL, "active", P.available_tools(demonstration=True))
PASSIVE_SINGLE = P.DecisionContext(SINGLE, "passive", P.available_tools(demonstration=False))
PASSIVE_DUAL = P.DecisionContext(DUAL, "passive", P.available_tools(demonstration=False))

# Written out from FACTS.md rather than read from the module, so a dropped name fails here.
VIEWS = ["topdown", "side", "front_side_45", "side_top_45", "oblique_45"]
INCREMENTS = [
    "move_left", "move_right", "move_up", "move_down", "zoom_in", "zoom_out",
    "yaw_left", "yaw_right", "pitch_up", "pitch_down",
]  # fmt: skip
SINGLE_CAMERA = [f"camera.view_{v}" for v in VIEWS] + [f"camera.{i}" for i in INCREMENTS]
DUAL_ONLY_CAMERA = [f"camera.view_{t}_{v}" for t in ("left", "right", "both") for v in VIEWS]


def decide(obj, ctx=ACTIVE_SINGLE):
    return P.parse_decision(json.dumps(obj), ctx)


def rejected(obj_or_text, ctx=ACTIVE_SINGLE) -> P.DecisionError:
    text = obj_or_text if isinstance(obj_or_text, str) else json.dumps(obj_or_text)
    with pytest.raises(P.DecisionError) as e:
        P.parse_decision(text, ctx)
    return e.value


def move(axis="z", sign="+", mm=30, **extra):
    return {"action": "gripper.move_world", "axis": axis, "sign": sign, "distance_mm": mm, **extra}


def rotate(axis="rz", sign="+", deg=15, **extra):
    return {"action": "gripper.rotate_local", "axis": axis, "sign": sign, "angle_deg": deg, **extra}


def tool(name, **args):
    return {"tool": name, "args": args}


# -- every form of FACTS parses ----------------------------------------------------------------


@pytest.mark.parametrize("axis", ["x", "y", "z"])
@pytest.mark.parametrize("mm", [1, 55.5, 100])
def test_move_world_single(axis, mm):
    d = decide(move(axis, "-", mm))
    assert isinstance(d, P.MoveWorld)
    assert (d.axis, d.sign, d.distance_mm, d.arm) == (axis, "-", mm, None)


@pytest.mark.parametrize("axis", ["rx", "ry", "rz"])
@pytest.mark.parametrize("deg", [1, 90])
def test_rotate_local_single(axis, deg):
    d = decide(rotate(axis, "+", deg))
    assert isinstance(d, P.RotateLocal)
    assert (d.axis, d.sign, d.angle_deg) == (axis, "+", deg)


@pytest.mark.parametrize(
    "alias,sign",
    [("+", "+"), ("pos", "+"), ("positive", "+"), ("+1", "+"), ("1", "+"), (1, "+"),
     (" POS ", "+"), ("-", "-"), ("neg", "-"), ("negative", "-"), ("-1", "-"), (-1, "-")],
)  # fmt: skip
def test_sign_aliases_in_rotations_and_dual_moves(alias, sign):
    assert decide(rotate(sign=alias)).sign == sign
    dual = {
        "action": "dual_gripper.move_world",
        "left": {"axis": "x", "sign": alias, "distance_mm": 10},
        "right": {"axis": "y", "sign": "+", "distance_mm": 20},
    }
    assert decide(dual, ACTIVE_DUAL).left.sign == sign


@pytest.mark.parametrize("name", ["gripper.open", "gripper.close"])
def test_aperture_single(name):
    d = decide({"action": name})
    assert isinstance(d, P.Aperture) and d.opens == name.endswith("open")


@pytest.mark.parametrize("arm", ["left", "right"])
def test_single_gripper_actions_with_arm_in_dual_tasks(arm):
    assert decide(move(arm=arm), ACTIVE_DUAL).arm == arm
    assert decide(rotate(arm=arm), ACTIVE_DUAL).arm == arm
    assert decide({"action": "gripper.close", "arm": arm}, ACTIVE_DUAL).arm == arm


@pytest.mark.parametrize(
    "name",
    [f"{side}_gripper.{verb}" for side in ("left", "right", "dual") for verb in ("open", "close")],
)
def test_named_grippers_in_dual_tasks(name):
    d = decide({"action": name}, ACTIVE_DUAL)
    assert isinstance(d, P.Aperture) and d.action == name and d.arm is None


def test_dual_move():
    d = decide(
        {
            "action": "dual_gripper.move_world",
            "left": {"axis": "x", "sign": "-", "distance_mm": 10},
            "right": {"axis": "z", "sign": "+", "distance_mm": 100},
        },
        PASSIVE_DUAL,  # robot actions are the same in both protocols
    )
    assert isinstance(d, P.DualMove)
    assert (d.left.axis, d.left.sign, d.right.distance_mm) == ("x", "-", 100)


@pytest.mark.parametrize("name", SINGLE_CAMERA)
def test_camera_actions_single(name):
    d = decide({"action": name})
    assert isinstance(d, P.CameraAction) and d.action == name and d.kind == "camera"


@pytest.mark.parametrize("name", SINGLE_CAMERA + DUAL_ONLY_CAMERA)
def test_camera_actions_dual(name):
    assert decide({"action": name}, ACTIVE_DUAL).action == name


def test_camera_vocabulary_is_exactly_facts():
    assert sorted(P.camera_action_names(SINGLE)) == sorted(SINGLE_CAMERA)
    assert sorted(P.camera_action_names(DUAL)) == sorted(SINGLE_CAMERA + DUAL_ONLY_CAMERA)


@pytest.mark.parametrize(
    "name,view,target,increment",
    [
        ("camera.view_topdown", "topdown", None, None),
        ("camera.view_side_top_45", "side_top_45", None, None),
        ("camera.view_left_side", "side", "left", None),
        ("camera.view_both_front_side_45", "front_side_45", "both", None),
        ("camera.view_right_oblique_45", "oblique_45", "right", None),
        ("camera.zoom_in", None, None, "zoom_in"),
        ("camera.pitch_down", None, None, "pitch_down"),
    ],
)
def test_camera_action_parts(name, view, target, increment):
    d = decide({"action": name}, ACTIVE_DUAL)
    assert (d.view, d.target, d.increment) == (view, target, increment)


@pytest.mark.parametrize(
    "obj,label",
    [
        ({"tool": "geometry.verify", "args": {}}, "tool geometry.verify"),
        ({"tool": "geometry.verify"}, "tool geometry.verify"),  # no args means {}
        ({"tool": "camera.history", "args": {"step": 0}}, "tool camera.history step=0"),
        ({"tool": "expert.retrieve", "args": {}}, "tool expert.retrieve"),
        ({"tool": "expert.frame", "args": {"step": 4}}, "tool expert.frame steps=4"),
        (
            {"tool": "expert.frame", "args": {"steps": [0, 9, 3, 5, 7, 11, 13, 2], "view": "head"}},
            "tool expert.frame steps=0,9,3,5,7,11,13,2 view=head",
        ),
        ({"tool": "expert.learn", "args": {"grasp_region": "mid"}}, "tool expert.learn"),
        (
            {"tool": "expert.learn", "args": {"summary": {"grasp_region": "mid"}}},
            "tool expert.learn",
        ),
        (
            {"tool": "expert.learn", "args": {}},
            "tool expert.learn",
        ),  # the tool says what is missing
    ],
)
def test_tools_parse(obj, label):
    d = decide(obj)
    assert isinstance(d, P.ToolCall) and d.kind == "tool"
    assert d.name == obj["tool"]
    assert P.decision_label(d) == label


def test_tool_arguments_are_typed():
    assert decide({"tool": "camera.history", "args": {"step": 7}}).args.step == 7
    frames = decide({"tool": "expert.frame", "args": {"steps": [3, 1]}}).args
    assert frames.frames == (3, 1) and frames.view is None
    assert decide({"tool": "expert.frame", "args": {"step": 2}}).args.frames == (2,)
    # expert.learn keeps its args whole, whatever their keys (the demonstration tools check them)
    fields = {"grasp_region": "mid", "fields": 1, "model_config": [2], "pre_close_checks": []}
    learn = decide({"tool": "expert.learn", "args": fields})
    assert learn.args.fields == fields
    assert learn.model_dump(exclude_none=True)["args"] == fields


@pytest.mark.parametrize(
    "obj,ctx",
    [
        (move(reason="lower onto the cube"), ACTIVE_SINGLE),
        (rotate(arm="left", reason="lower onto the cube"), ACTIVE_DUAL),
        ({"action": "gripper.open", "reason": "lower onto the cube"}, ACTIVE_SINGLE),
        ({"action": "camera.view_side", "reason": "lower onto the cube"}, ACTIVE_SINGLE),
        ({"tool": "geometry.verify", "args": {}, "reason": "lower onto the cube"}, ACTIVE_SINGLE),
        ({"stop": True, "reason": "lower onto the cube"}, ACTIVE_SINGLE),
    ],
)
def test_reason_kept(obj, ctx):
    assert decide(obj, ctx).reason == "lower onto the cube"


def test_stop():
    d = decide({"stop": True})
    assert isinstance(d, P.Stop) and d.reason is None and P.decision_label(d) == "stop"


def test_dispatch_order_stop_then_tool_then_action():
    everything = {"stop": True, "tool": "geometry.verify", "args": {}, **move()}
    assert isinstance(decide(everything), P.Stop)
    assert isinstance(decide({**everything, "stop": False}), P.ToolCall)
    no_tool = {k: v for k, v in everything.items() if k not in ("tool", "args")}
    assert isinstance(decide({**no_tool, "stop": False}), P.MoveWorld)


# -- reply extraction -------------------------------------------------------------------------


def test_fenced_block_with_prose_around():
    text = (
        "The cube is left of the gripper {roughly}.\n```json\n"
        + json.dumps(move("x", "-", 20))
        + "\n```\nAfter this I will lower the gripper."
    )
    d = P.parse_decision(text, ACTIVE_SINGLE)
    assert (d.axis, d.sign, d.distance_mm) == ("x", "-", 20)


def test_the_first_fenced_decision_block_is_taken():
    """The reference's rule: the first fenced block (tagged json in any case, or untagged)."""
    text = (
        'Option A:\n```json\n{"action": "gripper.open"}\n```\n'
        'Better, option B:\n```JSON\n{"action": "gripper.close"}\n```\n'
        "```python\nprint({'action': 'camera.zoom_in'})\n```"
    )
    assert P.parse_decision(text, ACTIVE_SINGLE).action == "gripper.open"
    text = '{"action": "camera.zoom_out"}\n```\n{"action": "gripper.close"}\n```'
    assert P.parse_decision(text, ACTIVE_SINGLE).action == "gripper.close"


def test_a_fenced_block_that_is_no_decision_is_passed_over():
    text = (
        'The state is\n```json\n{"is_open": true, "finger_center_xyz": [0, 0, 1]}\n```\n'
        'so I close:\n```json\n{"action": "gripper.close"}\n```'
    )
    assert P.parse_decision(text, ACTIVE_SINGLE).action == "gripper.close"
    only_state = '```json\n{"is_open": true}\n```'
    assert rejected(only_state).field == "action"


def test_a_fenced_block_that_does_not_decode_is_an_error():
    text = '```json\n{"action": "gripper.open",}\n```\n```json\n{"action": "gripper.close"}\n```'
    err = rejected(text)
    assert err.field == P.REPLY and "first ```json block is not valid JSON" in str(err)


def test_untagged_and_one_line_fences():
    assert P.parse_decision('```\n{"action": "gripper.open"}\n```', ACTIVE_SINGLE).action == (
        "gripper.open"
    )
    assert P.parse_decision('```json {"stop": true}```', ACTIVE_SINGLE).kind == "stop"


def test_bare_object_first_brace_to_last_brace_with_nested_braces_in_strings():
    obj = {
        "action": "dual_gripper.move_world",
        "left": {"axis": "x", "sign": "+", "distance_mm": 10},
        "right": {"axis": "y", "sign": "-", "distance_mm": 12},
        "reason": 'close the gap {"between" the grippers} \\ } {{ and a lone " then }',
    }
    text = f"Plan: the handles need closing. {json.dumps(obj)} That is all."
    d = P.parse_decision(text, ACTIVE_DUAL)
    assert isinstance(d, P.DualMove)
    assert d.reason == obj["reason"] and d.right.distance_mm == 12


def test_braces_in_the_prose_around_a_bare_object_break_it_as_in_the_reference():
    text = "Coordinates use {x, y, z}. " + json.dumps(move()) + " done"
    err = rejected(text)
    assert err.field == P.REPLY and "first '{' to the last '}'" in str(err)
    assert "```json block" in str(err)


def test_reply_cut_off_after_the_object_but_before_the_closing_fence():
    text = "Lowering now.\n```json\n" + json.dumps(move("z", "-", 40))
    assert P.parse_decision(text, ACTIVE_SINGLE).distance_mm == 40


@pytest.mark.parametrize(
    "text",
    [
        '<think>draft:\n```json\n{"action": "gripper.open"}\n```\n</think>\n'
        '```json\n{"action": "gripper.close"}\n```',
        'draft {"action": "gripper.open"} no wait</think>{"action": "gripper.close"}',
        '<THINK>x</THINK>{"action": "gripper.close"}<think>after {"action": "gripper.open"}',
    ],
)
def test_inline_reasoning_is_never_parsed(text):
    assert P.parse_decision(text, ACTIVE_SINGLE).action == "gripper.close"


def test_split_reasoning():
    assert P.split_reasoning("<think>a</think> {b} <think>c</think>") == ("{b}", "a\nc")
    assert P.split_reasoning("plan</think>\n{x}") == ("{x}", "plan")
    assert P.split_reasoning("<think>cut off while thinking {") == ("", "cut off while thinking {")
    assert P.split_reasoning('{"stop": true}') == ('{"stop": true}', None)
    assert rejected('<think>{"stop": true}').message.startswith("the reply is empty")


def test_decoded_objects_validate_without_text():
    d = P.decision_from_object({"action": "camera.view_side"}, ACTIVE_SINGLE)
    assert isinstance(d, P.CameraAction)
    with pytest.raises(P.DecisionError) as e:
        P.decision_from_object(["gripper.open"], ACTIVE_SINGLE)
    assert e.value.field == P.REPLY


# -- rejections name the field ----------------------------------------------------------------

DUAL_MOVE = {
    "action": "dual_gripper.move_world",
    "left": {"axis": "x", "sign": "+", "distance_mm": 10},
    "right": {"axis": "x", "sign": "+", "distance_mm": 10},
}


@pytest.mark.parametrize(
    "reply,ctx,field,says",
    [
        (move(axis="w"), ACTIVE_SINGLE, "axis", "must be 'x', 'y' or 'z', got \"w\""),
        (rotate(axis="w"), ACTIVE_SINGLE, "axis", "'rx', 'ry' or 'rz'"),
        (move(sign="up"), ACTIVE_SINGLE, "sign", "got \"up\""),
        (move(sign=True), ACTIVE_SINGLE, "sign", "got true"),
        (move(mm=0), ACTIVE_SINGLE, "distance_mm", "must be between 1 and 100, got 0"),
        (move(mm=101), ACTIVE_SINGLE, "distance_mm", "must be between 1 and 100, got 101"),
        (move(mm="30mm"), ACTIVE_SINGLE, "distance_mm", "must be a number"),
        (move(mm=True), ACTIVE_SINGLE, "distance_mm", "must be a number, got true"),
        (rotate(deg=91), ACTIVE_SINGLE, "angle_deg", "must be between 1 and 90, got 91"),
        (rotate(deg=0.5), ACTIVE_SINGLE, "angle_deg", "got 0.5"),
        ({"action": "gripper.move_world", "axis": "x"}, ACTIVE_SINGLE, "sign", "required"),
        (move(), ACTIVE_DUAL, "arm", "required in dual-arm tasks"),
        (rotate(arm="up"), ACTIVE_DUAL, "arm", "'left' or 'right'"),
        (move(arm="left"), ACTIVE_SINGLE, "arm", "not an arm of this task"),
        ({"action": "left_gripper.open"}, ACTIVE_SINGLE, "action", "needs a dual-arm task"),
        (DUAL_MOVE, ACTIVE_SINGLE, "action", "needs a dual-arm task"),
        ({"action": "dual_gripper.open", "arm": "left"}, ACTIVE_DUAL, "arm", "omit 'arm'"),
        (
            {**DUAL_MOVE, "right": {"axis": "x", "sign": "+", "distance_mm": 101}},
            ACTIVE_DUAL,
            "right.distance_mm",
            "between 1 and 100",
        ),
        ({**DUAL_MOVE, "left": "x+10"}, ACTIVE_DUAL, "left", "must be a JSON object"),
        ({"action": "gripper.fly"}, ACTIVE_SINGLE, "action", "unknown action \"gripper.fly\""),
        ({"action": 3}, ACTIVE_SINGLE, "action", "must be a string"),
        ({"action": "stop"}, ACTIVE_SINGLE, "action", '{"stop": true}'),
        ({"reason": "thinking"}, ACTIVE_SINGLE, "action", "required"),
        ({"action": "camera.view_topdown"}, PASSIVE_SINGLE, "action", "passive protocol"),
        ({"action": "camera.zoom_in"}, PASSIVE_DUAL, "action", "passive protocol"),
        ({"action": "camera.view_left_topdown"}, ACTIVE_SINGLE, "action", "dual-arm task"),
        ({"action": "camera.view_both_side"}, ACTIVE_SINGLE, "action", "dual-arm task"),
        ({"action": "camera.view_top"}, ACTIVE_SINGLE, "action", "unknown action"),
        ({"action": "camera.view_topdown", "arm": "left"}, ACTIVE_DUAL, "arm", "view_left_"),
        ({"action": "camera.zoom_in", "reason": 5}, ACTIVE_SINGLE, "reason", "must be a string"),
        ({"stop": "yes"}, ACTIVE_SINGLE, "action", "required"),
        ({"tool": "geometry.fly"}, ACTIVE_SINGLE, "tool", "unknown tool"),
        ({"tool": ["geometry.verify"]}, ACTIVE_SINGLE, "tool", "must be a string"),
        ({"tool": "camera.zoom_in"}, ACTIVE_SINGLE, "tool", "is an action"),
        ({"tool": "expert.retrieve"}, PASSIVE_SINGLE, "tool", "not available in this episode"),
        ({"tool": "geometry.verify", "args": []}, ACTIVE_SINGLE, "args", "must be a JSON object"),
        ({"tool": "camera.history", "args": {}}, ACTIVE_SINGLE, "args.step", "required"),
        ({"tool": "camera.history", "args": {"step": -1}}, ACTIVE_SINGLE, "args.step", ">= 0"),
        ({"tool": "camera.history", "args": {"step": 1.5}}, ACTIVE_SINGLE, "args.step", "integer"),
        ({"tool": "camera.history", "args": {"step": True}}, ACTIVE_SINGLE, "args.step", "true"),
        ({"tool": "expert.frame", "args": {}}, ACTIVE_SINGLE, "args.steps", "required"),
        (
            {"tool": "expert.frame", "args": {"steps": list(range(9))}},
            ACTIVE_SINGLE,
            "args.steps",
            "at most 8 items, got 9",
        ),
        ({"tool": "expert.frame", "args": {"steps": []}}, ACTIVE_SINGLE, "args.steps", "least 1"),
        (tool("expert.frame", steps=[1, -2]), ACTIVE_SINGLE, "args.steps[1]", ">= 0"),
        (tool("expert.frame", step=1, steps=[2]), ACTIVE_SINGLE, "args", "not both"),
        (tool("expert.frame", step=1, view=""), ACTIVE_SINGLE, "args.view", "must not be empty"),
        ({"tool": "expert.learn", "args": "grasp it"}, ACTIVE_SINGLE, "args", "JSON object"),
        ('["gripper.open"]', ACTIVE_SINGLE, "reply", "must be one JSON object, got a list"),
        ('```json\n"gripper.open"\n```', ACTIVE_SINGLE, "reply", "got a string"),
        ('```json\n{"action": "gripper.open",}\n```', ACTIVE_SINGLE, "reply", "not valid JSON"),
        ('I will open: {"action": gripper.open}', ACTIVE_SINGLE, "reply", "not valid JSON"),
        ('{"action": "gripper.open",} near {the cube}', ACTIVE_SINGLE, "reply", "column 27"),
        ("I will open the gripper now.", ACTIVE_SINGLE, "reply", "no JSON object found"),
        ('{"action": "gripper.open"', ACTIVE_SINGLE, "reply", "without a matching '}'"),
        ("   ", ACTIVE_SINGLE, "reply", "empty"),
    ],
)  # fmt: skip
def test_rejections_name_the_field(reply, ctx, field, says):
    err = rejected(reply, ctx)
    assert err.field == field
    assert says in err.message
    assert says in str(err)
    if field != P.REPLY:
        assert str(err).startswith(f"field '{field}': ")


def test_unknown_names_list_the_valid_ones():
    err = rejected({"action": "gripper.fly"}, PASSIVE_DUAL)
    assert "dual_gripper.move_world" in err.message and "left_gripper.open" in err.message
    assert "camera." not in err.message  # passive: no camera action is valid
    err = rejected({"action": "gripper.fly"}, ACTIVE_SINGLE)
    assert "camera.view_topdown" in err.message and "dual_gripper" not in err.message
    err = rejected({"tool": "expert.fly"}, ACTIVE_SINGLE)
    assert err.message.endswith(
        "available tools: geometry.verify, camera.history, expert.retrieve, expert.frame, "
        "expert.learn"
    )


def test_every_wrong_field_reported_at_once():
    err = rejected(move(axis="w", sign="up", mm=500))
    assert err.field == "axis"
    assert [f for f, _ in err.others] == ["sign", "distance_mm"]
    assert "field 'distance_mm': must be between 1 and 100, got 500" in str(err)


def test_action_error_is_decision_error():
    with pytest.raises(P.DecisionError):
        P.parse_robot_action(move(mm=0), SINGLE)
    assert P.ActionError is P.DecisionError


# -- camera chain -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kinds,length",
    [
        ([], 0),
        (["camera"] * 3, 3),
        (["camera", "robot", "camera", "camera"], 2),
        (["camera", "tool", "camera", "rejected", "tool", "camera"], 3),
        (["camera"] * 5 + ["robot"], 0),
        (["camera"] * 7, 7),
    ],
)
def test_camera_chain_length(kinds, length):
    assert P.camera_chain_length(kinds) == length


def test_a_long_camera_chain_is_an_instruction_not_a_rejection():
    """The paper's "agent instruction limits camera-only chains": the prompt says so, and a
    sixth camera action in a row is still a valid decision."""
    ctx = P.DecisionContext(SINGLE, "active", camera_chain=P.MAX_CAMERA_CHAIN + 3)
    decision = P.parse_decision('{"action": "camera.zoom_out"}', ctx)
    assert isinstance(decision, P.CameraAction) and decision.increment == "zoom_out"
    assert isinstance(P.parse_decision(json.dumps(move()), ctx), P.MoveWorld)
    assert isinstance(P.parse_decision('{"stop": true}', ctx), P.Stop)


# -- labels and vocabulary --------------------------------------------------------------------


@pytest.mark.parametrize(
    "obj,ctx,label",
    [
        (move("z", "pos", 30), ACTIVE_SINGLE, "move_world z+30mm"),
        (move("z", "+", 30, arm="right"), ACTIVE_DUAL, "move_world right z+30mm"),
        (move("x", "-", 12.5), ACTIVE_SINGLE, "move_world x-12.5mm"),
        (rotate("ry", "-1", 45, arm="left"), ACTIVE_DUAL, "rotate_local left ry-45deg"),
        ({"action": "gripper.close"}, ACTIVE_SINGLE, "gripper.close"),
        ({"action": "gripper.open", "arm": "left"}, ACTIVE_DUAL, "gripper.open left"),
        ({"action": "dual_gripper.close"}, ACTIVE_DUAL, "dual_gripper.close"),
        (DUAL_MOVE, ACTIVE_DUAL, "dual_move_world left x+10mm right x+10mm"),
        ({"action": "camera.view_topdown"}, ACTIVE_SINGLE, "camera.view_topdown"),
        ({"action": "camera.view_both_side", "reason": "r"}, ACTIVE_DUAL, "camera.view_both_side"),
        ({"tool": "geometry.verify", "reason": "r"}, ACTIVE_SINGLE, "tool geometry.verify"),
        ({"stop": True, "reason": "done"}, ACTIVE_SINGLE, "stop"),
    ],
)
def test_labels_are_stable(obj, ctx, label):
    assert P.decision_label(decide(obj, ctx)) == label


def test_available_actions_single_active():
    lines = P.available_actions(SINGLE, "active", P.available_tools(demonstration=False))
    text = "\n".join(lines)
    assert '"distance_mm": 1..100' in text and '"angle_deg": 1..90' in text
    assert "arm" not in text and "dual_gripper" not in text and "left_gripper" not in text
    assert all(f'"{n}"' in text for n in SINGLE_CAMERA)
    assert not any(f'"{n}"' in text for n in DUAL_ONLY_CAMERA)
    assert "geometry.verify" in text and "camera.history" in text and "expert." not in text
    assert lines[-1] == '{"stop": true}'


def test_available_actions_dual_passive_with_demonstration():
    lines = P.available_actions(DUAL, "passive", P.available_tools(demonstration=True))
    text = "\n".join(lines)
    assert '"arm": "left|right"' in text and "dual_gripper.move_world" in text
    assert all(
        f"{s}_gripper.{v}" in text for s in ("left", "right", "dual") for v in ("open", "close")
    )
    assert "camera." not in text.replace("camera.history", "")
    assert all(t in text for t in ("expert.retrieve", "expert.frame", "expert.learn"))


@pytest.mark.parametrize("ctx", [ACTIVE_SINGLE, ACTIVE_DUAL, PASSIVE_SINGLE, PASSIVE_DUAL])
def test_every_parameterless_listed_action_parses(ctx):
    """The vocabulary shown to the model and the parser agree."""
    for line in P.available_actions(ctx.arms, ctx.protocol, ctx.tools):
        if line.startswith('{"action"') and line.count('"') == 4:
            assert decide(json.loads(line), ctx).action == json.loads(line)["action"]


def test_context_validation():
    with pytest.raises(ValueError, match="arms"):
        P.DecisionContext(("up",))
    with pytest.raises(ValueError, match="protocol"):
        P.DecisionContext(SINGLE, "both")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="tools"):
        P.DecisionContext(SINGLE, tools=("expert.fly",))


def test_budget_constants():
    assert (P.MAX_REPAIRS_PER_DECISION, P.MAX_TOOL_ROUND_TRIPS, P.MAX_CAMERA_CHAIN) == (2, 20, 5)


# -- the reference harness's spellings (PROTOCOL_FACTS 3.3) -------------------------------------


@pytest.mark.parametrize(
    "obj,expected",
    [
        ({"tool_name": "geometry.verify", "tool_args": None}, "tool geometry.verify"),
        ({"tool_name": "camera.history", "tool_args": {"step": 2}}, "tool camera.history step=2"),
        ({"tool": "geometry.verify", "args": None}, "tool geometry.verify"),
        ({"tool": "history.image", "args": {"step": 1}}, "tool camera.history step=1"),
        ({"tool": "image.history", "args": {"step": 1}}, "tool camera.history step=1"),
        ({"tool": "robot.geometry"}, "tool geometry.verify"),
        ({"action": "geometry.verify"}, "tool geometry.verify"),
        ({"action": "camera.history", "step": 3}, "tool camera.history step=3"),
        ({"action": "camera.history", "args": {"step": 4}}, "tool camera.history step=4"),
        ({**move(), "tool": None}, "move_world z+30mm"),
        ({**move(), "stop": None, "arm": None}, "move_world z+30mm"),
        ({**move(), "stop": False}, "move_world z+30mm"),
        ({**move(), "stop": "no"}, "move_world z+30mm"),
        (move(axis="X"), "move_world x+30mm"),
        (move(axis=" Y "), "move_world y+30mm"),
        (move(sign="ccw"), "move_world z+30mm"),
        (move(sign="CW"), "move_world z-30mm"),
        (rotate(axis="x"), "rotate_local rx+15deg"),
        (rotate(axis="Z", sign="cw"), "rotate_local rz-15deg"),
        (rotate(axis="RY", sign="ccw"), "rotate_local ry+15deg"),
        ({"action": "gripper.world_z_neg.20mm"}, "move_world z-20mm"),
        ({"action": "gripper.world_x_pos.12.5mm", "reason": "r"}, "move_world x+12.5mm"),
        ({"action": "gripper.local_rotate_ry_ccw.30deg"}, "rotate_local ry+30deg"),
        ({"action": "right_gripper.local_rotate_rz_cw.15deg"}, "rotate_local right rz-15deg"),
    ],
)
def test_reference_spellings_are_accepted(obj, expected):
    assert P.decision_label(decide(obj)) == expected


def test_reference_spellings_in_dual_arm_tasks():
    d = decide({"action": "left_gripper.world_y_pos.10mm"}, ACTIVE_DUAL)
    assert (d.arm, d.axis, d.sign) == ("left", "y", "+")
    dual = {
        "action": "dual_gripper.move_world",
        "left": {"axis": "Z", "sign": "pos", "distance_mm": 10, "arm": None},
        "right": {"axis": "z", "sign": "ccw", "distance_mm": 10},
    }
    assert P.decision_label(decide(dual, ACTIVE_DUAL)) == (
        "dual_move_world left z+10mm right z+10mm"
    )


def world(axis="z", sign="+", deg=15, **extra):
    return {"action": "gripper.rotate_world", "axis": axis, "sign": sign, "angle_deg": deg, **extra}


@pytest.mark.parametrize(
    "obj,ctx,label",
    [
        (world(), ACTIVE_SINGLE, "rotate_world z+15deg"),
        (world("X", "cw", 90), ACTIVE_SINGLE, "rotate_world x-90deg"),
        (world("rz", "ccw", 1), ACTIVE_SINGLE, "rotate_world z+1deg"),
        (world(" RY ", -1, "12.5"), ACTIVE_SINGLE, "rotate_world y-12.5deg"),
        (world("y", arm="left"), ACTIVE_DUAL, "rotate_world left y+15deg"),
        ({"action": "gripper.rotate_rz_ccw.30deg"}, ACTIVE_SINGLE, "rotate_world z+30deg"),
        ({"action": "gripper.rotate_rx_cw.7.5deg"}, PASSIVE_SINGLE, "rotate_world x-7.5deg"),
        ({"action": "left_gripper.rotate_ry_cw.45deg"}, ACTIVE_DUAL, "rotate_world left y-45deg"),
    ],
)
def test_world_rotations_are_accepted(obj, ctx, label):
    """The reference's unadvertised world rotation, in its JSON and its legacy form: world
    axes x|y|z, also spelled rx|ry|rz (the legacy name's spelling)."""
    d = decide(obj, ctx)
    assert isinstance(d, P.RotateWorld) and d.kind == "robot"
    assert P.decision_label(d) == label
    assert P.parse_robot_action(d.model_dump(exclude_none=True), ctx.arms) == d  # the sim's path


@pytest.mark.parametrize(
    "obj,ctx,field,words",
    [
        (world(deg=91), ACTIVE_SINGLE, "angle_deg", "90"),
        (world(deg=0.5), ACTIVE_SINGLE, "angle_deg", "1"),
        (world(axis="w"), ACTIVE_SINGLE, "axis", "'x'"),
        (world(sign="up"), ACTIVE_SINGLE, "sign", "+"),
        (world(), ACTIVE_DUAL, "arm", "required in dual-arm tasks"),
        (world(arm="left"), ACTIVE_SINGLE, "arm", "not an arm of this task"),
        ({"action": "gripper.rotate_rz_ccw.95deg"}, ACTIVE_SINGLE, "angle_deg", "90"),
    ],
)
def test_world_rotations_are_validated_as_local_ones(obj, ctx, field, words):
    err = rejected(obj, ctx)
    assert err.field == field and words in str(err), str(err)


@pytest.mark.parametrize("ctx", [ACTIVE_SINGLE, ACTIVE_DUAL, PASSIVE_SINGLE, PASSIVE_DUAL])
def test_world_rotation_is_never_advertised(ctx):
    """Accepted, never offered (as the reference): not in the vocabulary, not among the valid
    names an unknown action's repair lists."""
    listed = "\n".join(P.available_actions(ctx.arms, ctx.protocol, ctx.tools))
    assert "rotate_world" not in listed
    assert "gripper.rotate_world" not in P.action_names(ctx.arms, ctx.protocol)
    assert "rotate_world" not in str(rejected({"action": "gripper.fly"}, ctx))


@pytest.mark.parametrize(
    "name", ["gripper.image_left.small", "gripper.rotate_cw", "gripper.world_w_pos.20mm"]
)
def test_names_that_match_no_reference_pattern_stay_unknown(name):
    assert "unknown action" in str(rejected({"action": name}))


def test_the_sign_repair_lists_every_spelling():
    message = str(rejected(move(sign="up")))
    assert all(a in message for a in ("ccw", "cw", "pos", "negative"))
