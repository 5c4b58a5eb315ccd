"""Nothing evaluator-only reaches a learning session: every request body of a session over a
real demonstration (one video, and the basket's form of several videos in one index) passes
the leak checker with the demonstrations' secrets (object positions at the demo seed, the head
camera's position, the family names and the model ids, the demo seed), and the summary the
session stores carries none of them either."""

from __future__ import annotations

import asyncio
import json

from vabench.agent.demonstration import DemoFrames
from vabench.agent.learning import learn_summary
from vabench.agent.learning_stage import load_demo_frames
from vabench.agent.visibility import Secret, episode_secrets, find_leaks
from vabench.demos import build_demo, load_demo
from vabench.demos.store import default_cache
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.render.camera import head_view
from vabench.tasks import get_task
from vabench.tasks.base import Task
from vabench.tasks.task_batch import TaskBatch

FAMILIES = ("grasp_single_cube", "place_single_cube")


def demo_secrets(task: Task) -> list[Secret]:
    info = build_demo(task.name, mp4=False)
    sample = task.sample(info.seed)
    objects = {f"{task.name} {n}": pos for n, (pos, _) in sample.poses.items()}
    batch = TaskBatch(task, 1, backend="c")
    batch.reset([0], [info.seed])
    view = batch.views([0])[0]
    gcs = {arm: view.arms[arm].gc for arm in task.arms}
    cameras = {f"{task.name} head": head_view(gcs, task.arms).pos}
    identifiers = [task.name, *task.variants, *task.latches, *task.checkpoints]
    secrets = episode_secrets(objects, None, cameras, identifiers)
    return [*secrets, Secret(f"{task.name} demo seed", word=str(info.seed))]


def run_session(demo: DemoFrames, task: Task) -> tuple[list[bytes], dict]:
    async def main():
        async with LocalServer(ServerConfig(policy="random_action"), capture_bodies=True) as srv:
            async with LLMPool([srv.endpoint_config("m", "openai_chat")]) as llm:
                result = await learn_summary(task, demo, llm, "m")
            return [body for _, body in srv.bodies], result

    bodies, result = asyncio.run(main())
    assert result.status == "learned", result.error
    return bodies, result.model_dump()


def test_a_learning_session_sees_no_evaluator_only_state():
    secrets = [s for name in FAMILIES for s in demo_secrets(get_task(name))]
    task = get_task(FAMILIES[0])
    single = load_demo_frames(task, default_cache())
    parts = [
        (get_task(n).instruction, DemoFrames(load_demo(n).frames, load_demo(n).info.fps, n))
        for n in FAMILIES
    ]
    several = DemoFrames.concat(parts, label="+".join(FAMILIES))
    for demo in (single, several):
        bodies, result = run_session(demo, task)
        assert len(bodies) == 3  # retrieve, frames, learn
        for body in bodies:
            leaks = find_leaks(json.loads(body), secrets)
            assert not leaks, "\n".join(map(str, leaks))
        assert not find_leaks({"summary": result["summary_text"]}, secrets)


def test_the_checker_sees_a_family_name_in_a_session():
    """The test above can fail: a label that reached the prompt would be caught."""
    task = get_task(FAMILIES[0])
    secrets = demo_secrets(task)
    leaky = {"messages": [{"role": "user", "content": f"video of {task.name}"}]}
    assert find_leaks(leaky, secrets)
