"""The sweep through a real LiteLLM proxy, a process of its own in front of the embedded server,
as a user runs one: a wrong key, a missing key, a model name the proxy does not route and an
upstream that is not running each stop the sweep with one line naming the cause, nothing
recorded (through the sweep's endpoint check and, `--no-check`, through the pool itself); the
proxy's own rate limit loses no episode; episodes whose upstream kept failing end as
infrastructure errors, and the same command runs them again once it is healthy.

One proxy serves the module: its config routes one model name per case (`served`, `down`,
`flaky`, `limited`). The proxy is `$VABENCH_TEST_LITELLM` or `litellm` on PATH (`pip install
'litellm[proxy]'`, in a virtual environment of its own: .ci/run makes `.gateway-venv`); the
module is skipped without one. Stop times are printed (`-s`), not asserted;
benchmarks/gateway_litellm.py measures them.
"""

from __future__ import annotations

import json
import logging
import os
import random
import shutil
import socket
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from vabench.llm_pool.faults import FaultConfig, FaultPlan
from vabench.llm_pool.server import ServerConfig
from vabench.llm_pool.testing import server_in_thread
from vabench.run_layout import INFRASTRUCTURE, RESULTS
from vabench.sweep.__main__ import main

MASTER_KEY = "sk-vabench-gateway-test"
KEY_ENV = "GATEWAY_TEST_KEY"
LIMITED_RPM = 8
"""The `limited` deployment's rpm. LiteLLM's usage-based routing counts a calendar minute and
refuses the call that would reach the limit, so `LIMITED_RPM - 1` calls pass a minute."""
START_TIMEOUT_S = 240.0  # its import alone takes 20-40 s on a loaded 2-core machine


def litellm_executable() -> str | None:
    return os.environ.get("VABENCH_TEST_LITELLM") or shutil.which("litellm")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def proxy_config(served: str, flaky: str, down: str) -> str:
    """The proxy's config: each model name a case, `openai/...` at the embedded servers."""

    def deployment(name: str, base: str, extra: str = "") -> str:
        return (
            f"  - model_name: {name}\n"
            f"    litellm_params:\n"
            f"      model: openai/{name}\n"
            f"      api_base: {base}\n"
            f"      api_key: upstream-key\n{extra}"
        )

    return (
        "model_list:\n"
        + deployment("served", served)
        + deployment("down", down)
        + deployment("flaky", flaky)
        + deployment("limited", served, f"      rpm: {LIMITED_RPM}\n")
        + f"general_settings:\n  master_key: {MASTER_KEY}\n"
        # The rpm is enforced by usage-based routing; without retries the proxy answers 429
        # at once instead of holding the call until the next minute.
        + "router_settings:\n  routing_strategy: usage-based-routing-v2\n  num_retries: 0\n"
    )


@dataclass
class Gateway:
    base_url: str
    log: Path
    flaky: object  # the flaky upstream's LocalServer (its `faults` are swapped)

    def post(self, model: str, key: str | None = MASTER_KEY) -> int:
        """One chat call straight to the proxy; its HTTP status."""
        body = {"model": model, "messages": [{"role": "user", "content": "hi"}]}
        headers = {"Content-Type": "application/json"}
        if key:
            headers["Authorization"] = f"Bearer {key}"
        request = urllib.request.Request(
            f"{self.base_url}/chat/completions", json.dumps(body).encode(), headers
        )
        try:
            with urllib.request.urlopen(request, timeout=60) as resp:
                return resp.status
        except urllib.error.HTTPError as err:
            return err.code


