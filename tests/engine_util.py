"""Shared helpers of the engine tests: one episode end to end against the embedded server.

`run_scripted(...)` runs one `Episode` of a task on the C MuJoCo backend, with tiny images,
a short step budget and a `ProbingPolicy` behind a real `LocalServer` (real HTTP on
loopback, request bodies captured). The policy replays scripted replies and, before each
reply, records what the evaluator side looks like at that moment (`Probe`): the simulator is
idle then (the episode is waiting for the model), so the probe reads the batch without racing
the engine. Tests compare probes around a decision (a camera action must not touch physics)
and build each episode's secrets from them (object positions, camera positions).
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vabench.agent.engine import Episode, EpisodeSpec
from vabench.agent.observation import GRIPPER_STATE_FIELDS
from vabench.agent.records import EpisodeResult
from vabench.agent.services import EngineSettings, task_services
from vabench.agent.simulation import SimCounters
from vabench.agent.visibility import Secret, episode_secrets
from vabench.llm_pool.apis.base import IncomingRequest
from vabench.llm_pool.policies import PolicyReply, ScriptedPolicy, fenced_json
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.render import camera as cam
from vabench.render.backends import Renderer
from vabench.render.images import ImageSettings
from vabench.tasks import get_task
from vabench.tasks.base import Task
from vabench.tasks.manifests import verified_seeds

SMALL = ImageSettings(160, 120)
"""Tiny images: the engine's behaviour does not depend on the resolution."""
FAST_RETRY = {"backoff_base_s": 0.01, "backoff_max_s": 0.02}
SLOT = 0  # every run here has one slot


def reply(obj: dict[str, Any]) -> str:
    """A reply in the shape the harness parses (one fenced json block)."""
    return fenced_json(obj)


def move(axis: str = "z", sign: str = "+", mm: int = 10, arm: str | None = None) -> str:
    action: dict[str, Any] = {
        "action": "gripper.move_world",
        "axis": axis,
        "sign": sign,
        "distance_mm": mm,
    }
    if arm is not None:
        action["arm"] = arm
    return reply(action)


def camera(name: str) -> str:
    return reply({"action": f"camera.{name}"})


def tool(name: str, **args: Any) -> str:
    return reply({"tool": name, "args": args})


STOP = reply({"stop": True})


@dataclass(frozen=True)
class Probe:
    """The evaluator side while the model is being asked (one per request)."""

    step_calls: int
    qpos: np.ndarray  # the episode's slot
    objects: dict[str, np.ndarray]  # body name -> position (m)
    gcs: dict[str, np.ndarray]  # arm -> grasp centre (m)
    camera_pos: np.ndarray | None  # the active camera; None in the passive protocol


class ProbingPolicy:
    """`ScriptedPolicy` that records a `Probe` before each reply (see the module docstring)."""

    def __init__(self, replies: Sequence[str | dict[str, Any]], cycle: bool = False):
        self.script = ScriptedPolicy(replies, cycle=cycle)
        self.episode: Episode | None = None
        self.probes: list[Probe] = []

    async def respond(self, request: IncomingRequest) -> str | PolicyReply:
        ep = self.episode
        if ep is not None:
            tb = ep.svc.sim.batch
            view = tb.views([SLOT])[SLOT]
            self.probes.append(
                Probe(
                    step_calls=ep.svc.sim.counters.step_calls,
                    qpos=np.array(tb.batch.qpos()[SLOT], copy=True),
                    objects={n: np.array(p) for n, (p, _) in view.objects.items()},
                    gcs={a: np.array(v.gc) for a, v in view.arms.items()},
                    camera_pos=None if ep.camera is None else np.array(ep.camera.pos),
                )
            )
        return await self.script.respond(request)


@dataclass
class EpisodeRun:
    task: Task
    seed: int
    result: EpisodeResult
    episode: Episode
    bodies: list[tuple[str, bytes]]
    probes: list[Probe]
    counters: SimCounters
    object_names: tuple[str, ...]
    events: list[dict[str, Any]] = field(default_factory=list)

    def of_type(self, type_: str) -> list[dict[str, Any]]:
        return [e for e in self.events if e["type"] == type_]


async def run_scripted_async(
    task_name: str,
    replies: Sequence[str | dict[str, Any]],
    pool: Renderer,
    *,
    seed: int | None = None,
    protocol: str = "active",
    budget: int | None = 6,
    api: str = "openai_chat",
    out_dir: Path | None = None,
    server_config: ServerConfig | None = None,
    retry: dict[str, Any] | None = None,
    cycle: bool = False,
    inner: Any | None = None,
    image: ImageSettings = SMALL,
    settings: EngineSettings | None = None,
    backend: str = "c",
    endpoint: dict[str, Any] | None = None,
    **batch_kwargs: Any,
) -> EpisodeRun:
    """One episode of `task_name` (its first verified seed unless `seed`) answered by
    `replies`, or by the embedded-server policy `inner` (an object with `async respond`)
    when given; see the module docstring. `endpoint`: more fields of the model's config."""
    task = get_task(task_name)
    seed = verified_seeds(task_name)[0] if seed is None else seed
    policy = ProbingPolicy(replies or [STOP], cycle=cycle)
    if inner is not None:
        policy.script = inner
    spec = EpisodeSpec(
        task_name,
        seed,
        "m",
        protocol,
        out_dir=out_dir,
        step_budget=budget,  # type: ignore[arg-type]
    )
    async with LocalServer(server_config, policy=policy, capture_bodies=True) as server:
        config = server.endpoint_config(
            "m", api, retry={**FAST_RETRY, **(retry or {})}, **(endpoint or {})
        )
        async with (
            LLMPool([config]) as llm,
            task_services(
                task,
                1,
                llm,
                pool,
                backend=backend,
                image=image,
                settings=settings,
                **batch_kwargs,
            ) as services,
        ):
            episode = Episode(spec, services)
            policy.episode = episode
            result = await episode.run()
            counters = services.sim.counters
            names = tuple(services.sim.batch.ix.adr)
    assert server.bodies is not None
    return EpisodeRun(
        task,
        seed,
        result,
        episode,
        list(server.bodies),
        policy.probes,
        counters,
        names,
        list(episode.rec.events),
    )


