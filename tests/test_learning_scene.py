"""The scene of the learning stage (PROTOCOL_FACTS 6.1): the first message of a learning
session over one video is what an evaluation episode at the demonstration's seed shows first,
its observation text and its head-camera image (frame 0 of the video), built from what the
model may see; the basket's atomic videos come with none.

Real parts: the demo is built by `vabench.demos` (C MuJoCo, the GL renderer, at the demo
settings), the episode runs through the engine on the C backend at the same image settings,
and the learning session talks to the embedded server over HTTP."""

from __future__ import annotations

import asyncio
import base64
import json
from typing import Any

from engine_util import STOP, count_images, run_scripted, user_texts

from vabench.agent.learning import learn_summary
from vabench.agent.learning_stage import load_demo_frames
from vabench.demos import build_demo, load_demo
from vabench.demos.build import DEMO_SETTINGS
from vabench.demos.store import default_cache
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.render.worker import RenderPool
from vabench.tasks import get_task

TASK = "grasp_single_cube"


def images(body: dict[str, Any]) -> list[bytes]:
    """The JPEG bytes of every image part of a Chat Completions body, in order."""
    out = []
    for m in body["messages"]:
        for part in m["content"] if isinstance(m["content"], list) else ():
            if part.get("type") == "image_url":
                out.append(base64.b64decode(part["image_url"]["url"].split(",", 1)[1]))
    return out


def test_the_scene_is_the_first_observation_of_an_episode_at_the_demo_seed():
    info = build_demo(TASK, mp4=False)
    task = get_task(TASK)
    demo = load_demo_frames(task, default_cache())
    assert demo.scene is not None
    assert demo.scene.image == load_demo(TASK).frames[0] == demo.frames[0]
    size = (DEMO_SETTINGS.width, DEMO_SETTINGS.height)
    with RenderPool(workers=1, max_size=size, timeout_s=120) as pool:
        episode = run_scripted(TASK, [STOP], pool, seed=info.seed, budget=3, image=DEMO_SETTINGS)
    first = json.loads(episode.bodies[0][1])
    (shown,) = user_texts(first)
    assert shown == demo.scene.text
    assert images(first) == [demo.scene.image]

    # and that is what the learning session's first request carries, with the video's size
    async def learn() -> list[bytes]:
        async with (
            LocalServer(ServerConfig(policy="random_action"), capture_bodies=True) as srv,
            LLMPool([srv.endpoint_config("m", "openai_chat")]) as llm,
        ):
            result = await learn_summary(task, demo, llm, "m")
        assert result.learned and result.scene, result.error
        assert srv.bodies is not None
        return [body for _, body in srv.bodies]

    body = json.loads(asyncio.run(learn())[0])
    (text,) = user_texts(body)
    assert demo.scene.text in text
    assert f"The demonstration video has {len(demo)} frames" in text
    assert images(body) == [demo.scene.image]


def test_the_basket_learns_from_its_atomic_videos_without_a_scene():
    basket = get_task("put_everything_in_basket")
    demo = load_demo_frames(basket, default_cache())
    assert demo.scene is None and demo.composite

    async def learn() -> tuple[Any, list[bytes]]:
        async with (
            LocalServer(ServerConfig(policy="random_action"), capture_bodies=True) as srv,
            LLMPool([srv.endpoint_config("m", "openai_chat")]) as llm,
        ):
            result = await learn_summary(basket, demo, llm, "m")
        assert srv.bodies is not None
        return result, [body for _, body in srv.bodies]

    result, bodies = asyncio.run(learn())
    # the stand-in passes the per-video gate (3 frames of each of 4 videos: two frame calls)
    assert result.learned and not result.scene, result.error
    assert len(bodies) == 4 and len(set(result.frames_inspected)) == 12
    first = json.loads(bodies[0])
    assert count_images(first) == 0
    (text,) = user_texts(first)
    assert "Observation step" not in text and "Gripper state" not in text
    assert "object_strategies" in (result.summary or {})
