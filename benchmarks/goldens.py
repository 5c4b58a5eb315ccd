"""Goldens for a refactor that must not change behaviour: capture, then compare.

    python benchmarks/goldens.py capture OUT_DIR [--repo DIR] [--python EXE] [--only PARTS]
        [--force]
    python benchmarks/goldens.py compare BEFORE_DIR AFTER_DIR [--max-lines 80] [--width 200]

`capture` runs the code of `--repo` (default: the checkout this script is in) with `--python`
(default: this interpreter) and writes three kinds of golden into OUT_DIR:

- `dryrun/<config>.txt`: the command, its exit status and its stdout+stderr (one stream, in
  the order written) of `python -m vabench.sweep configs/<config>.yaml --dry-run --out TMP`
  for every `configs/*.yaml`. `configs/models.example.yaml` is not a sweep config (a `models:`
  list for `vabench.episode`; the sweep refuses it: no `tracks`), so its file holds that
  refusal, and the README's way of using it, its models under the `models:` of a sweep config,
  is captured as `all+models.example` and `smoke+models.example` (those configs with the
  example's models in place of theirs): the estimate for real APIs and prices.
- `smoke/`: the records of the smoke sweep (`configs/smoke.yaml`, `--plain`, run from a temp
  directory, its caches in the temp directory, the demonstrations among them), normalised: `run/`
  holds every text file of the run directory (results.jsonl, plan.json, sweep.yaml, each episode's
  events.jsonl and result.json, the summaries, the report's md/csv/html), `demo_cache/` the
  demonstrations it built, `files.tsv` (in each) name, size and sha256 of every other file (JPEG
  frames, report PNGs, lock files; on this CPU path the images are byte-identical run to run), and
  `log.txt` its exit status and output without the progress and stage lines. The shipped smoke
  config's `random_action` policy is unseeded and draws in arrival order, so no two runs agree; the
  goldens run the config with `embedded_server.policy: conversation_hash` (the same random action,
  drawn from a hash of the conversation's text: the decisions follow the prompts, the observations
  and the physics, whatever the order of arrival), written to `smoke/config.yaml`.
- `wire/<api>/<case>.body.json`: the request body the LLM pool sends (pretty JSON) for each
  API (openai_chat, openai_responses, anthropic) and each kind of option, captured by a local
  HTTP server on loopback from a real `LLMPool.complete` (a system prompt, a user turn with
  a small JPEG, an assistant reply, a five-view turn); `<case>.request.json` beside it: method,
  path, headers, the body's size and sha256 (byte-exact) and what the pool made of a canned
  reply (text, usage, cost).

The environment is pinned so that the output does not depend on the machine or the shell:
VABENCH_CORES=2, CUDA_VISIBLE_DEVICES="" (no GPU: C MuJoCo and GL rendering), TZ=UTC,
C.UTF-8 locale, PYTHONHASHSEED=0, PYTHONUNBUFFERED=1 (stdout and stderr interleave in
write order), dummy API keys (OPENAI_API_KEY=sk-golden, ANTHROPIC_API_KEY=golden), no
inherited VABENCH_/JAX_/XLA_/MUJOCO_/PYOPENGL_/WARP_/RAY_ variables, and fresh caches in the
temp directory (settled states, JAX compilations, matplotlib, `XDG_CACHE_HOME`: the measured
pace): nothing a run before (the BEFORE capture included) computed is reused, so a cache cannot
hide a change.

What still varies from run to run, found by running the smoke sweep twice and diffing, is
replaced by a placeholder: the JSON keys `t` (event time), `started_at`, `wall_s`,
`latency_s` and `slot` (the batch slot of a reset event, taken in order of admission; numbers
only: a null stays null), the HH:MM:SS of log lines, loopback ports, and the temp and repo
paths (`<TMP>`, `<REPO>`). Nothing else is normalised: a new time field shows up in `compare`
and is a decision to make, not to hide. What the machine and the virtualenv are stays in the
goldens (Warp's "no CUDA driver" warning, the GL renderer's name, JPEG and PNG bytes, aiohttp's
User-Agent): compare captures made on the same machine with the same interpreter.

`compare` diffs two captures file by file (CAPTURE.txt, the capture's own notes: commit,
durations, is not compared), prints a unified diff of each text file that differs (at most
--max-lines lines, lines cut at --width characters), the files present on one side only,
and a summary line. Exit status 0 when identical, 1 otherwise.

`wire OUT_DIR` is the wire step alone; `capture` runs it in a subprocess with the repo's
`vabench` on PYTHONPATH.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import dataclasses
import difflib
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("dryrun", "smoke", "wire")
NOTES = "CAPTURE.txt"
"""The capture's notes (commit, durations): written by `capture`, skipped by `compare`."""