def run_scripted(*args: Any, **kwargs: Any) -> EpisodeRun:
    return asyncio.run(run_scripted_async(*args, **kwargs))


def secrets_of(run: EpisodeRun) -> list[Secret]:
    """Everything evaluator-only an episode knew, as `find_leaks` secrets: object positions
    as sampled and at every request, the seed, every camera position a view action could
    produce at every request, the active camera's, model ids, latch, checkpoint and body
    names."""
    task = run.task
    objects: dict[str, Any] = {
        f"{name} sampled": pos for name, (pos, _) in task.sample(run.seed).poses.items()
    }
    cameras: dict[str, Any] = {}
    for i, probe in enumerate(run.probes):
        objects.update({f"{name} at request {i}": pos for name, pos in probe.objects.items()})
        views = camera_positions(probe.gcs, task.arms)
        cameras.update({f"{view} at request {i}": pos for view, pos in views.items()})
        if probe.camera_pos is not None:
            cameras[f"active camera at request {i}"] = probe.camera_pos
    identifiers = [*task.variants, *task.latches, *task.checkpoints, *run.object_names]
    return episode_secrets(objects, run.seed, cameras, identifiers)


# -- reading provider request bodies ----------------------------------------------------------

_IMAGE_PART_TYPES = frozenset({"image_url", "input_image", "image"})


def _walk(node: Any) -> Iterator[dict[str, Any]]:
    if isinstance(node, dict):
        yield node
        for value in node.values():
            yield from _walk(value)
    elif isinstance(node, list):
        for value in node:
            yield from _walk(value)


def body_json(raw: bytes) -> dict[str, Any]:
    return json.loads(raw)


def count_images(body: dict[str, Any]) -> int:
    """Image parts of an OpenAI Chat, OpenAI Responses or Anthropic request body."""
    return sum(1 for node in _walk(body) if node.get("type") in _IMAGE_PART_TYPES)


def user_messages(body: dict[str, Any]) -> list[dict[str, Any]]:
    """The user messages of a request body, oldest first (any of the three APIs)."""
    messages = body.get("messages", body.get("input", []))
    return [m for m in messages if m.get("role") == "user"]


def user_texts(body: dict[str, Any]) -> list[str]:
    """The text of each user message, oldest first (any of the three APIs)."""
    out = []
    for msg in user_messages(body):
        content = msg.get("content")
        if isinstance(content, str):
            out.append(content)
            continue
        out.append(
            "\n".join(
                part["text"]
                for part in content
                if isinstance(part, dict) and isinstance(part.get("text"), str)
            )
        )
    return out


_GRIPPER_LINE = re.compile(r"^Gripper state: (\{.*\})$", re.M)
_GEOMETRY_LINE = re.compile(r"^Robot self-geometry[^\n]*\n(\{.*\})$", re.M)


def robot_state(text: str) -> dict[str, Any]:
    """The robot state of an observation text, per arm: the gripper state's fields
    (`GRIPPER_STATE_FIELDS`), the episode's feedback flags and the self-geometry's
    `local_axes_world`."""
    state, geometry = _GRIPPER_LINE.search(text), _GEOMETRY_LINE.search(text)
    assert state is not None and geometry is not None, f"no robot state in: {text[:300]}"
    gripper, geo = json.loads(state.group(1)), json.loads(geometry.group(1))
    flags = {k: gripper[k] for k in ("last_action_valid", "last_planner_success")}
    if gripper["active_arm"] != "both":
        arms = {gripper["active_arm"]: (gripper, geo)}
    else:
        arms = {a: (gripper[a], geo[a]) for a in ("left", "right")}
    return {
        arm: {
            **{k: v for k, v in fields.items() if k in GRIPPER_STATE_FIELDS},
            **flags,
            "local_axes_world": g["local_axes_world"],
        }
        for arm, (fields, g) in arms.items()
    }


def camera_positions(
    gcs: dict[str, np.ndarray], arms: Sequence[str]
) -> dict[str, tuple[float, ...]]:
    """Every camera position a view action can put the camera at for these grasp centres:
    the head camera and each semantic view for each target the task offers."""
    targets = ["left", "right", "both"] if len(arms) > 1 else list(arms)
    out = {"head": tuple(float(v) for v in cam.HEAD_POS)}
    for view in cam.VIEWS:
        for target in targets:
            pose = cam.semantic_view(view, gcs, target)
            out[f"{target}_{view}"] = tuple(float(v) for v in pose.pos)
    return out
