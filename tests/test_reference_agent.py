"""The reference-servo agent (vabench.reference_agent): what it may import, how it treats an
image it cannot read, determinism, and one real episode through the engine and the embedded
server.

The episode (grasp_single_cube, its first verified seed, 640x480, C backend) runs once per
module; its requests, recorded as the policy received them, feed the other tests.
"""

from __future__ import annotations

import ast
import asyncio
import dataclasses
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image as PILImage

from vabench import protocol
from vabench.agent.conversation import SUMMARY_INSTRUCTION
from vabench.agent.engine import Episode, EpisodeSpec
from vabench.agent.records import EpisodeResult
from vabench.agent.services import task_services
from vabench.llm_pool.apis.base import IncomingRequest
from vabench.llm_pool.config import load_endpoints
from vabench.llm_pool.messages import ChatRequest, Image, Turn
from vabench.llm_pool.policies import make_policy
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer
from vabench.reference_agent import ReferenceServo, reply_text
from vabench.reference_agent.policy import SUMMARY_REPLY
from vabench.render.worker import ImageSettings, RenderPool
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds

PACKAGE = Path(__file__).resolve().parents[1] / "vabench" / "reference_agent"
FORBIDDEN = ("mujoco", "jax", "vabench.sim_mjx", "vabench.tasks", "vabench.render")
# What the package may import: the standard library, numpy, Pillow, simplejpeg (libjpeg-turbo:
# its decode) and itself.
ALLOWED_ROOTS = {"numpy", "PIL", "simplejpeg", "__future__", *sys.stdlib_module_names}
TASK = "grasp_single_cube"


def _forbidden(names: set[str]) -> list[str]:
    return sorted(n for n in names if any(n == f or n.startswith(f + ".") for f in FORBIDDEN))


# -- (a) import isolation ----------------------------------------------------------------------