PINNED = {
    "VABENCH_CORES": "2",
    "CUDA_VISIBLE_DEVICES": "",
    "TZ": "UTC",
    "LC_ALL": "C.UTF-8",
    "LANG": "C.UTF-8",
    "PYTHONHASHSEED": "0",
    "PYTHONUNBUFFERED": "1",
    "TERM": "dumb",
    "COLUMNS": "100",
    "OPENAI_API_KEY": "sk-golden",
    "ANTHROPIC_API_KEY": "golden",
}
DROPPED_PREFIXES = ("VABENCH_", "JAX_", "XLA_", "MUJOCO_", "PYOPENGL_", "WARP_", "RAY_")
EXAMPLE_MODELS = "models.example"
DERIVED = ("all", "smoke")
"""Sweep configs also captured with the example's models in place of theirs."""
SMOKE_POLICY = "conversation_hash"

VARYING_KEYS = ("t", "started_at", "wall_s", "latency_s", "slot")
"""JSON keys whose numbers differ between two runs of the same code: times and durations, and
the batch slot an episode's reset took (episodes are admitted as the adaptive in-flight limit
grows, so which free slot one gets depends on timing; a slot's physics does not)."""
_VARYING = re.compile(r'(?<!\\)"(' + "|".join(VARYING_KEYS) + r')": -?\d[\d.eE+-]*')
_CLOCK = re.compile(r"^\d\d:\d\d:\d\d ", re.MULTILINE)
_PORT = re.compile(r"(127\.0\.0\.1|localhost):\d+")
_PROGRESS = re.compile(r": episodes \d+/\d+ \(|: physics \d+ calls, \d+ items")
"""Lines that depend on timing: the progress display, and each task's stage line (its calls
and seconds follow how requests happened to batch)."""
TEXT_SUFFIXES = (".json", ".jsonl", ".yaml", ".yml", ".md", ".csv", ".html", ".txt")


# -- normalising --------------------------------------------------------------------------


class Normaliser:
    """Replaces what varies between runs of the same code: paths, clocks, ports, times."""

    def __init__(self, tmp: Path, repo: Path):
        paths = {str(tmp): "<TMP>", str(tmp.resolve()): "<TMP>"}
        paths.update({str(repo): "<REPO>", str(repo.resolve()): "<REPO>"})
        self.paths = sorted(paths.items(), key=lambda kv: -len(kv[0]))  # longest first

    def text(self, text: str) -> str:
        for path, placeholder in self.paths:
            text = text.replace(path, placeholder)
        text = _CLOCK.sub("HH:MM:SS ", text)
        return _PORT.sub(r"\1:PORT", text)

    def record(self, text: str) -> str:
        """A JSON or JSON Lines file: the numbers of VARYING_KEYS too (byte for byte
        otherwise: key order, spacing and float digits are kept)."""
        return _VARYING.sub(lambda m: f'"{m.group(1)}": "<varies>"', self.text(text))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def copy_tree(src: Path, dst: Path, norm: Normaliser) -> tuple[int, int]:
    """Text files of `src` normalised into `dst`; every other file listed in dst/files.tsv
    (path, size, sha256). Returns (text files, listed files)."""
    rows, n_text = [], 0
    for path in sorted(p for p in src.rglob("*") if p.is_file()):
        rel = path.relative_to(src)
        if path.suffix in TEXT_SUFFIXES:
            text = path.read_text(encoding="utf-8")
            json_like = path.suffix in (".json", ".jsonl")
            out = dst / rel
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(norm.record(text) if json_like else norm.text(text), encoding="utf-8")
            n_text += 1
        else:
            rows.append(f"{rel}\t{path.stat().st_size}\t{sha256(path)}")
    dst.mkdir(parents=True, exist_ok=True)
    (dst / "files.tsv").write_text("path\tbytes\tsha256\n" + "".join(r + "\n" for r in rows))
    return n_text, len(rows)


