"""Golden requests: the exact Chat Completions body a model receives at the first and at a
mid-episode decision of five episodes (active single-arm, passive, dual-arm, held-out, the
basket), with each image reduced to its size. A protocol change (prompt, observation text,
image retention, API defaults) shows as a diff of tests/golden/*.json: deliberate, reviewed,
and paired with a new `PROTOCOL_VERSION`, which every run directory's plan records (tested
here too).

The bodies are built by the engine's own parts (system prompt, observation text, conversation,
request options, the Chat Completions adapter) from a fixed robot state and fixed replies, so
the test takes no physics and runs in well under a second. Regenerate after a deliberate change:

    PYTHONPATH=. python tests/test_golden_requests.py --write
"""

from __future__ import annotations

import base64
import json
import re
import sys
from pathlib import Path
from typing import Any

import pytest

from vabench import protocol as P
from vabench.agent.conversation import Conversation
from vabench.agent.generation import request_options
from vabench.agent.observation import PASSIVE_VIEWS, ActionFeedback, observation_text
from vabench.agent.prompts import system_prompt
from vabench.config.load import load_config
from vabench.llm_pool import ModelEndpoint
from vabench.llm_pool.apis import ADAPTERS
from vabench.llm_pool.apis.base import encode_body
from vabench.llm_pool.testing import synthetic_image
from vabench.protocol.version import PROTOCOL_VERSION
from vabench.run_layout import RunDir
from vabench.sweep.plan import plan as plan_episodes
from vabench.sweep.rundir import check_run_dir, run_dir_problem
from vabench.tasks import get_task

GOLDEN = Path(__file__).parent / "golden"
SIZE = (640, 480)
EPISODES = {
    "active_single": ("grasp_single_cube", "active"),
    "passive_single": ("grasp_single_cube", "passive"),
    "active_dual": ("lift_pot", "active"),
    "active_heldout": ("place_cube_in_bowl_heldout", "active"),
    "active_basket": ("put_everything_in_basket", "active"),
}
MID_STEP = 6
_DATA_URL = re.compile(r"^data:image/jpeg;base64,(.*)$")


def _arm_state(x: float) -> dict[str, Any]:
    """A gripper pointing straight down, GC 12 cm below the control point."""
    return {
        "is_open": True,
        "finger_center_xyz": [x, -0.25, 0.93],
        "control_eepose_xyz": [x, -0.25, 1.05],
        "control_eepose_rpy_deg": [180.0, 0.0, 90.0],
        "control_eepose_quat": [0.0, 0.7071, 0.7071, 0.0],
        "local_axes_world": {"rx": [0.0, 0.0, -1.0], "ry": [1.0, 0.0, 0.0], "rz": [0.0, 1.0, 0.0]},
    }


def _reply(arms: tuple[str, ...], protocol: str, step: int) -> dict[str, Any]:
    if protocol == "active" and step % 2 == 1:
        return {"action": "camera.view_topdown", "reason": "look from above"}
    move: dict[str, Any] = {"action": "gripper.move_world", "axis": "z", "sign": "-"}
    move["distance_mm"] = 10
    if len(arms) > 1:
        move["arm"] = "right"
    return {**move, "reason": "lower"}


def _label(decision: dict[str, Any], arms: tuple[str, ...], protocol: str) -> str:
    ctx = P.DecisionContext(arms, protocol, _tools(protocol))  # type: ignore[arg-type]
    return P.decision_label(P.parse_decision(json.dumps(decision), ctx))


def _tools(protocol: str) -> tuple[str, ...]:
    tools = P.available_tools(demonstration=False)
    return tuple(t for t in tools if protocol == "active" or t != "camera.history")


def _images(protocol: str, step: int) -> Any:
    w, h = SIZE
    if protocol == "active":
        return synthetic_image(w, h, size=512, seed=step)
    return {
        v: synthetic_image(w, h, size=512, seed=10 * step + i) for i, v in enumerate(PASSIVE_VIEWS)
    }


def _jpeg_size(jpeg: bytes) -> list[int]:
    """Width and height from a JPEG's first start-of-frame marker."""
    i = jpeg.find(b"\xff\xc0")
    assert i >= 0, "no start-of-frame marker"
    return [int.from_bytes(jpeg[i + 7 : i + 9], "big"), int.from_bytes(jpeg[i + 5 : i + 7], "big")]


