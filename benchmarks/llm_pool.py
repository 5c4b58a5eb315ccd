"""The LLM pool against the embedded server, in one run: does the client ever become the limit?

(a) Concurrency: the server (a separate process, same machine) answers every call after exactly
    L seconds; C closed-loop callers send 500 KB requests (four images, freshly encoded each
    call). The ideal is C/L calls per second; the ratio achieved/ideal shows when the client,
    the server or the machine becomes the bottleneck. CPU use of both processes is reported.
(b) Rate limits: the server enforces RPM and TPM (strict sliding windows; a 429 with
    Retry-After beyond them); the client is configured with the same limits and far more
    demand than they allow. Achieved requests and tokens per period over the allowed ones,
    measured on the server's own log, and the 429s the client caused.

    python benchmarks/llm_pool.py [--latency 5] [--concurrency 10,50,100,200,500,1000,2000]
        [--body-kb 500] [--measure-periods 3] [--rate-period 60] [--json OUT] [--quick]

The soft open-files limit is raised to the hard limit (2,000 callers hold 2,000 client and
2,000 server sockets). `--quick` shortens everything (latency 1 s, 10 s rate periods).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vabench.llm_pool import ChatRequest, Image, InfrastructureError, LLMPool, Turn
from vabench.llm_pool.testing import max_in_window, synthetic_jpeg

IMAGES_PER_CALL = 4
TEXT = "Step 12/50. Task: pick up the red cube. Gripper state: ... " * 8


def raise_open_files_limit() -> int:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


class ServerProcess:
    """`python -m vabench.llm_pool.serve` on a free port, with its CPU time readable."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "vabench.llm_pool.serve", "--port", "0", *args],
            stdout=subprocess.PIPE,
            text=True,
        )
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        match = re.search(r"http://[\d.]+:\d+", line)
        if not match:
            self.proc.kill()
            raise RuntimeError(f"server did not start: {line!r}")
        self.url = match.group(0)

    def cpu_seconds(self) -> float:
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=30)


def make_request(images: list[bytes], rng: random.Random) -> ChatRequest:
    """A request whose images are new Image objects: base64 is paid on every call, as if every
    image were new (the engine resends 3 of 4, already encoded, so this is the harder case)."""
    chosen = [Image(rng.choice(images)) for _ in range(IMAGES_PER_CALL)]
    parts: list = []
    for view, image in zip(("topdown", "side", "front_side_45", "oblique_45"), chosen, strict=True):
        parts += [view, image]
    return ChatRequest([Turn.user(TEXT, *parts)], system="You control a robot arm.")


async def concurrency_point(
    url: str, c: int, latency: float, images: list[bytes], measure_s: float, server: ServerProcess
) -> dict:
    endpoint = {
        "name": "bench",
        "api": "openai_chat",
        "base_url": f"{url}/v1",
        "limits": {"max_concurrency": c},
        "retry": {"request_timeout_s": latency * 4 + 60},
        "generation": {"max_output_tokens": 256},
    }
    pool = LLMPool([endpoint], seed=c)
    loop = asyncio.get_running_loop()
    done: list[tuple[float, float]] = []  # (completion time, latency)
    errors: list[str] = []
    retried: list[str] = []  # the first failure of calls that needed more than one attempt
    rng = random.Random(c)

    async def caller(i: int) -> None:
        await asyncio.sleep(i * latency / c)  # staggered, as episodes are
        while True:
            start = loop.time()
            try:
                result = await pool.complete("bench", make_request(images, rng))
                done.append((loop.time(), loop.time() - start))
                retried.extend(result.failures[:1])
            except InfrastructureError as err:
                errors.append(str(err)[:200])

    t0 = loop.time()
    tasks = [asyncio.create_task(caller(i)) for i in range(c)]
    warmup = 2 * latency  # every caller has started and completed at least one call
    await asyncio.sleep(warmup)
    cpu_client0, cpu_server0 = time.process_time(), server.cpu_seconds()
    await asyncio.sleep(measure_s)
    cpu_client = time.process_time() - cpu_client0
    cpu_server = server.cpu_seconds() - cpu_server0
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await pool.close()
    window = [lat for at, lat in done if t0 + warmup <= at < t0 + warmup + measure_s]
    achieved = len(window) / measure_s
    ideal = c / latency
    window.sort()
    return {
        "concurrency": c,
        "ideal_per_s": ideal,
        "achieved_per_s": achieved,
        "ratio": achieved / ideal,
        "mean_latency_s": sum(window) / max(1, len(window)),
        "p99_latency_s": window[int(0.99 * (len(window) - 1))] if window else float("nan"),
        "client_cpu": cpu_client / measure_s,
        "server_cpu": cpu_server / measure_s,
        "errors": len(errors),
        "first_error": errors[0] if errors else None,
        "retried_calls": len(retried),
        "first_retry_reason": retried[0] if retried else None,
    }