# -- running ------------------------------------------------------------------------------


def pinned_environment(repo: Path, tmp: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(DROPPED_PREFIXES)}
    env.update(PINNED)
    env.update(
        {
            "PYTHONPATH": str(repo),
            "VABENCH_STATE_CACHE": str(tmp / "cache" / "settled"),
            "VABENCH_JAX_CACHE": str(tmp / "cache" / "jax"),
            "MPLCONFIGDIR": str(tmp / "cache" / "matplotlib"),
            # the pace a machine measured (~/.cache/vabench/pace.json) changes the dry-run's
            # estimate: every cache of vabench's starts empty
            "XDG_CACHE_HOME": str(tmp / "cache" / "xdg"),
        }
    )
    return env


def run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float) -> tuple[int, str]:
    """Exit status and stdout+stderr (one stream) of a command."""
    done = subprocess.run(
        cmd,
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        timeout=timeout,
    )
    return done.returncode, done.stdout.decode("utf-8", "replace")


def shown(cmd: list[str], python: str) -> str:
    return "$ " + " ".join("python" if c == python else c for c in cmd)


def sweep_configs(repo: Path) -> list[Path]:
    return sorted((repo / "configs").glob("*.yaml"))


def derived_configs(repo: Path, folder: Path) -> list[Path]:
    """The sweep configs of DERIVED with the models of configs/models.example.yaml (the README:
    "put entries like those of configs/models.example.yaml under `models:`")."""
    import yaml

    example = repo / "configs" / f"{EXAMPLE_MODELS}.yaml"
    if not example.exists():
        return []
    models = yaml.safe_load(example.read_text())["models"]
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name in DERIVED:
        source = repo / "configs" / f"{name}.yaml"
        if not source.exists():
            continue
        doc = yaml.safe_load(source.read_text())
        doc["models"] = models
        doc.pop("embedded_server", None)  # no embedded model left to serve
        path = folder / f"{name}+{EXAMPLE_MODELS}.yaml"
        path.write_text(yaml.safe_dump(doc, sort_keys=False))
        out.append(path)
    return out


def capture_dryruns(
    repo: Path, out: Path, tmp: Path, python: str, env: dict[str, str], norm: Normaliser
) -> list[str]:
    notes = []
    configs = [c.relative_to(repo) for c in sweep_configs(repo)]
    configs += derived_configs(repo, tmp / "derived")
    (out / "dryrun").mkdir(parents=True)
    for config in configs:
        name = config.name.removesuffix(".yaml")
        cmd = [python, "-m", "vabench.sweep", str(config), "--dry-run"]
        cmd += ["--out", str(tmp / "dryrun" / name)]
        t0 = time.perf_counter()
        code, output = run(cmd, repo, env, timeout=600)
        wall = time.perf_counter() - t0
        text = f"{shown(cmd, python)}\nexit status: {code}\n\n{output}"
        (out / "dryrun" / f"{name}.txt").write_text(norm.text(text))
        notes.append(f"dryrun {name}: exit {code}, {wall:.1f} s")
        print(notes[-1], flush=True)
    return notes


