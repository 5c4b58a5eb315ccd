"""`python -m vabench.llm_pool.serve --port P`: the embedded server as a process.

    python -m vabench.llm_pool.serve --port 8123 --policy random_action --latency 2 \
        --fault rate_limit=0.05 --fault drop=0.01 --rpm 600 --log requests.jsonl

To answer as a local inference server with its limits (the tests of `vabench.check`):

    python -m vabench.llm_pool.serve --port 8123 --served-model-name qwen-vl \
        --max-model-len 32768 --limit-images 1      # vLLM's --limit-mm-per-prompt image=1
    python -m vabench.llm_pool.serve --port 8123 --num-ctx 2048   # Ollama's default context
    python -m vabench.llm_pool.serve --port 8123 --ignore-field max_completion_tokens

A full configuration can also come from a YAML or JSON file (`--config`, the fields of
`ServerConfig`); flags override it. An API key to require is read from the environment
variable named by `--api-key-env`, never from the command line.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from vabench.llm_pool.faults import FAULT_KINDS
from vabench.llm_pool.policies import POLICIES
from vabench.llm_pool.server import LocalServer, ServerConfig


def _fault(text: str) -> tuple[str, float]:
    kind, sep, rate = text.partition("=")
    if not sep or kind not in FAULT_KINDS:
        raise argparse.ArgumentTypeError(f"expected KIND=RATE with KIND in {list(FAULT_KINDS)}")
    return kind, float(rate)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m vabench.llm_pool.serve",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8123, help="0 picks a free port")
    p.add_argument("--config", type=Path, help="ServerConfig as YAML or JSON")
    p.add_argument("--policy", choices=sorted(POLICIES))
    p.add_argument("--policy-options", type=json.loads, help='JSON object, e.g. {"seed": 1}')
    p.add_argument("--script", type=Path, help="JSON list of replies: the scripted policy")
    p.add_argument("--latency", type=float, help="mean seconds per reply")
    p.add_argument("--latency-dist", choices=["fixed", "uniform", "exponential", "lognormal"])
    p.add_argument("--latency-spread", type=float)
    p.add_argument("--fault", type=_fault, action="append", default=[], metavar="KIND=RATE")
    p.add_argument("--retry-after", type=float, help="seconds announced with injected 429s")
    p.add_argument("--slow", type=float, help="seconds a 'slow' fault takes")
    p.add_argument("--rpm", type=float)
    p.add_argument("--tpm", type=float)
    p.add_argument("--rate-period", type=float, help="seconds per rate window (default 60)")
    p.add_argument("--api-key-env", help="require the key held by this environment variable")
    p.add_argument("--log", help="append a JSON line per request to this file")
    p.add_argument("--seed", type=int)
    traits = p.add_argument_group("a local inference server's limits (ServerTraits)")
    traits.add_argument("--served-model-name", help="vLLM's: the one model served")
    traits.add_argument("--max-model-len", type=int, help="vLLM's context length")
    traits.add_argument("--limit-images", type=int, help="vLLM's --limit-mm-per-prompt image count")
    traits.add_argument("--num-ctx", type=int, help="Ollama's context: longer prompts are cut")
    traits.add_argument(
        "--ignore-field",
        action="append",
        default=[],
        choices=["max_completion_tokens", "max_tokens"],
        help="an output-limit field the server does not read (llama.cpp's server)",
    )
    traits.add_argument(
        "--reasoning-model",
        action="store_true",
        default=None,
        help="refuse max_tokens and a temperature other than 1, as OpenAI's reasoning models",
    )
    traits.add_argument(
        "--no-reasoning",
        action="store_true",
        default=None,
        help="refuse reasoning_effort, as OpenAI's models that do not reason",
    )
    p.add_argument(
        "--policy-processes",
        type=int,
        help="worker processes computing the replies of a stateless policy (reference_servo, "
        "conversation_hash); default 0: in this process",
    )
    p.add_argument(
        "--server-processes",
        type=int,
        help="processes serving the routes on one port (each with its policy in threads); "
        "default 0: this process serves",
    )
    return p


def config_from_args(args: argparse.Namespace) -> ServerConfig:
    data: dict[str, Any] = {}
    if args.config:
        data = yaml.safe_load(args.config.read_text()) or {}
    latency = dict(data.get("latency", {}))
    faults = dict(data.get("faults", {}))
    rates = dict(faults.get("rates", {}))
    for key, value in (
        ("mean_s", args.latency),
        ("dist", args.latency_dist),
        ("spread", args.latency_spread),
    ):
        if value is not None:
            latency[key] = value
    rates.update(dict(args.fault))
    for key, value in (("retry_after_s", args.retry_after), ("slow_s", args.slow)):
        if value is not None:
            faults[key] = value
    data.update(latency=latency, faults={**faults, "rates": rates})
    imitate = dict(data.get("imitate", {}))
    for key, value in (
        ("served_model_name", args.served_model_name),
        ("max_model_len", args.max_model_len),
        ("max_images_per_prompt", args.limit_images),
        ("num_ctx", args.num_ctx),
        ("ignored_fields", args.ignore_field or None),
        ("reasoning_model", args.reasoning_model),
        ("no_reasoning", args.no_reasoning),
    ):
        if value is not None:
            imitate[key] = value
    if imitate:
        data["imitate"] = imitate
    if args.script:
        data.update(
            policy="scripted", policy_options={"replies": json.loads(args.script.read_text())}
        )
    for key, value in (
        ("policy", args.policy),
        ("policy_options", args.policy_options),
        ("rpm", args.rpm),
        ("tpm", args.tpm),
        ("rate_period_s", args.rate_period),
        ("log_path", args.log),
        ("seed", args.seed),
        ("policy_processes", args.policy_processes),
        ("server_processes", args.server_processes),
    ):
        if value is not None:
            data[key] = value
    if args.api_key_env:
        api_key = os.environ.get(args.api_key_env)
        if not api_key:
            raise SystemExit(f"--api-key-env: environment variable {args.api_key_env} is not set")
        data["api_key"] = api_key
    return ServerConfig.model_validate(data)


class CannotListen(Exception):
    """The server's address is taken or not this machine's (one line, no traceback)."""


async def serve(config: ServerConfig, host: str, port: int) -> None:
    server = LocalServer(config)
    try:
        await server.start(host, port)
    except OSError as err:
        await server.stop()
        raise CannotListen(
            f"error: cannot listen on {host}:{port}: {err.strerror or err} (another process "
            "may hold the port: --port 0 picks a free one)"
        ) from err
    served = f", {server.processes} processes" if server.processes else ""
    print(
        f"vabench llm server on {server.url} (policy {config.policy}{served}); Ctrl-C stops",
        flush=True,
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await server.stop()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = config_from_args(args)
    except (ValidationError, ValueError, KeyError) as err:
        print(f"invalid server configuration: {err}", file=sys.stderr)
        return 2
    try:
        asyncio.run(serve(config, args.host, args.port))
    except CannotListen as err:
        print(err, file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
