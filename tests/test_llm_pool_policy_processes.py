"""The embedded server computing a stateless policy's replies in worker processes
(`ServerConfig.policy_processes`): the same replies as in-process for the same requests, over
real HTTP; the workers are the server's children, started before its first request and ended
with it; policies that keep state ignore the setting."""

from __future__ import annotations

import asyncio
from pathlib import Path

from vabench.llm_pool import ChatRequest, LLMPool, Turn
from vabench.llm_pool.server import LocalServer, ServerConfig


def children(pid: int) -> set[int]:
    """Live spawned worker processes of `pid` (not multiprocessing's resource tracker)."""
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z" and b"spawn_main" in cmdline:
            out.add(int(stat.parent.name))
    return out


async def replies(config: ServerConfig) -> tuple[list[str], int, int]:
    """The replies to 40 distinct conversations, the server's child processes while it ran,
    and after it stopped."""
    import os

    before = children(os.getpid())
    async with LocalServer(config) as server:
        running = children(os.getpid()) - before
        endpoint = server.endpoint_config("local", "openai_chat")
        async with LLMPool([endpoint]) as pool:
            requests = [ChatRequest([Turn.user(f"Step 1/5: episode {i}")]) for i in range(40)]
            results = await asyncio.gather(*(pool.complete("local", r) for r in requests))
    await asyncio.sleep(0.5)
    left = children(os.getpid()) - before
    return [r.text for r in results], len(running), len(left)


def test_replies_from_worker_processes_equal_the_in_process_ones():
    here, n_here, _ = asyncio.run(replies(ServerConfig(policy="conversation_hash")))
    there, n_there, left = asyncio.run(
        replies(ServerConfig(policy="conversation_hash", policy_processes=2))
    )
    assert here == there and len(set(here)) > 1
    assert n_here == 0 and n_there == 2 and left == 0


def test_a_policy_with_state_stays_in_the_server_process():
    _, n, _ = asyncio.run(replies(ServerConfig(policy="random_action", policy_processes=2)))
    assert n == 0
