"""Validation of robot actions: aliases, ranges, arm rules, error messages naming the field."""

from __future__ import annotations

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
