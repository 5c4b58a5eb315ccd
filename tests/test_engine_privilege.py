"""The privilege boundary through the whole engine: every byte a model would receive, for one
episode of every base task (single- and dual-arm) and one passive episode of a single-arm and
a dual-arm task, holds no evaluator-only information.

Each episode runs against the embedded server with its request bodies captured, under a
scripted policy that exercises everything model-visible: a camera view, an increment, both
tools, an invalid reply (repair turn), a robot move, stop. The secrets are built from what the
evaluator knew during that episode (object positions sampled and after settling, at every
request; the seed; every camera position a view action could produce; task identifiers and
object body names) and every captured body is checked with `find_leaks`. The three provider
APIs take turns, so each body format is inspected.

The last test injects leaks into a real captured body and shows the same check catches them.
"""

from __future__ import annotations

import asyncio
import json

import pytest
from engine_util import (
    STOP,
    EpisodeRun,
    body_json,
    camera,
    count_images,
    move,
    robot_state,
    run_scripted_async,
    secrets_of,
    tool,
    user_texts,
)

from vabench.agent.conversation import ContextLimits
from vabench.agent.observation import GRIPPER_STATE_FIELDS
from vabench.agent.visibility import (
    FEEDBACK_FIELDS,
    LOCAL_AXES,
    find_leaks,
)
from vabench.render import camera as cam
from vabench.render.worker import RenderPool
from vabench.tasks import base_tasks, get_task

TASKS = [t.name for t in base_tasks()]
APIS = ("openai_chat", "openai_responses", "anthropic")
PASSIVE_TASKS = ("grasp_single_cube", "handover_horizontal_block")
ACTIVE_IMAGE_CAP = ContextLimits().max_images  # 4: FACTS image retention
PASSIVE_IMAGES = 5  # the current five-view bundle, nothing else


def test_every_base_family_is_covered():
    assert len(TASKS) == 14
    arms = {tuple(t.arms) for t in base_tasks()}
    assert arms == {("right",), ("left", "right")}


def _arm(run_arms: tuple[str, ...]) -> str | None:
    return "right" if len(run_arms) > 1 else None


def active_script(arms: tuple[str, ...]) -> list[str]:
    return [
        camera("view_topdown"),
        camera("zoom_in"),
        tool("geometry.verify"),
        tool("camera.history", step=1),
        "I would like to move the gripper up a little.",  # no JSON: a repair turn
        move("z", "+", 10, arm=_arm(arms)),
        STOP,
    ]


def passive_script(arms: tuple[str, ...]) -> list[str]:
    return [
        tool("geometry.verify"),
        "{not json",  # a repair turn
        move("z", "+", 10, arm=_arm(arms)),
        camera("view_topdown"),  # not available in the passive protocol: a repair turn
        STOP,
    ]


@pytest.fixture(scope="module")
def pool():
    with RenderPool(workers=1, timeout_s=60) as p:
        yield p


EPISODES = [(t, "active") for t in TASKS] + [(t, "passive") for t in PASSIVE_TASKS]
CONCURRENT = 3  # episodes at once: one renders while another simulates (2 cores here)


@pytest.fixture(scope="module")
def episodes(pool) -> dict[tuple[str, str], EpisodeRun]:
    """One episode per (task, protocol), all run once for the module, a few at a time (each
    on its own server, batch and slot; they share only the render pool)."""

    async def one(gate: asyncio.Semaphore, task: str, protocol: str) -> EpisodeRun:
        arms = tuple(get_task(task).arms)
        script = active_script(arms) if protocol == "active" else passive_script(arms)
        api = APIS[(TASKS.index(task) + (protocol == "passive")) % len(APIS)]
        async with gate:
            return await run_scripted_async(
                task, script, pool, protocol=protocol, budget=5, api=api
            )

    async def run_all() -> list[EpisodeRun]:
        gate = asyncio.Semaphore(CONCURRENT)
        return list(await asyncio.gather(*(one(gate, t, p) for t, p in EPISODES)))

    return dict(zip(EPISODES, asyncio.run(run_all()), strict=True))