def capture_smoke(
    repo: Path, out: Path, tmp: Path, python: str, env: dict[str, str], norm: Normaliser
) -> list[str]:
    import yaml

    work = tmp / "smoke"
    (work / "configs").mkdir(parents=True)
    doc = yaml.safe_load((repo / "configs" / "smoke.yaml").read_text())
    doc.setdefault("embedded_server", {})["policy"] = SMOKE_POLICY
    config = yaml.safe_dump(doc, sort_keys=False)
    (work / "configs" / "smoke.yaml").write_text(config)
    run_dir = work / "run"
    cmd = [python, "-m", "vabench.sweep", "configs/smoke.yaml", "--out", str(run_dir), "--plain"]
    t0 = time.perf_counter()
    code, output = run(cmd, work, env, timeout=1800)
    wall = time.perf_counter() - t0
    dst = out / "smoke"
    dst.mkdir(parents=True)
    (dst / "config.yaml").write_text(config)
    kept = [line for line in output.splitlines() if not _PROGRESS.search(line)]
    log = f"{shown(cmd, python)}\nexit status: {code}\n\n" + "".join(x + "\n" for x in kept)
    (dst / "log.txt").write_text(norm.text(log))
    if not run_dir.is_dir():
        raise SystemExit(f"the smoke sweep wrote no run directory (exit {code}):\n{output[-3000:]}")
    texts, listed = copy_tree(run_dir, dst / "run", norm)
    demos = Path(env["XDG_CACHE_HOME"]) / "vabench" / "demos"
    demos = demos if demos.is_dir() else work / ".cache" / "demos"  # a commit before
    if demos.is_dir():
        copy_tree(demos, dst / "demo_cache", norm)
    note = f"smoke: exit {code}, {wall:.1f} s, {texts} text files, {listed} other files listed"
    print(note, flush=True)
    return [note]


