"""How long the sweep takes to stop through a real LiteLLM proxy at its default settings.

The proxy (`--litellm`, default `litellm` on PATH) routes `served` to the embedded server,
run as a process of its own so that it can be killed, and `down` to a port where nothing
listens; its `general_settings.master_key` is the key. Each case runs the real sweep command
(`python -m vabench.sweep`, a new process, its import included), once with its endpoint check
and once `--no-check`, and reports the exit status, the seconds to exit and its stderr lines
that say why it stopped (`error:`, `stopped`; the rest of stderr is the sweep's log):

- wrong key, missing key (no `api_key_env`), unknown model name, upstream not running: each
  should exit 2 with the line naming the cause;
- upstream killed mid-sweep (`--no-check`, after the first episode is recorded): the episodes
  it stopped end as infrastructure errors (exit 1); the upstream started again, the same
  command runs them again (exit 0), each episode recorded once.

The proxy keeps LiteLLM's own retries (`num_retries` unset): what a user's proxy does.

    python benchmarks/gateway_litellm.py [--litellm PATH] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

KEY = "sk-vabench-bench"
KEY_ENV = "GATEWAY_TEST_KEY"
SWEEP = """\
name: gateway
models:
  - name: gw
    api: openai_chat
    base_url: {url}
    model: {model}
{key}tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: {seeds}}}
runs: 1
step_budget: 3
retries: {{infrastructure_rounds: 0}}
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{kind: local}}
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_url(url: str, timeout_s: float) -> float:
    started = time.monotonic()
    while time.monotonic() - started < timeout_s:
        try:
            with urllib.request.urlopen(url, timeout=5) as resp:
                if resp.status == 200:
                    return time.monotonic() - started
        except (urllib.error.URLError, OSError):
            time.sleep(0.5)
    raise RuntimeError(f"{url} not healthy after {timeout_s:g} s")


def upstream(port: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "vabench.llm_pool.serve", "--port", str(port)]
    proc = subprocess.Popen(cmd + ["--policy", "conversation_hash"], stdout=subprocess.PIPE)
    assert proc.stdout is not None and b"llm server on" in proc.stdout.readline()
    return proc


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def sweep_file(tmp: Path, url: str, model: str, key: bool, seeds: int = 2) -> Path:
    cfg = tmp / f"{model}_{key}_{seeds}.yaml"
    key_line = f"    api_key_env: {KEY_ENV}\n" if key else ""
    cfg.write_text(SWEEP.format(url=url, model=model, key=key_line, seeds=seeds))
    return cfg


def run_sweep(cfg: Path, out: Path, key: str | None, *flags: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != KEY_ENV}
    if key is not None:
        env[KEY_ENV] = key
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "vabench.sweep", str(cfg), "--out", str(out), "--plain"]
        + ["--no-report", *flags],
        capture_output=True,
        text=True,
        env=env,
    )
    results = out / "results.jsonl"
    records = [json.loads(x) for x in results.read_text().splitlines()] if results.exists() else []
    return {
        "exit": done.returncode,
        "seconds": round(time.monotonic() - started, 1),
        "stderr": [x for x in done.stderr.splitlines() if x.startswith(("error:", "stopped"))],
        "statuses": [r["status"] for r in records],
    }


def killed_mid_sweep(tmp: Path, url: str, port: int, proc: subprocess.Popen) -> dict:
    """Kill the upstream once an episode is recorded; then start it again and rerun."""
    cfg, out = sweep_file(tmp, url, "served", True, seeds=6), tmp / "killed"
    env = {**os.environ, KEY_ENV: KEY}
    cmd = [sys.executable, "-m", "vabench.sweep", str(cfg), "--out", str(out), "--plain"]
    started = time.monotonic()
    child = subprocess.Popen(
        cmd + ["--no-report", "--no-check"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    while not (out / "results.jsonl").exists() and child.poll() is None:
        time.sleep(0.2)
    stop(proc)
    killed = time.monotonic()
    err, _ = child.communicate()
    first = {
        "exit": child.returncode,
        "seconds_after_kill": round(time.monotonic() - killed, 1),
        "seconds": round(time.monotonic() - started, 1),
        "unscored": sum(x.startswith("unscored:") for x in err.splitlines()),
    }
    records = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    first["statuses"] = [r["status"] for r in records]
    proc = upstream(port)
    try:
        again = run_sweep(cfg, out, KEY, "--no-check")
    finally:
        stop(proc)
    infra = out / "infrastructure.jsonl"
    again["reopened"] = len(infra.read_text().splitlines()) if infra.exists() else 0
    return {"first": first, "rerun": again}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--litellm", default=shutil.which("litellm"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not args.litellm:
        sys.exit("no litellm executable: pip install 'litellm[proxy]' and pass --litellm PATH")
    tmp = Path(tempfile.mkdtemp(prefix="gateway_bench_"))
    up_port, proxy_port = free_port(), free_port()
    cfg = tmp / "litellm.yaml"
    cfg.write_text(
        "model_list:\n"
        f"  - {{model_name: served, litellm_params: {{model: openai/served, api_base: "
        f"'http://127.0.0.1:{up_port}/v1', api_key: upstream-key}}}}\n"
        f"  - {{model_name: down, litellm_params: {{model: openai/down, api_base: "
        f"'http://127.0.0.1:{free_port()}/v1', api_key: upstream-key}}}}\n"
        f"general_settings: {{master_key: {KEY}}}\n"
    )
    proc = upstream(up_port)
    log = (tmp / "litellm.log").open("w")
    started = time.monotonic()
    proxy = subprocess.Popen(
        [args.litellm, "--config", str(cfg), "--host", "127.0.0.1", "--port", str(proxy_port)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env={**os.environ, "LITELLM_LOCAL_MODEL_COST_MAP": "True"},
    )
    report: dict = {}
    try:
        wait_url(f"http://127.0.0.1:{proxy_port}/health/liveliness", 300)
        report["proxy_start_s"] = round(time.monotonic() - started, 1)
        print(f"litellm healthy after {report['proxy_start_s']} s", flush=True)
        url = f"http://127.0.0.1:{proxy_port}/v1"
        cases = {
            "wrong key": ("served", True, "sk-wrong"),
            "missing key": ("served", False, None),
            "unknown model": ("no-such-model", True, KEY),
            "upstream not running": ("down", True, KEY),
        }
        for name, (model, with_key, key) in cases.items():
            for flags in ((), ("--no-check",)):
                label = f"{name}{' --no-check' if flags else ''}"
                out = tmp / label.replace(" ", "_")
                result = run_sweep(sweep_file(tmp, url, model, with_key), out, key, *flags)
                report[label] = result
                print(f"{label}: exit {result['exit']} after {result['seconds']} s: "
                      f"{result['stderr'][:1]}", flush=True)  # fmt: skip
        report["upstream killed mid-sweep"] = killed_mid_sweep(tmp, url, up_port, proc)
        print(f"upstream killed mid-sweep: {report['upstream killed mid-sweep']}", flush=True)
    finally:
        stop(proxy)
        if proc.poll() is None:
            stop(proc)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
