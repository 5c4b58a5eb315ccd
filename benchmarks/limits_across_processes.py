"""Rate limits across worker processes: one limit board against each process's own limits.

    python benchmarks/limits_across_processes.py --rpm 10 --period 2 --calls 12

For 1, 2 and 4 worker processes (spawned, each with its own LLM pool, as the processes
executor's workers), every process sends `--calls` calls at once to one embedded server on
loopback that enforces `--rpm` requests per `--period` seconds (its `rpm`, `rate_period_s`).
The pools' limits are the same `rpm` and period, taken either from the sweep's limit board in
this process (`llm_pool.board_socket`, what the processes executor does) or, the baseline, kept
by each process alone. Prints per row the busiest window of the period the server saw
(requests), the limit, and the 429s it sent. With the board the busiest window stays at or
under the limit and the server sends none, whatever the number of processes.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import time

from vabench.llm_pool import ChatRequest, LLMPool, Turn
from vabench.llm_pool.board_socket import BoardAddress, BoardServer, joined
from vabench.llm_pool.limit_board import LimitBoard
from vabench.llm_pool.server import ServerConfig
from vabench.llm_pool.testing import max_in_window, server_in_thread


def _worker(endpoint: dict, board: BoardAddress | None, calls: int, done) -> None:
    async def main() -> None:
        request = ChatRequest([Turn.user("ping")])
        if board is None:
            async with LLMPool([endpoint]) as pool:
                await asyncio.gather(*(pool.complete("m", request) for _ in range(calls)))
            return
        async with joined(board) as limits, LLMPool([endpoint], shared_limits=limits) as pool:
            await asyncio.gather(*(pool.complete("m", request) for _ in range(calls)))

    asyncio.run(main())
    done.put(True)


def measure(workers: int, shared: bool, args: argparse.Namespace) -> dict[str, float]:
    limits = {"rpm": args.rpm, "period_s": args.period, "max_concurrency": 16}
    server_config = ServerConfig(
        rpm=args.rpm, rate_period_s=args.period, latency={"mean_s": args.latency}
    )
    retry = {"max_attempts": 100, "backoff_base_s": 0.05, "backoff_max_s": 0.5}
    with server_in_thread(server_config) as server:
        endpoint = server.endpoint_config(
            "m", "openai_chat", limits=limits, generation={"max_output_tokens": 50}, retry=retry
        )
        board = BoardServer(LimitBoard({"m": limits}))
        address = BoardAddress(board.start(), ("m",), False) if shared else None
        context = multiprocessing.get_context("spawn")
        done = context.SimpleQueue()
        processes = [
            context.Process(target=_worker, args=(endpoint, address, args.calls, done))
            for _ in range(workers)
        ]
        started = time.monotonic()
        try:
            for p in processes:
                p.start()
            for _ in processes:
                done.get()
            for p in processes:
                p.join(30)
        finally:
            board.close()
        elapsed = time.monotonic() - started
        log = [(r.received_s, r.status) for r in server.log]
    ok = [(t, 1.0) for t, s in log if s == 200]
    return {
        "busiest": max_in_window([(t, 1.0) for t, _ in log], args.period),
        "busiest_ok": max_in_window(ok, args.period),
        "requests": len(log),
        "429s": sum(s == 429 for _, s in log),
        "seconds": elapsed,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--rpm", type=float, default=10, help="requests per period (client and server)")
    p.add_argument("--period", type=float, default=2.0, help="seconds per window")
    p.add_argument("--calls", type=int, default=12, help="calls per worker process")
    p.add_argument("--latency", type=float, default=0.05, help="the server's seconds per reply")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--no-baseline", action="store_true", help="skip each process's own limits")
    p.add_argument(
        "--record",
        action="store_true",
        help="append the largest count's busiest window to benchmarks/results/limits.json",
    )
    args = p.parse_args()
    rows = {}
    print(f"limit {args.rpm:g} requests per {args.period:g} s; {args.calls} calls per process")
    print(f"{'processes':>9} {'limits':>13} {'busiest window':>15} {'requests':>9} {'429s':>6}")
    for workers in args.workers:
        for shared in (True, False) if not args.no_baseline else (True,):
            row = measure(workers, shared, args)
            rows[workers, shared] = row
            print(
                f"{workers:>9} {'one board' if shared else 'own each':>13} "
                f"{row['busiest']:>10.0f} / {args.rpm:<3g} {row['requests']:>9} "
                f"{row['429s']:>6}",
                flush=True,
            )
    if args.record:
        record_headline(rows, args)


def record_headline(rows: dict, args: argparse.Namespace) -> None:
    """The busiest window over the limit at the most processes, one board against own limits."""
    import results_log

    workers = max(w for w, _ in rows)
    board = rows[workers, True]
    own = rows.get((workers, False))
    extra = {}
    if own is not None:
        extra = {
            "baseline": "own limits each",
            "ratio": round(board["busiest"] / own["busiest"], 3),
        }
    figure = f"busiest window over the limit, {workers} processes, one board"
    note = f"{args.rpm:g} requests per {args.period:g} s; {board['429s']} 429s"
    value = board["busiest"] / args.rpm
    results_log.append("limits", results_log.record(figure, value, "x limit", note, **extra))


if __name__ == "__main__":
    main()