def test_import_loads_nothing_of_simulator_tasks_or_renderer() -> None:
    """A fresh interpreter imports the package, then builds the policy through the registry:
    neither step loads the simulator, the tasks or MuJoCo/JAX, and the package itself loads
    no renderer module either (the registry's own module does, through vabench.protocol's
    camera names; that is the pool's, not the agent's)."""
    code = f"""
import json, sys
forbidden = {FORBIDDEN!r}
def bad(names):
    return sorted(n for n in names if any(n == f or n.startswith(f + ".") for f in forbidden))
import vabench.reference_agent
after_package = bad(sys.modules)
import vabench.llm_pool.policies as policies
before = set(sys.modules)
policy = policies.make_policy("reference_servo")
new = set(sys.modules) - before
print(json.dumps({{
    "after_package": after_package,
    "new_by_make_policy": bad(new),
    "everything": [n for n in bad(sys.modules) if not n.startswith("vabench.render")],
    "type": type(policy).__name__,
}}))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["after_package"] == []
    assert report["new_by_make_policy"] == []
    assert report["everything"] == []
    assert report["type"] == "ReferenceServo"


def test_package_source_imports_only_stdlib_numpy_pillow_simplejpeg_and_itself() -> None:
    files = sorted(PACKAGE.glob("*.py"))
    assert len(files) >= 5
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{path.name}: relative import"
                names = [node.module or ""]
            else:
                continue
            for name in names:
                ok = name.split(".")[0] in ALLOWED_ROOTS or name.startswith(
                    "vabench.reference_agent"
                )
                assert ok, f"{path.name} imports {name}"


# -- one real episode, recording the requests --------------------------------------------------


class Recording:
    """The reference policy, keeping every request it answered."""

    def __init__(self) -> None:
        self.inner = ReferenceServo()
        self.requests: list[IncomingRequest] = []

    async def respond(self, request: IncomingRequest) -> str:
        self.requests.append(request)
        return await self.inner.respond(request)


@dataclasses.dataclass
class Run:
    result: EpisodeResult
    requests: list[IncomingRequest]


async def _episode(out_dir: Path) -> Run:
    task = get_task(TASK)
    seed = verified_seeds(TASK)[0]
    policy = Recording()
    spec = EpisodeSpec(TASK, seed, "reference-servo", "active", 0, out_dir)
    with RenderPool(workers=1, max_size=(640, 480), timeout_s=60) as pool:
        async with LocalServer(policy=policy) as server:
            endpoint = server.endpoint_config("reference-servo", "openai_chat")
            async with (
                LLMPool(load_endpoints([endpoint])) as llm,
                task_services(
                    task, 1, llm, pool, backend="c", image=ImageSettings(640, 480, 95)
                ) as services,
            ):
                result = await Episode(spec, services).run()
    return Run(result, policy.requests)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    return asyncio.run(_episode(tmp_path_factory.mktemp("ref") / "episode"))


# -- (d) the episode succeeds --------------------------------------------------------------------


def test_real_episode_succeeds(run: Run) -> None:
    assert run.result.status == "success", run.result
    assert run.result.steps_used < run.result.step_budget
    assert run.result.invalid_outputs == 0


# -- (b) noise instead of the image --------------------------------------------------------------


def _noise_jpeg(shape: tuple[int, int], seed: int) -> bytes:
    pixels = np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)
    buf = io.BytesIO()
    PILImage.fromarray(pixels).save(buf, "JPEG", quality=95)
    return buf.getvalue()


def _with_images_replaced(request: IncomingRequest, jpeg: bytes) -> IncomingRequest:
    turns = tuple(
        Turn(t.role, tuple(p if isinstance(p, str) else Image(jpeg) for p in t.content))
        for t in request.chat.turns
    )
    chat = dataclasses.replace(request.chat, turns=turns)
    return dataclasses.replace(request, chat=chat)


def _decision(text: str) -> protocol.Decision:
    ctx = protocol.DecisionContext(arms=("right",))
    return protocol.parse_decision(text, ctx)


def test_noise_image_makes_it_look_again_or_stop(run: Run) -> None:
    """Every request of the episode, with its images replaced by noise: the reply is a camera
    action or stop, never a robot action; and a second noisy look in a row ends in a stop."""
    kinds = set()
    for k, request in enumerate(run.requests):
        noisy = _with_images_replaced(request, _noise_jpeg((480, 640), k))
        decision = _decision(reply_text(noisy))
        assert isinstance(decision, protocol.CameraAction | protocol.Stop), (k, decision)
        kinds.add(type(decision).__name__)
    assert "CameraAction" in kinds
    # the clean run did act on the same requests (so the test can fail)
    clean = [_decision(reply_text(r)) for r in run.requests]
    assert any(isinstance(d, protocol.MoveWorld) for d in clean)


def test_noise_again_and_again_stops(run: Run) -> None:
    request = run.requests[0]
    first = reply_text(_with_images_replaced(request, _noise_jpeg((480, 640), 1)))
    assert isinstance(_decision(first), protocol.CameraAction)
    turns = run.requests[0].chat.turns
    chat = dataclasses.replace(
        request.chat,
        turns=(*turns, Turn("assistant", (first,)), *turns[-1:]),
    )
    again = _with_images_replaced(
        dataclasses.replace(request, chat=chat), _noise_jpeg((480, 640), 2)
    )
    replies = [reply_text(again)]
    chat2 = dataclasses.replace(
        again.chat, turns=(*again.chat.turns, Turn("assistant", (replies[0],)), *turns[-1:])
    )
    third = _with_images_replaced(
        dataclasses.replace(request, chat=chat2), _noise_jpeg((480, 640), 3)
    )
    replies.append(reply_text(third))
    assert isinstance(_decision(replies[-1]), protocol.Stop)


# -- (c) determinism -------------------------------------------------------------------------------


def test_same_request_same_reply(run: Run) -> None:
    fresh = make_policy("reference_servo")
    for request in run.requests:
        a = reply_text(request)
        b = reply_text(request)
        c = asyncio.run(fresh.respond(request))
        assert a == b == c


def test_unreadable_request_stops(run: Run) -> None:
    request = run.requests[3]
    turns = (*request.chat.turns[:-1], Turn.user("hello"))
    chat = ChatRequest(turns=turns, system="s")
    reply = reply_text(IncomingRequest(api="openai_chat", model="m", chat=chat))
    assert isinstance(_decision(reply), protocol.Stop)


def test_compaction_request_gets_text_not_an_action(run: Run) -> None:
    """History compaction sends the earlier messages as text in one user turn; the agent's
    summary is its memo, so it answers with a short text (the engine only stores it)."""
    earlier = "\n\n".join(
        f"--- {'You' if t.role == 'assistant' else 'Harness'}:\n{t.text}"
        for t in run.requests[5].chat.turns
    )
    chat = ChatRequest((Turn.user(earlier + "\n\n" + SUMMARY_INSTRUCTION),), "system")
    reply = reply_text(IncomingRequest(api="openai_chat", model="m", chat=chat))
    assert reply == SUMMARY_REPLY