def capture(args: argparse.Namespace) -> int:
    repo = Path(args.repo).resolve()
    out = Path(args.out_dir)
    parts = args.only.split(",") if args.only else list(PARTS)
    if unknown := sorted(set(parts) - set(PARTS)):
        raise SystemExit(f"--only: unknown part(s) {unknown}; parts are {', '.join(PARTS)}")
    if out.exists() and any(out.iterdir()):
        if not args.force:
            raise SystemExit(f"{out} exists and is not empty (--force replaces it)")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(
        ["git", "-C", str(repo), "describe", "--always", "--dirty"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    notes = [f"repo: {repo} at {commit}", f"python: {args.python}", f"parts: {', '.join(parts)}"]
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="vabench-goldens-") as name:
        tmp = Path(name)
        env = pinned_environment(repo, tmp)
        norm = Normaliser(tmp, repo)
        where = run([args.python, "-c", "import vabench; print(vabench.__file__)"], repo, env, 120)
        if where[0] != 0 or not Path(where[1].strip()).resolve().is_relative_to(repo):
            raise SystemExit(f"vabench does not import from {repo}: {where[1].strip()}")
        notes.append(f"vabench: {where[1].strip()}")
        if "dryrun" in parts:
            notes += capture_dryruns(repo, out, tmp, args.python, env, norm)
        if "smoke" in parts:
            notes += capture_smoke(repo, out, tmp, args.python, env, norm)
        if "wire" in parts:
            t0 = time.perf_counter()
            cmd = [args.python, str(Path(__file__).resolve()), "wire", str(out / "wire")]
            code, output = run(cmd, repo, env, timeout=300)
            if code != 0:
                raise SystemExit(f"wire capture failed ({code}):\n{output[-3000:]}")
            notes.append(f"wire: {output.strip()}, {time.perf_counter() - t0:.1f} s")
            print(notes[-1], flush=True)
    notes.append(f"capture: {time.perf_counter() - t_all:.1f} s")
    notes.append(f"captured at: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}")
    (out / NOTES).write_text("".join(n + "\n" for n in notes))
    print(notes[-2])
    return 0


# -- wire bodies --------------------------------------------------------------------------

TINY_JPEG = (
    "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDAAgGBgcGBQgHBwcJCQgKDBQNDAsLDBkSEw8UHRofHh0aHBwgJC4nICIsIxwc"
    "KDcpLDAxNDQ0Hyc5PTgyPC4zNDL/2wBDAQkJCQwLDBgNDRgyIRwhMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIyMjIy"
    "MjIyMjIyMjIyMjIyMjIyMjL/wAARCAAMABADASIAAhEBAxEB/8QAHwAAAQUBAQEBAQEAAAAAAAAAAAECAwQFBgcICQoL"
    "/8QAtRAAAgEDAwIEAwUFBAQAAAF9AQIDAAQRBRIhMUEGE1FhByJxFDKBkaEII0KxwRVS0fAkM2JyggkKFhcYGRolJico"
    "KSo0NTY3ODk6Q0RFRkdISUpTVFVWV1hZWmNkZWZnaGlqc3R1dnd4eXqDhIWGh4iJipKTlJWWl5iZmqKjpKWmp6ipqrKz"
    "tLW2t7i5usLDxMXGx8jJytLT1NXW19jZ2uHi4+Tl5ufo6erx8vP09fb3+Pn6/8QAHwEAAwEBAQEBAQEBAQAAAAAAAAEC"
    "AwQFBgcICQoL/8QAtREAAgECBAQDBAcFBAQAAQJ3AAECAxEEBSExBhJBUQdhcRMiMoEIFEKRobHBCSMzUvAVYnLRChYk"
    "NOEl8RcYGRomJygpKjU2Nzg5OkNERUZHSElKU1RVVldYWVpjZGVmZ2hpanN0dXZ3eHl6goOEhYaHiImKkpOUlZaXmJma"
    "oqOkpaanqKmqsrO0tba3uLm6wsPExcbHyMnK0tPU1dbX2Nna4uPk5ebn6Onq8vP09fb3+Pn6/9oADAMBAAIRAxEAPwDh"
    "7Dw30+T9K6ew8N9Pk/SupsbGDj5K6axsYOPkpYvNZmPD+d1ND//Z"
)
"""A 16x12 baseline JPEG (663 bytes), fixed here so the bodies do not depend on an encoder."""

WIRE_CASES: list[tuple[str, str, dict[str, Any], dict[str, Any] | None]] = [
    # (api, case, endpoint fields beyond the common ones, per-request option overrides)
    ("openai_chat", "default", {}, None),
    (
        "openai_chat",
        "options",
        {"generation": {"max_output_tokens": 512, "temperature": 0.3, "reasoning_effort": "low"}},
        None,
    ),
    ("openai_chat", "max_tokens_field", {"max_tokens_field": "max_tokens"}, None),
    ("openai_chat", "headers", {"headers": {"X-Golden": "1"}}, None),
    (
        "openai_chat",
        "request_options",
        {"generation": {"temperature": 0.3, "max_output_tokens": 512}},
        {"max_output_tokens": 64, "temperature": 0.0},
    ),
    ("openai_responses", "default", {}, None),
    (
        "openai_responses",
        "options",
        {"generation": {"max_output_tokens": 512, "temperature": 0.3, "reasoning_effort": "high"}},
        None,
    ),
    ("anthropic", "default", {}, None),
    (
        "anthropic",
        "thinking",
        {"generation": {"max_output_tokens": 4096, "thinking_budget": 1024}},
        None,
    ),
    ("anthropic", "no_cache", {"generation": {"cache_prompt": False}}, None),
]
WIRE_USAGE = {"input": 1200, "cached": 1024, "output": 20, "reasoning": 8}
WIRE_TEXT = '```json\n{"action": "gripper.open", "reason": "golden"}\n```'
WIRE_PRICES = {"input": 1.25, "cached_input": 0.125, "output": 10.0}


def canned_reply(api: str) -> dict[str, Any]:
    """A fixed valid response body of `api` (as the provider documents it)."""
    u = WIRE_USAGE
    if api == "openai_chat":
        return {
            "id": "chatcmpl-golden",
            "object": "chat.completion",
            "created": 1700000000,
            "model": "golden-model",
            "choices": [
                {
                    "index": 0,
                    "message": {"role": "assistant", "content": WIRE_TEXT, "refusal": None},
                    "logprobs": None,
                    "finish_reason": "stop",
                }
            ],
            "usage": {
                "prompt_tokens": u["input"],
                "completion_tokens": u["output"],
                "total_tokens": u["input"] + u["output"],
                "prompt_tokens_details": {"cached_tokens": u["cached"]},
                "completion_tokens_details": {"reasoning_tokens": u["reasoning"]},
            },
        }
    if api == "openai_responses":
        return {
            "id": "resp_golden",
            "object": "response",
            "created_at": 1700000000,
            "status": "completed",
            "error": None,
            "incomplete_details": None,
            "model": "golden-model",
            "output": [
                {"type": "reasoning", "id": "rs_golden", "summary": []},
                {
                    "type": "message",
                    "id": "msg_golden",
                    "status": "completed",
                    "role": "assistant",
                    "content": [{"type": "output_text", "text": WIRE_TEXT, "annotations": []}],
                },
            ],
            "usage": {
                "input_tokens": u["input"],
                "input_tokens_details": {"cached_tokens": u["cached"]},
                "output_tokens": u["output"],
                "output_tokens_details": {"reasoning_tokens": u["reasoning"]},
                "total_tokens": u["input"] + u["output"],
            },
        }
    return {
        "id": "msg_golden",
        "type": "message",
        "role": "assistant",
        "model": "golden-model",
        "content": [{"type": "text", "text": WIRE_TEXT}],
        "stop_reason": "end_turn",
        "stop_sequence": None,
        "usage": {
            "input_tokens": u["input"] - u["cached"],
            "cache_creation_input_tokens": 0,
            "cache_read_input_tokens": u["cached"],
            "output_tokens": u["output"],
        },
    }


def wire_conversation(options: dict[str, Any] | None) -> Any:
    """What the engine sends: a system prompt, an observation with an image, the model's
    reply, then a five-view turn whose images are each labelled by the text before them."""
    from vabench.llm_pool import ChatRequest, Image, Turn

    image = Image(base64.b64decode(TINY_JPEG))
    views = ("topdown", "side", "front_side_45", "side_top_45", "oblique_45")
    five = [part for v in views for part in (f"View {v}:", image)]
    return ChatRequest(
        (
            Turn.user("Step 1/5. The head camera sees:", image, "Reply with one JSON action."),
            Turn.assistant('```json\n{"action": "camera.view_topdown", "reason": "look"}\n```'),
            Turn.user("Step 2/5. Five views of the scene.", *five),
        ),
        "You control a dual-arm robot through metric commands. Answer in JSON.",
        options,
    )


def plain(value: Any) -> Any:
    """A result as JSON-able data (dataclasses, tuples), without the timings."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
        return {k: plain(v) for k, v in fields.items() if k not in ("latency_s", "elapsed_s")}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    return value


async def capture_wire(out: Path) -> int:
    from aiohttp import web

    from vabench.llm_pool import LLMPool

    seen: list[tuple[str, str, dict[str, str], bytes]] = []
    routes = {
        "/v1/chat/completions": "openai_chat",
        "/v1/responses": "openai_responses",
        "/v1/messages": "anthropic",
    }

    async def handle(request: web.Request) -> web.Response:
        body = await request.read()
        seen.append((request.method, request.path_qs, dict(request.headers), body))
        return web.json_response(canned_reply(routes[request.path]))

    app = web.Application(client_max_size=64 * 1024 * 1024)
    for route in routes:
        app.router.add_post(route, handle)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = runner.addresses[0][1]
    endpoints = []
    for api, case, fields, _ in WIRE_CASES:
        base = f"http://127.0.0.1:{port}" + ("" if api == "anthropic" else "/v1")
        endpoints.append(
            {
                "name": f"{api}.{case}",
                "api": api,
                "model": "golden-model",
                "base_url": base,
                "api_key_env": "GOLDEN_KEY",
                "prices": WIRE_PRICES,
                "retry": {"max_attempts": 1},
                **fields,
            }
        )
    try:
        async with LLMPool(endpoints, environ={"GOLDEN_KEY": "sk-golden-key"}) as pool:
            for (api, case, _, options), endpoint in zip(WIRE_CASES, endpoints, strict=True):
                before = len(seen)
                result = await pool.complete(endpoint["name"], wire_conversation(options))
                if len(seen) != before + 1:
                    raise SystemExit(f"{api}/{case}: {len(seen) - before} requests, expected 1")
                method, path, headers, body = seen[-1]
                folder = out / api
                folder.mkdir(parents=True, exist_ok=True)
                pretty = json.dumps(json.loads(body), indent=2, ensure_ascii=False) + "\n"
                (folder / f"{case}.body.json").write_text(pretty)
                request = {
                    "method": method,
                    "path": path,
                    "headers": {k: _PORT.sub(r"\1:PORT", v) for k, v in sorted(headers.items())},
                    "body_bytes": len(body),
                    "body_sha256": hashlib.sha256(body).hexdigest(),
                    "result": plain(result),
                }
                (folder / f"{case}.request.json").write_text(
                    json.dumps(request, indent=2, ensure_ascii=False) + "\n"
                )
    finally:
        await runner.cleanup()
    print(f"{len(WIRE_CASES)} requests over {len({c[0] for c in WIRE_CASES})} APIs")
    return 0


# -- comparing ----------------------------------------------------------------------------


def files_of(root: Path) -> set[str]:
    return {
        str(p.relative_to(root))
        for p in root.rglob("*")
        if p.is_file() and str(p.relative_to(root)) != NOTES
    }


def text_of(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return None


def compare(args: argparse.Namespace) -> int:
    before, after = Path(args.before), Path(args.after)
    for d in (before, after):
        if not d.is_dir():
            raise SystemExit(f"{d}: not a directory")
    a, b = files_of(before), files_of(after)
    only_before, only_after = sorted(a - b), sorted(b - a)
    differ = []
    for rel in sorted(a & b):
        x, y = before / rel, after / rel
        if x.read_bytes() == y.read_bytes():
            continue
        differ.append(rel)
        tx, ty = text_of(x), text_of(y)
        if tx is None or ty is None:
            print(f"--- {rel}: binary files differ\n")
            continue
        lines = list(
            difflib.unified_diff(
                tx.splitlines(), ty.splitlines(), f"before/{rel}", f"after/{rel}", lineterm=""
            )
        )
        for line in lines[: args.max_lines]:
            print(line if len(line) <= args.width else line[: args.width] + " [...]")
        if len(lines) > args.max_lines:
            print(f"[... {len(lines) - args.max_lines} more diff lines of {rel}]")
        print()
    for rel in only_before:
        print(f"only in {before}: {rel}")
    for rel in only_after:
        print(f"only in {after}: {rel}")
    same = len(a & b) - len(differ)
    verdict = "IDENTICAL" if not (differ or only_before or only_after) else "DIFFERENT"
    print(
        f"{verdict}: {len(a | b)} files, {same} identical, {len(differ)} differ, "
        f"{len(only_before)} only before, {len(only_after)} only after"
    )
    return 0 if verdict == "IDENTICAL" else 1


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("capture", help="write the goldens of --repo into OUT_DIR")
    c.add_argument("out_dir")
    c.add_argument("--repo", default=str(ROOT), help="checkout whose code runs (default: this)")
    c.add_argument("--python", default=sys.executable, help="interpreter (default: this one)")
    c.add_argument("--only", help=f"comma-separated parts of {', '.join(PARTS)} (default: all)")
    c.add_argument("--force", action="store_true", help="replace a non-empty OUT_DIR")
    d = sub.add_parser("compare", help="diff two captures; exit 1 when they differ")
    d.add_argument("before")
    d.add_argument("after")
    d.add_argument("--max-lines", type=int, default=80, help="diff lines shown per file")
    d.add_argument("--width", type=int, default=200, help="characters shown per diff line")
    w = sub.add_parser("wire", help="the wire bodies alone (run by capture)")
    w.add_argument("out_dir")
    args = p.parse_args()
    if args.command == "capture":
        sys.exit(capture(args))
    if args.command == "compare":
        sys.exit(compare(args))
    sys.exit(asyncio.run(capture_wire(Path(args.out_dir))))


if __name__ == "__main__":
    main()