def run_concurrency(args, images: list[bytes]) -> list[dict]:
    server = ServerProcess("--policy", "random_action", "--latency", str(args.latency))
    rows = []
    try:
        for c in args.concurrency:
            measure = args.measure_periods * args.latency
            row = asyncio.run(
                concurrency_point(server.url, c, args.latency, images, measure, server)
            )
            rows.append(row)
            print(
                f"  C={c:5d}  ideal {row['ideal_per_s']:7.1f}/s"
                f"  achieved {row['achieved_per_s']:7.1f}/s"
                f"  ratio {row['ratio']:.3f}  latency mean {row['mean_latency_s']:.3f} s"
                f" p99 {row['p99_latency_s']:.3f} s  cpu client {row['client_cpu']:.2f}"
                f" server {row['server_cpu']:.2f}  errors {row['errors']}"
                f"  retried {row['retried_calls']} {row['first_retry_reason'] or ''}",
                flush=True,
            )
    finally:
        server.stop()
    return rows


async def drive_rate_limited(
    url: str, limits: dict, callers: int, duration: float, images: list[bytes]
) -> int:
    endpoint = {
        "name": "bench",
        "api": "anthropic",
        "base_url": url,
        "limits": {**limits, "max_concurrency": callers},
        "generation": {"max_output_tokens": 256},
        "retry": {"max_attempts": 20, "total_timeout_s": duration * 2},
    }
    pool = LLMPool([endpoint], seed=1)
    rng = random.Random(1)

    async def caller() -> None:
        while True:
            with contextlib.suppress(InfrastructureError):
                await pool.complete("bench", make_request(images, rng))

    tasks = [asyncio.create_task(caller()) for _ in range(callers)]
    await asyncio.sleep(duration)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    stats = pool.stats()["bench"]
    await pool.close()
    return stats.rate_limited