def wait_healthy(url: str, proc: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"litellm exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"{url}/health/liveliness", timeout=5) as resp:
                if resp.status == 200:
                    return
        except (urllib.error.URLError, OSError):
            pass
        time.sleep(0.5)
    pytest.fail(f"litellm not healthy after {START_TIMEOUT_S:g} s:\n{log.read_text()[-3000:]}")


@pytest.fixture(scope="module")
def gateway(tmp_path_factory) -> Iterator[Gateway]:
    exe = litellm_executable()
    if exe is None:
        why = (
            "no LiteLLM proxy: set VABENCH_TEST_LITELLM to a `litellm` executable (pip install "
            "'litellm[proxy]' in a venv of its own) or put one on PATH"
        )
        if os.environ.get("CI") == "true":  # .ci/run installs one: its absence is a failure
            pytest.fail(why)
        pytest.skip(why)
    tmp = tmp_path_factory.mktemp("gateway")
    healthy = ServerConfig(policy="conversation_hash")
    failing = ServerConfig(policy="conversation_hash", faults={"rates": {"server_error": 1.0}})
    with server_in_thread(healthy) as served, server_in_thread(failing) as flaky:
        cfg = tmp / "litellm.yaml"
        down = f"http://127.0.0.1:{free_port()}/v1"  # nothing listens there
        cfg.write_text(
            proxy_config(served.base_url("openai_chat"), flaky.base_url("openai_chat"), down)
        )
        port = free_port()
        log = tmp / "litellm.log"
        env = {**os.environ, "LITELLM_LOCAL_MODEL_COST_MAP": "True"}  # no fetch at start
        with log.open("w") as out:
            proc = subprocess.Popen(
                [exe, "--config", str(cfg), "--host", "127.0.0.1", "--port", str(port)],
                stdout=out,
                stderr=subprocess.STDOUT,
                env=env,
            )
        try:
            base = f"http://127.0.0.1:{port}"
            started = time.monotonic()
            wait_healthy(base, proc, log)
            print(f"\nlitellm healthy after {time.monotonic() - started:.1f} s")
            yield Gateway(f"{base}/v1", log, flaky)
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


SWEEP = """\
name: gateway
models:
  - name: gw
    api: openai_chat
    base_url: {url}
    model: {model}
{key}    retry: {{max_attempts: 2, backoff_base_s: 0.01, backoff_max_s: 0.02}}
tracks: [active]
tasks: [grasp_single_cube]
seeds: {{verified: 2}}
runs: 1
step_budget: 2
retries: {{infrastructure_rounds: 0}}
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {{kind: local}}
"""


def sweep_config(tmp_path: Path, gateway: Gateway, model: str, key: bool = True) -> Path:
    cfg = tmp_path / f"{model}.yaml"
    key_line = f"    api_key_env: {KEY_ENV}\n" if key else ""
    cfg.write_text(SWEEP.format(url=gateway.base_url, model=model, key=key_line))
    return cfg


def lines(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def sweep(cfg: Path, out: Path, *flags: str) -> tuple[int, float]:
    started = time.monotonic()
    code = main([str(cfg), "--out", str(out), "--plain", "--no-report", *flags])
    return code, time.monotonic() - started


# The fatal cases: (model name, key sent, what the one stderr line must hold).
CASES = {
    "wrong key": ("served", "sk-wrong", ["No connected db.", KEY_ENV]),
    "missing key": ("served", None, ["no API key", "api_key_env"]),
    "unknown model": ("no-such-model", MASTER_KEY, ["Invalid model name", "'no-such-model'"]),
    "upstream down": ("down", MASTER_KEY, ["Connection error", "cannot reach the server"]),
}


def stop_on(case, tmp_path, gateway, monkeypatch, capsys) -> tuple[list[str], Path]:
    """Run the sweep of a fatal case: exit 2, nothing recorded; its stderr lines."""
    model, key, _ = CASES[case]
    if key:
        monkeypatch.setenv(KEY_ENV, key)
    else:
        monkeypatch.delenv(KEY_ENV, raising=False)
    cfg = sweep_config(tmp_path, gateway, model, key=key is not None)
    out = tmp_path / "out"
    capsys.readouterr()
    code, took = sweep(cfg, out)
    err = capsys.readouterr().err.strip().splitlines()
    with capsys.disabled():
        print(f"\n{case}: stopped after {took:.1f} s: {err}")
    assert code == 2, err
    assert lines(out / RESULTS) == [] and not (out / INFRASTRUCTURE).exists()
    assert not list(out.glob("episodes/**/result.json"))
    return err, out


def test_a_key_variable_not_set_is_refused_before_any_call(tmp_path, gateway, monkeypatch, capsys):
    """`api_key_env` names a variable the environment lacks: the sweep refuses to start, one
    line naming the field, before it calls the proxy."""
    monkeypatch.delenv(KEY_ENV, raising=False)
    out = tmp_path / "out"
    code, took = sweep(sweep_config(tmp_path, gateway, "served"), out)
    err = capsys.readouterr().err.strip().splitlines()
    with capsys.disabled():
        print(f"\nkey variable not set: stopped after {took:.1f} s: {err}")
    assert code == 2 and len(err) == 1, err
    assert f"models[0].api_key_env: environment variable {KEY_ENV} is not set" in err[0]
    assert lines(out / RESULTS) == []


@pytest.mark.endpoint_check
@pytest.mark.parametrize("case", list(CASES))
def test_the_sweeps_check_stops_it_in_one_line_naming_the_cause(
    case, tmp_path, gateway, monkeypatch, capsys
):
    """The sweep's first step: one problem line naming the cause and its fix, then the line
    saying nothing was recorded."""
    err, _ = stop_on(case, tmp_path, gateway, monkeypatch, capsys)
    assert len(err) == 2 and err[1].startswith("stopped before the first episode"), err
    assert err[0].startswith("error: model 'gw': ") and "fix: " in err[0], err
    for named in CASES[case][2]:
        assert named in err[0], (named, err)


@pytest.mark.parametrize("case", list(CASES))
def test_the_pool_stops_the_sweep_at_its_first_call_in_one_line(
    case, tmp_path, gateway, monkeypatch, capsys
):
    """`--no-check` (or a check passed before the proxy changed): the first episode's call
    stops the sweep, one line, naming the cause."""
    err, out = stop_on(case, tmp_path, gateway, monkeypatch, capsys)
    assert len(err) == 1 and err[0].startswith("stopped: model 'gw': "), err
    for named in CASES[case][2]:
        assert named in err[0], (named, err)
    refused = sum(
        p.read_text().count('"type": "endpoint_refused"') for p in out.rglob("events.jsonl")
    )
    assert refused <= 1  # the first refused call stopped the sweep


def test_the_proxys_rate_limit_loses_no_episode(tmp_path, gateway, monkeypatch, caplog):
    """The `limited` model's minute is spent before the sweep starts: its calls get the
    proxy's 429s, wait them out (no attempt spent), and every episode is recorded once."""
    monkeypatch.setenv(KEY_ENV, MASTER_KEY)
    if time.time() % 60 > 50:  # spend the limit at the start of a minute, not at its end
        time.sleep(61 - time.time() % 60)
    statuses = [gateway.post("limited") for _ in range(LIMITED_RPM)]
    assert statuses[-1] == 429, statuses  # the minute's calls are spent
    caplog.set_level(logging.INFO, logger="vabench.llm_pool")
    cfg, out = sweep_config(tmp_path, gateway, "limited"), tmp_path / "out"
    code, took = sweep(cfg, out)
    print(f"\nrate limit: the sweep took {took:.1f} s")
    records = lines(out / RESULTS)
    assert code == 0, records
    assert len(records) == 2 and len({(r["seed"], r["run"]) for r in records}) == 2
    assert {r["status"] for r in records} <= {"success", "failure"}
    assert any("HTTP 429" in m for m in caplog.messages)  # the limit was met
    assert not (out / INFRASTRUCTURE).exists()


def test_infrastructure_errors_through_the_proxy_are_run_again_by_the_same_command(
    tmp_path, gateway, monkeypatch
):
    """The `flaky` upstream answers every call with a 500, which the proxy relays: each
    episode ends as an infrastructure error (not a stop: the upstream answered); healthy
    again, the same command runs them again, each recorded once."""
    monkeypatch.setenv(KEY_ENV, MASTER_KEY)
    cfg, out = sweep_config(tmp_path, gateway, "flaky"), tmp_path / "out"
    gateway.flaky.faults = FaultPlan(FaultConfig(rates={"server_error": 1.0}), random.Random(0))
    try:
        code, took = sweep(cfg, out)
        print(f"\nflaky upstream: the first run took {took:.1f} s")
        first = lines(out / RESULTS)
        assert code == 1, first  # every episode unscored, listed
        assert len(first) == 2 and {r["status"] for r in first} == {"infrastructure_error"}
        assert all("HTTP 500" in r["error"] for r in first), first
    finally:
        gateway.flaky.faults = FaultPlan(FaultConfig(), random.Random(0))  # healthy again
    code, took = sweep(cfg, out)
    print(f"flaky upstream: the rerun took {took:.1f} s")
    records = lines(out / RESULTS)
    assert code == 0, records
    keys = {(r["seed"], r["run"]) for r in records}
    assert len(records) == 2 and len(keys) == 2
    assert {r["status"] for r in records} <= {"success", "failure"}
    attempts = lines(out / INFRASTRUCTURE)
    assert len(attempts) == 2 and all(a["reopened"] for a in attempts)
    assert {(a["seed"], a["run"]) for a in attempts} == keys