def _check_episode(run: EpisodeRun, protocol: str) -> None:
    r = run.result
    # The script ran to its end: every model-visible feature was exercised before stop.
    assert (r.status, r.stop_reason) == ("failure", "model_stop"), r.error
    assert len(run.bodies) == r.model_calls == len(run.probes)
    if protocol == "active":
        assert (r.camera_actions, r.robot_actions, r.tool_calls, r.invalid_outputs) == (2, 1, 2, 1)
    else:
        assert (r.camera_actions, r.robot_actions, r.tool_calls, r.invalid_outputs) == (0, 1, 1, 2)
    assert [e["ok"] for e in run.of_type("tool")] == [True] * r.tool_calls

    secrets = secrets_of(run)
    assert any(s.name == "seed" for s in secrets)
    assert any(s.name.startswith("object") for s in secrets)
    assert any(s.name.startswith("camera head") for s in secrets)
    for i, (api, raw) in enumerate(run.bodies):
        leaks = find_leaks(raw, secrets)
        assert not leaks, f"request {i} ({api}):\n" + "\n".join(map(str, leaks))
        images = count_images(body_json(raw))
        if protocol == "active":
            assert 1 <= images <= ACTIVE_IMAGE_CAP, f"request {i}: {images} images"
        else:
            assert images == PASSIVE_IMAGES, f"request {i}: {images} images"

    last = user_texts(body_json(run.bodies[-1][1]))[-1]
    robot = robot_state(last)
    assert list(robot) == list(run.task.arms)
    for arm, fields in robot.items():
        assert list(fields) == [*GRIPPER_STATE_FIELDS, *FEEDBACK_FIELDS, "local_axes_world"], arm
        assert list(fields["local_axes_world"]) == list(LOCAL_AXES), arm
        # after the move: the feedback of an executed action, not the None of step 1
        assert fields["last_action_valid"] is not None


@pytest.mark.parametrize("task", TASKS)
def test_active_episode_leaks_nothing(episodes, task):
    _check_episode(episodes[task, "active"], "active")


@pytest.mark.parametrize("task", PASSIVE_TASKS)
def test_passive_episode_leaks_nothing(episodes, task):
    _check_episode(episodes[task, "passive"], "passive")


def _inject(raw: bytes, extra: str) -> bytes:
    """The body with `extra` appended to the text of its last user message."""
    body = json.loads(raw)
    messages = body.get("messages", body.get("input"))
    last = next(m for m in reversed(messages) if m.get("role") == "user")
    if isinstance(last["content"], str):
        last["content"] += extra
    else:
        part = next(p for p in last["content"] if isinstance(p.get("text"), str))
        part["text"] += extra
    return json.dumps(body).encode()


@pytest.mark.parametrize(
    "task",
    ["grasp_single_cube", "grasp_single_pen", "grasp_single_bottle", "handover_horizontal_block"],
)
def test_an_injected_leak_is_caught(episodes, task):
    """The check above can fail: the same bodies, each with one evaluator-only fact added."""
    run = episodes[task, "active"]
    secrets = secrets_of(run)
    raw = run.bodies[-1][1]
    assert find_leaks(raw, secrets) == []
    name, pos = next(iter(run.probes[-1].objects.items()))
    x, y, z = (float(v) for v in pos)
    hx, hy, hz = cam.HEAD_POS
    injected = {  # the text added -> the secret the leak must name
        f"\nThe {name} is at [{x:.4f}, {y:.4f}, {z:.4f}].": f"object {name}",
        f"\nTarget: {x * 1000:.1f} {y * 1000:.1f} {z * 1000:.1f} mm": f"object {name}",
        f'\n{{"seed": {run.seed}}}': "seed",
        f"\nEpisode {run.seed}.": "seed",
        f"\nThe camera sits at ({hx}, {hy}, {hz}).": "camera head",
    }
    for extra, secret in injected.items():
        leaks = find_leaks(_inject(raw, extra), secrets)
        assert any(leak.what.startswith(secret) for leak in leaks), extra
        assert all(leak.where.startswith(("messages", "input")) for leak in leaks), extra
    # identifiers: a latch or checkpoint name that is not plain prose
    words = [w for w in (*run.task.latches, *run.task.checkpoints) if "_" in w]
    for word in words:
        leaks = find_leaks(_inject(raw, f"\nstate: {word}"), secrets)
        assert any(leak.kind == "identifier" for leak in leaks), word