def run_rate_limits(args, images: list[bytes]) -> list[dict]:
    period = args.rate_period
    # Request size: 4 images of 1280x960 (~1,600 tokens each by Anthropic's rule) + text,
    # estimated at admission with 256 max output tokens.
    scenarios = [
        ("RPM-bound", {"rpm": 600 * period / 60, "tpm": 1e9}),
        ("TPM-bound", {"rpm": 1e6, "tpm": 1_000_000 * period / 60}),
    ]
    rows = []
    for name, limits in scenarios:
        with tempfile.TemporaryDirectory() as tmp:
            log = Path(tmp) / "requests.jsonl"
            server = ServerProcess(
                "--policy",
                "random_action",
                "--latency",
                "0.5",
                "--latency-dist",
                "uniform",
                "--latency-spread",
                "0.5",
                "--rpm",
                str(limits["rpm"]),
                "--tpm",
                str(limits["tpm"]),
                "--rate-period",
                str(period),
                "--log",
                str(log),
            )
            try:
                duration = args.measure_periods * period + 2.0
                limits_cfg = {**limits, "period_s": period}
                rate_limited = asyncio.run(
                    drive_rate_limited(server.url, limits_cfg, 200, duration, images)
                )
            finally:
                server.stop()
            records = [json.loads(line) for line in log.read_text().splitlines()]
        ok = [r for r in records if r["status"] == 200]
        refused = sum(r["status"] == 429 for r in records)
        start = min(r["received_s"] for r in ok)
        horizon = start + args.measure_periods * period
        in_window = [r for r in ok if r["received_s"] < horizon]
        tokens = [(r["received_s"], r["input_tokens"] + r["output_tokens"]) for r in ok]
        requests = [(r["received_s"], 1.0) for r in ok]
        if name == "RPM-bound":
            allowed = limits["rpm"] * args.measure_periods
            achieved = len(in_window)
            worst = max_in_window(requests, period) / limits["rpm"]
        else:
            allowed = limits["tpm"] * args.measure_periods
            achieved = sum(r["input_tokens"] + r["output_tokens"] for r in in_window)
            worst = max_in_window(tokens, period) / limits["tpm"]
        row = {
            "scenario": name,
            "period_s": period,
            "limit_per_period": limits["rpm"] if name == "RPM-bound" else limits["tpm"],
            "periods": args.measure_periods,
            "achieved": achieved,
            "allowed": allowed,
            "ratio": achieved / allowed,
            "max_window_over_limit": worst,
            "server_429s": refused,
            "429_at_s": [round(r["received_s"] - start, 2) for r in records if r["status"] == 429],
            "client_saw_429s": rate_limited,
            "requests": len(in_window),
        }
        rows.append(row)
        print(
            f"  {name}: achieved {achieved:,.0f} of {allowed:,.0f} allowed"
            f" in {args.measure_periods} x {period:g} s  ratio {row['ratio']:.3f}"
            f"  busiest window {worst:.3f} of the limit"
            f"  429s {refused}",
            flush=True,
        )
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--latency", type=float, default=5.0)
    p.add_argument("--concurrency", default="10,50,100,200,500,1000,2000")
    p.add_argument("--body-kb", type=int, default=500)
    p.add_argument(
        "--measure-periods",
        type=int,
        default=3,
        help="(a) measure over this many latencies; (b) over this many rate periods",
    )
    p.add_argument("--rate-period", type=float, default=60.0)
    p.add_argument("--skip", choices=["a", "b"], help="skip one part")
    p.add_argument("--json", type=Path)
    p.add_argument("--quick", action="store_true")
    p.add_argument(
        "--record",
        action="store_true",
        help="append each point's calls/s against C/L to benchmarks/results/llm_pool.json",
    )
    args = p.parse_args()
    if args.quick:
        args.latency, args.rate_period, args.measure_periods = 1.0, 10.0, 2
    args.concurrency = [int(c) for c in args.concurrency.split(",")]
    files = raise_open_files_limit()
    # Base64 of the raw image bytes makes up nearly all of a body: size them to the target.
    raw = args.body_kb * 1000 * 3 // 4 // IMAGES_PER_CALL
    images = [synthetic_jpeg(1280, 960, size=raw, seed=s) for s in range(16)]
    body = len(json.dumps(make_request(images, random.Random(0)).turns[0].content[-1].b64)) * 4
    load = os.getloadavg()
    print(
        f"open files limit {files}; body ~{body / 1000:.0f} KB; load {load[0]:.2f} "
        f"{load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs",
        flush=True,
    )
    out: dict = {"latency_s": args.latency, "body_kb": body / 1000, "load_before": load}
    if args.skip != "a":
        print(f"(a) concurrency at L = {args.latency:g} s", flush=True)
        out["concurrency"] = run_concurrency(args, images)
    if args.skip != "b":
        print(f"(b) rate limits, period {args.rate_period:g} s", flush=True)
        out["rate_limits"] = run_rate_limits(args, images)
    out["load_after"] = os.getloadavg()
    print(
        f"load after {out['load_after'][0]:.2f} {out['load_after'][1]:.2f} "
        f"{out['load_after'][2]:.2f}"
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    if args.record:
        record_results(out, args)
    return 0


def record_results(out: dict, args: argparse.Namespace) -> None:
    """Part (a)'s calls/s against the ideal, one record a concurrency (a --quick run is not)."""
    import results_log

    if args.quick:
        print("--record: a --quick run is a smoke run; nothing recorded", file=sys.stderr)
        return
    body = f"~{out['body_kb']:.0f} KB bodies; load {out['load_before'][0]:.2f} before"
    for row in out.get("concurrency", []):
        results_log.append(
            "llm_pool",
            results_log.record(
                f"pool calls/s at L = {args.latency:g} s, C = {row['concurrency']:,}",
                round(row["achieved_per_s"], 1),
                "calls/s",
                f"{body}; {row['errors']} errors",
                baseline="ideal C/L",
                ratio=round(row["ratio"], 3),
            ),
        )


if __name__ == "__main__":
    sys.exit(main())