def _summarize(body: dict[str, Any]) -> dict[str, Any]:
    """The body with every image replaced by its pixel size."""

    def part(p: Any) -> Any:
        if isinstance(p, dict) and p.get("type") == "image_url":
            data = _DATA_URL.match(p["image_url"]["url"])
            assert data is not None
            return {"type": "image", "size": _jpeg_size(base64.b64decode(data.group(1)))}
        return p

    messages = []
    for m in body["messages"]:
        content = m["content"]
        if isinstance(content, list):
            content = [part(p) for p in content]
        messages.append({**m, "content": content})
    return {**body, "messages": messages}


def golden_requests(task_name: str, protocol: str) -> dict[str, Any]:
    """The first and the mid-episode (decision `MID_STEP`) request bodies of one episode."""
    task = get_task(task_name)
    arms = tuple(task.arms)
    tools = _tools(protocol)
    endpoint = ModelEndpoint(name="model", api="openai_chat", model="model")
    options = request_options(endpoint, None)
    conv = Conversation(
        system_prompt(arms, protocol, list(tools), task=task_name),
        protocol=protocol,  # type: ignore[arg-type]
    )
    available = P.available_actions(arms, protocol, tools)  # type: ignore[arg-type]
    xs = {"left": -0.3, "right": 0.3}
    executed: list[str] = []
    bodies: dict[str, Any] = {}
    for step in range(1, MID_STEP + 1):
        text = observation_text(
            step=step,
            step_budget=task.step_budget,
            instruction=task.instruction,
            proprio={a: _arm_state(xs[a]) for a in arms},
            arms=arms,
            feedback=ActionFeedback(),
            executed_actions=executed,
            demonstration_summary=None,
            available_actions=available,
            history_steps=list(range(1, step)) if "camera.history" in tools else None,
        )
        conv.add_observation(text, _images(protocol, step), step)
        if step in (1, MID_STEP):
            body = ADAPTERS["openai_chat"].build_body(endpoint, conv.request(options), options)
            bodies["first" if step == 1 else "mid"] = _summarize(json.loads(encode_body(body)))
        decision = _reply(arms, protocol, step)
        conv.add_reply("```json\n" + json.dumps(decision) + "\n```")
        executed.append(_label(decision, arms, protocol))
    return {"protocol_version": PROTOCOL_VERSION, "task": task_name, "protocol": protocol, **bodies}


def _path(name: str) -> Path:
    return GOLDEN / f"request_{name}.json"


@pytest.mark.parametrize("name", list(EPISODES))
def test_request_bodies_match_the_golden_files(name):
    want = json.loads(_path(name).read_text(encoding="utf-8"))
    got = golden_requests(*EPISODES[name])
    assert got == want, (
        f"the request body of {name} changed: if the protocol change is deliberate, bump "
        "PROTOCOL_VERSION and regenerate (python tests/test_golden_requests.py --write)"
    )


def test_golden_requests_show_the_protocol():
    active = golden_requests(*EPISODES["active_single"])
    passive = golden_requests(*EPISODES["passive_single"])
    assert active["first"]["reasoning_effort"] == "medium"

    def images(body: dict[str, Any]) -> int:
        return sum(
            1
            for m in body["messages"]
            if isinstance(m["content"], list)
            for p in m["content"]
            if p.get("type") == "image"
        )

    assert images(active["first"]) == 1 and images(passive["first"]) == 5
    assert images(passive["mid"]) == 5  # the current bundle only
    assert images(active["mid"]) == 1  # the current image only (paper)
    held = golden_requests(*EPISODES["active_heldout"])["first"]["messages"][0]["content"]
    assert "# Held-out evaluation" in held
    basket = golden_requests(*EPISODES["active_basket"])["first"]["messages"][0]["content"]
    assert "# Task profile: put_everything_in_basket" in basket


def test_the_plan_of_a_run_directory_records_the_protocol_version(tmp_path):
    config = load_config(Path(__file__).parents[1] / "configs" / "smoke.yaml", require_keys=False)
    keys = plan_episodes(config)
    check_run_dir(tmp_path, config, keys, config.document())
    plan = json.loads(RunDir(tmp_path).plan.read_text(encoding="utf-8"))
    assert plan["fields"]["protocol_version"] == PROTOCOL_VERSION
    # a run directory of another protocol is refused on resume, naming the field
    plan["fields"]["protocol_version"] = "vabench-0"
    RunDir(tmp_path).plan.write_text(json.dumps(plan), encoding="utf-8")
    problem = run_dir_problem(tmp_path, config, keys)
    assert problem is not None and "protocol_version: " in problem


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_golden_requests.py --write")
    GOLDEN.mkdir(exist_ok=True)
    for episode, (task_name, protocol) in EPISODES.items():
        doc = golden_requests(task_name, protocol)
        _path(episode).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(_path(episode))
