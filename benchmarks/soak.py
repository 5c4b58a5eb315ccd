"""Soak: the LLM pool and the episode engine for a long run against a faulty embedded server.

    python benchmarks/soak.py [--minutes 10] [--callers 1200] [--latency 4] [--fault-rate 0.2]
        [--episodes 6] [--steps 8] [--warmup 60] [--json FILE]

One process, one embedded server (real HTTP on loopback) that answers after a lognormal latency
and injects `--fault-rate` faults spread evenly over every kind it knows (`faults.FAULT_KINDS`:
429 with Retry-After, 529, 503, 500, a reply slower than the attempt timeout, a malformed body,
a truncated body, a dropped connection). Through one `LLMPool`:

- `--callers` loops (split over the registered APIs, one endpoint each) keep that many calls in
  flight: each call carries a unique id, the server's `echo` policy answers with it, and the
  caller checks the reply is its own;
- `--episodes` engine episodes at a time (C MuJoCo, 64x48 images, `--steps` decisions each,
  the `random_action` policy) run one after another into a records directory.

When the time is up no new call or episode starts; those running finish. Then the books:
- lost = calls started - calls ended (success, infrastructure error, rejection); double = calls
  that ended twice or got another call's reply; episodes: one result.json each, its calls equal
  to its reply events;
- every attempt the server logged (its request log) is matched with what the client logged
  for it, kind by kind: an injected fault as its status, malformed body, cut body or dropped
  connection; an attempt the client abandoned while the server was still on it (a "slow"
  fault, or a latency or a loaded loop that outlasted the attempt timeout) as a timeout. A
  client timeout at the instant the server answered is counted apart (`reconcile`): the
  server logged an answer (perhaps a faulted one), the client a timeout;
- the process's resident memory (VmRSS) every 15 s: first sample after warm-up (`--warmup`
  seconds), last, max, and its least-squares slope after warm-up in MB/min (flat memory: the
  target is < 0.1).
Prints the figures; `--json` writes them. Exit code 1 if anything is lost, doubled or
unaccounted for.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

RETRY = {"max_attempts": 6, "total_timeout_s": 300.0, "backoff_base_s": 0.2, "backoff_max_s": 2.0}


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def slope_per_min(samples: list[tuple[float, float]]) -> float:
    """Least-squares slope of (seconds, MB) samples, in MB per minute (0 for fewer than 2)."""
    if len(samples) < 2:
        return 0.0
    n = len(samples)
    mt = sum(t for t, _ in samples) / n
    mm = sum(m for _, m in samples) / n
    var = sum((t - mt) ** 2 for t, _ in samples)
    return 60 * sum((t - mt) * (m - mm) for t, m in samples) / var if var else 0.0


def fault_kind(line: str) -> str:
    """The injected fault a client-side failure line stands for."""
    if line.startswith("HTTP "):
        return {"429": "rate_limit", "529": "overloaded", "503": "unavailable"}.get(
            line[5:8], "server_error" if line[5:8] == "500" else f"http_{line[5:8]}"
        )
    if line.startswith("timeout"):
        return "slow"
    if "invalid JSON" in line or "response: field" in line or "empty body" in line:
        return "malformed"
    if "Payload" in line or "ContentLength" in line or "TransferEncoding" in line:
        return "truncated"
    if "Disconnected" in line or "Connection" in line:
        return "drop"
    return f"other: {line[:60]}"


class Books:
    """What the callers and episodes saw."""

    def __init__(self) -> None:
        self.started = 0
        self.ended: Counter[str] = Counter()
        self.outcomes = bytearray()  # one byte per call id: times it ended (flat memory)
        self.double = 0
        self.wrong_reply = 0
        self.client_faults: Counter[str] = Counter()
        self.in_flight_samples: list[int] = []
        self.attempts_in_flight: list[int] = []

    def end(self, call_id: int, how: str, failures: tuple[str, ...]) -> None:
        if call_id >= len(self.outcomes):
            self.outcomes.extend(bytes(max(call_id + 1 - len(self.outcomes), 1 << 16)))
        if self.outcomes[call_id]:
            self.double += 1
        self.outcomes[call_id] = 1
        self.ended[how] += 1
        self.client_faults.update(fault_kind(f) for f in failures)


async def caller(pool, endpoint: str, ids, books: Books, stop: asyncio.Event) -> None:
    from vabench.llm_pool import ChatRequest, InfrastructureError, RequestRejected, Turn

    history = [Turn.user("Step 1 of 50: observe."), Turn.assistant("camera.view_topdown")]
    while not stop.is_set():
        call_id = next(ids)
        request = ChatRequest((*history, Turn.user(f"call {call_id}")), "You control a robot.")
        books.started += 1
        try:
            result = await pool.complete(endpoint, request)
        except InfrastructureError as err:
            books.end(call_id, "infrastructure_error", err.failures)
            continue
        except RequestRejected as err:
            books.end(call_id, "rejected", (err.message,))
            continue
        books.end(call_id, "success", result.failures)
        if not result.text.startswith(f"call {call_id} "):
            books.wrong_reply += 1


async def episodes(pool, render, out: Path, n: int, steps: int, stop: asyncio.Event) -> Counter:
    from vabench.agent.engine import EpisodeSpec, run_episode
    from vabench.agent.services import task_services
    from vabench.render.worker import ImageSettings
    from vabench.tasks import get_task
    from vabench.tasks.manifests import verified_seeds

    task = get_task("grasp_single_cube")
    seeds = verified_seeds(task.name)
    results: Counter[str] = Counter()
    counter = itertools.count()
    async with task_services(
        task, n, pool, render, backend="c", image=ImageSettings(64, 48)
    ) as svc:

        async def loop() -> None:
            while not stop.is_set():
                i = next(counter)
                spec = EpisodeSpec(
                    task.name, seeds[i % len(seeds)], "engine", run=i, out_dir=out / f"ep_{i:05d}",
                    step_budget=steps,
                )  # fmt: skip
                results[(await run_episode(spec, svc)).status] += 1

        await asyncio.gather(*(loop() for _ in range(n)))
    return results


def expected_failures(server_log: Path) -> Counter:
    """The failed attempt the client should have logged for each request the server logged:
    a client that went away was a timeout (whatever the server meant to do); otherwise the
    injected fault, if any."""
    expected: Counter[str] = Counter()
    with server_log.open() as f:
        for line in f:
            r = json.loads(line)
            if r.get("error") == "client went away":
                expected["slow"] += 1
            elif r.get("fault"):
                expected[r["fault"]] += 1
    return expected


def reconcile(expected: Counter, client: Counter) -> dict:
    """Match the server's attempts with the client's failures, kind by kind. A reply the
    server finished as the client's attempt timed out (a loaded loop read it too late) is a
    timeout on the client's side and a normal or faulted reply on the server's: such extra
    timeouts (`timeouts_as_the_reply_came`) may stand in for faulted replies, and only for
    them; anything else is unaccounted."""
    surplus = client["slow"] - expected["slow"]
    stood_in = {
        k: expected[k] - client[k] for k in expected if k != "slow" and expected[k] > client[k]
    }
    unaccounted = {
        k: expected[k] - client[k]
        for k in set(expected) | set(client)
        if k != "slow" and client[k] > expected[k]
    }
    if surplus < 0 or sum(stood_in.values()) > surplus:
        unaccounted["slow"] = -surplus
        unaccounted.update({f"{k} (not seen)": n for k, n in stood_in.items()})
    return {
        "timeouts_as_the_reply_came": max(0, surplus),
        "of_them_faulted_replies": stood_in,
        "unaccounted": unaccounted,
    }


def check_episodes(out: Path, results: Counter) -> tuple[Counter, int, Counter]:
    """Statuses, episodes whose records disagree, and the faults their events logged."""
    from vabench.agent.records import read_events, read_result

    statuses: Counter[str] = Counter()
    bad = 0
    faults: Counter[str] = Counter()
    dirs = sorted(out.glob("ep_*"))
    for d in dirs:
        result = read_result(d)
        events = read_events(d)
        replies = [e for e in events if e["type"] == "reply"]
        for e in events:
            if e["type"] in ("reply", "llm_failure"):
                faults.update(fault_kind(f) for f in e.get("failures", []))
        if result is None or result.model_calls != len(replies) or events[-1]["type"] != "end":
            bad += 1
            continue
        statuses[result.status] += 1
    bad += abs(len(dirs) - sum(results.values())) + (statuses != results)
    return statuses, bad, faults


async def soak(args) -> dict:
    from vabench.llm_pool import LLMPool
    from vabench.llm_pool.apis import ADAPTERS
    from vabench.llm_pool.faults import FAULT_KINDS
    from vabench.llm_pool.server import LocalServer, ServerConfig
    from vabench.render.worker import RenderPool

    per_kind = args.fault_rate / len(FAULT_KINDS)
    # An attempt may take 5 mean latencies (a loaded 2-core box stretches the tail); a "slow"
    # fault takes longer than that, so it always ends as a client timeout.
    retry = {**RETRY, "request_timeout_s": 5 * args.latency}
    out = Path(tempfile.mkdtemp(prefix="vabench-soak-"))
    server_log = out / "server.jsonl"
    config = ServerConfig(
        policy="echo",
        model_policies={"engine": {"policy": "random_action"}},
        latency={"mean_s": args.latency, "dist": "lognormal", "spread": 0.5},
        faults={
            "rates": dict.fromkeys(FAULT_KINDS, per_kind),
            "retry_after_s": 0.1,
            "slow_s": retry["request_timeout_s"] + 2,
        },
        simulate_cache=False,  # its prefix store grows to 100,000 entries: not ours to measure
        log_size=0,
        log_path=str(server_log),
        seed=1,
    )
    books = Books()
    stop = asyncio.Event()
    rss: list[tuple[float, float]] = []
    apis = tuple(ADAPTERS)
    per_api = -(-args.callers // len(apis))
    async with LocalServer(config) as server:
        endpoints = [
            server.endpoint_config(api, api, retry=retry, limits={"max_concurrency": per_api + 16})
            for api in apis
        ]
        endpoints.append(server.endpoint_config("engine", "openai_chat", retry=retry))
        with RenderPool(workers=1, max_size=(64, 48)) as render:
            async with LLMPool(endpoints, seed=1) as pool:
                ids = itertools.count()
                t0 = time.monotonic()
                tasks = [
                    asyncio.create_task(caller(pool, apis[i % len(apis)], ids, books, stop))
                    for i in range(args.callers)
                ]
                engine = asyncio.create_task(
                    episodes(pool, render, out, args.episodes, args.steps, stop)
                )
                end = t0 + args.minutes * 60
                next_rss = t0 + 15
                while time.monotonic() < end:
                    await asyncio.sleep(1.0)
                    books.in_flight_samples.append(books.started - sum(books.ended.values()))
                    books.attempts_in_flight.append(
                        sum(st.in_flight for st in pool.stats().values())
                    )
                    if time.monotonic() >= next_rss:
                        rss.append((time.monotonic() - t0, rss_mb()))
                        next_rss += 15
                        print(
                            f"{rss[-1][0]:6.0f} s: calls {books.started:,}, in flight "
                            f"{books.in_flight_samples[-1]:,}, RSS {rss[-1][1]:.0f} MB",
                            flush=True,
                        )
                stop.set()
                steady_s = time.monotonic() - t0
                await asyncio.gather(*tasks)
                ep_results = await engine
                total_s = time.monotonic() - t0
                usage_books = {n: s.usage for n, s in pool.stats().items()}
                attempts = sum(s.attempts for s in pool.stats().values())
        server_faults = {k[6:]: v for k, v in server.counts.items() if k.startswith("fault:")}
    statuses, bad_records, episode_faults = check_episodes(out, ep_results)
    client_faults = books.client_faults + episode_faults
    expected = expected_failures(server_log)
    after = [(t, m) for t, m in rss if t >= args.warmup] or rss
    warm = [m for _, m in after]
    steady = books.in_flight_samples[len(books.in_flight_samples) // 10 :]
    figures = {
        "minutes": round(steady_s / 60, 2),
        "drain_s": round(total_s - steady_s, 1),
        "calls": books.started,
        "ended": dict(books.ended),
        "lost": books.started - sum(books.ended.values()),
        "double": books.double,
        "wrong_reply": books.wrong_reply,
        "attempts": attempts,
        "in_flight_min": min(steady),
        "in_flight_mean": round(sum(steady) / len(steady)),
        "attempts_in_flight_mean": round(
            sum(books.attempts_in_flight[len(books.attempts_in_flight) // 10 :])
            / max(1, len(books.attempts_in_flight) - len(books.attempts_in_flight) // 10)
        ),
        "server_requests": sum(1 for _ in server_log.open()),
        "episodes": sum(ep_results.values()),
        "episode_statuses": dict(statuses),
        "episode_records_bad": bad_records,
        "server_faults": server_faults,
        "client_faults": dict(client_faults),
        "expected_failures": dict(expected),
        **reconcile(expected, client_faults),
        "rss_mb_first_after_warmup": round(warm[0], 1),
        "rss_mb_last": round(warm[-1], 1),
        "rss_mb_max": round(max(warm), 1),
        "rss_slope_mb_per_min": round(slope_per_min(after), 3),
        "rss_samples": [(round(t), round(m, 1)) for t, m in rss],
        "tokens": {n: u.total_tokens for n, u in usage_books.items()},
        "records": str(out),
    }
    return figures


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--callers", type=int, default=1200)
    p.add_argument("--latency", type=float, default=4.0, help="mean seconds per reply")
    p.add_argument("--fault-rate", type=float, default=0.2)
    p.add_argument("--episodes", type=int, default=6, help="engine episodes at a time")
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--warmup", type=float, default=60.0, help="seconds before the RSS slope")
    p.add_argument("--json")
    args = p.parse_args()
    figures = asyncio.run(soak(args))
    print(json.dumps({k: v for k, v in figures.items() if k != "rss_samples"}))
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1))
    ok = (
        figures["lost"] == 0
        and figures["double"] == 0
        and figures["wrong_reply"] == 0
        and figures["episode_records_bad"] == 0
        and not figures["unaccounted"]
    )
    print("OK" if ok else "NOT OK: see lost / double / wrong_reply / records / faults")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
