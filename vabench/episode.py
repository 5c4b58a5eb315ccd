"""Run one episode against a configured model and print its trajectory.

    python -m vabench.episode --task place_single_cube --seed 1000 --model local \
        [--config models.yaml] [--protocol active|passive] [--out DIR]
        [--backend warp|mjx|c]

Without `--config`, the model is the embedded server (started here, policy `--policy`,
default a random valid actor), reached over real HTTP on loopback. With `--config`, the
model comes from the file's `models:` list (the sweep's schema; keys from the environment
variables the entries name). Records go to `--out` (default
`runs/episodes/<model>/<protocol>/<task>/seed_<S>/run_<R>`): events.jsonl, frames/,
result.json. The exit code is 0 for a finished episode (success or failure), 1 for an error.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from vabench.agent.engine import Episode, EpisodeSpec
from vabench.agent.records import EpisodeResult
from vabench.agent.services import task_services
from vabench.llm_pool.config import ConfigError, load_endpoints
from vabench.llm_pool.errors import RequestRejected
from vabench.llm_pool.policies import POLICIES
from vabench.llm_pool.pool import LLMPool
from vabench.llm_pool.server import LocalServer, ServerConfig
from vabench.llm_pool.spend import Pricing, cost_text, pricing_of
from vabench.render.backends import make_renderer
from vabench.render.images import ImageSettings
from vabench.run_layout import RESULT, RunDir
from vabench.sim_mjx.backends import BackendUnavailable
from vabench.sim_mjx.cli import add_physics_arguments, physics_of


def load_models(path: Path) -> list[Any]:
    """The `models:` list of a YAML file (a sweep config or a file of endpoints)."""
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(str(path), f"cannot read: {err}") from None
    if not isinstance(data, dict) or "models" not in data:
        raise ConfigError("models", f"{path} has no top-level 'models:' list")
    return load_endpoints(data["models"])


def print_trajectory(
    events: Sequence[dict[str, Any]], result: EpisodeResult, pricing: Pricing | None = None
) -> None:
    """The episode step by step, then its outcome; `pricing`: how the model is priced (its
    cost reads "price not set" rather than $0.0000 for a model without prices)."""
    for e in events:
        kind = e["type"]
        if kind == "reset":
            print(f"reset: {'ok' if e['ok'] else 'FAILED ' + str(e['reason'])}")
        elif kind == "rejection":
            print(f"  step {e['step']:>3}  rejected (repair {e['repair']}): {e['message']}")
        elif kind == "tool":
            print(f"  step {e['step']:>3}  {e['label']}" + ("" if e["ok"] else "  (error)"))
        elif kind == "camera":
            print(f"  step {e['step']:>3}  {e['label']:<38} -> view {e['view']}")
        elif kind == "action":
            status = (
                "ok"
                if e["valid"] and e["planner_success"]
                else ("invalid: " + str(e["error"]) if not e["valid"] else "planner failed")
            )
            flags = f"progress {e['progress']}" + ("  SUCCESS" if e["success"] else "")
            print(f"  step {e['step']:>3}  {e['label']:<38} {status:<16} {flags}")
            if e.get("reason"):
                print(f"            reason: {e['reason']}")
    print(
        f"{result.status}: {result.stop_reason}; {result.steps_used}/{result.step_budget} steps "
        f"({result.robot_actions} robot, {result.camera_actions} camera), "
        f"{result.invalid_outputs} invalid replies, checkpoints {result.checkpoints_reached}, "
        f"{result.model_calls} model calls, {result.tokens.input + result.tokens.cached_input} "
        f"input / {result.tokens.output} output tokens, "
        f"{cost_text(result.cost_usd, {} if pricing is None else {result.model: pricing}, '.4f')}, "
        f"{result.wall_s:.1f} s"
    )
    if result.error:
        print(f"error: {result.error}")


async def run(args: argparse.Namespace) -> EpisodeResult:
    from vabench.tasks import get_task

    task = get_task(args.task)
    server: LocalServer | None = None
    if args.config:
        endpoints = load_models(Path(args.config))
        names = [e.name for e in endpoints]
        if args.model not in names:
            raise ConfigError("--model", f"{args.model!r} is not in {args.config}; models: {names}")
    else:
        config = ServerConfig(policy=args.policy, seed=args.seed)
        server = await LocalServer(config).start()
        endpoints = load_endpoints([server.endpoint_config(args.model, "openai_chat")])
    # Without --out: the episode's place in a run directory "runs" whose track is the protocol.
    where = (args.model, args.protocol, args.task, args.seed, args.run)
    out = Path(args.out) if args.out else RunDir(Path("runs")).episode(*where).path
    spec = EpisodeSpec(
        args.task, args.seed, args.model, args.protocol, args.run, out, step_budget=args.max_steps
    )
    image = ImageSettings(args.width, args.height, args.quality)
    rp, choice = make_renderer(
        args.render, workers=1, platform=args.platform, max_size=(args.width, args.height)
    )
    try:
        with contextlib.closing(rp):
            print(f"renderer: {rp.start()} ({choice.reason})", file=sys.stderr)
            async with (
                LLMPool(endpoints) as llm,
                task_services(
                    task, 1, llm, rp, backend=args.physics.value, image=image
                ) as services,
            ):
                episode = Episode(spec, services)
                result = await episode.run()
    finally:
        if server is not None:
            await server.stop()
    if not args.json:  # --json: stdout is the result document alone (pipeable)
        endpoint = next(e for e in endpoints if e.name == args.model)
        print_trajectory(
            episode.rec.events, result, pricing_of(endpoint.prices, embedded=server is not None)
        )
    print(f"records: {out}", file=sys.stderr)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m vabench.episode",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--task", required=True)
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--model", default="local", help="endpoint name (default: local)")
    p.add_argument("--config", help="YAML with a models: list (default: embedded server)")
    p.add_argument(
        "--policy",
        default="random_action",
        choices=sorted(POLICIES),
        help="embedded server policy (without --config)",
    )
    p.add_argument("--protocol", choices=("active", "passive"), default="active")
    p.add_argument("--run", type=int, default=0)
    p.add_argument("--out")
    add_physics_arguments(p)
    p.add_argument(
        "--render",
        choices=("auto", "warp", "gl"),
        default="auto",
        help="renderer: warp (GPU ray tracer), gl, or auto (warp where it can run)",
    )
    p.add_argument("--platform", choices=("auto", "egl", "osmesa"), default="auto")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=960)
    p.add_argument("--quality", type=int, default=95)
    p.add_argument("--max-steps", type=int, help="cap the step budget (smoke runs)")
    p.add_argument("--json", action="store_true", help=f"print {RESULT} instead of the text")
    args = p.parse_args(argv)
    args.physics = physics_of(p, args)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        result = asyncio.run(run(args))
    except (ConfigError, KeyError, FileExistsError, BackendUnavailable) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except RequestRejected as err:  # the endpoint refuses every request (key, model, params)
        print(f"error: {err} ({err.hint})", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result.model_dump(), indent=1))
    return 0 if result.scored else 1


if __name__ == "__main__":
    sys.exit(main())
