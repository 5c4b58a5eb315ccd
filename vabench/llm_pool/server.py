"""The embedded server: the registered provider APIs on a local port, answered by a policy.

Tests, benchmarks and network-free sweeps talk to it exactly as they would to a provider:

    async with LocalServer(ServerConfig(policy="random_action")) as server:
        pool = LLMPool([server.endpoint_config("random", "anthropic")])
        ...

Routes: a `POST` at each registered API's `route` (`apis.ADAPTERS`: `/v1/chat/completions`,
`/v1/responses`, `/v1/messages`; each request validated against the documented shape, a
mismatch is a 400 naming the field, in the API's own error format), `GET /v1/models`,
`GET /health`, `GET /stats`.

Around the policy it simulates a provider: latency drawn from a distribution, usage with
prompt caching (`simulate.py`), injected faults (`faults.py`), optional RPM/TPM enforcement
(a strict sliding window: the requests and tokens admitted in any window of one period never
exceed the limits; refusals are 429s with Retry-After and the API's rate-limit headers), an
optional API key check, the limits of a local inference server answered as it answers them
(`imitate`: vLLM's image and context limits and model name, Ollama's silent truncation,
llama.cpp's unread output-limit field), and a request log (in memory, and as JSONL if asked)
that never holds a header or a key. Which policy answers is chosen per model name
(`model_policies`), falling back to `policy`. All of it is set in a `ServerConfig`
(`server_config.py`).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import multiprocessing
import os
import random
import socket
from collections import Counter, deque
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import IO, Any

from aiohttp import web

from vabench.children import children_ignore_sigint, exit_with_parent, ignore_sigint
from vabench.llm_pool.apis import (
    ADAPTERS,
    ApiAdapter,
    IncomingRequest,
    LimitState,
    ServerReply,
    get_adapter,
)
from vabench.llm_pool.apis.base import RequestShapeError
from vabench.llm_pool.faults import (
    IMMEDIATE_FAULTS,
    FaultPlan,
    drop_connection,
    error_response,
    malformed_response,
    no_reasoning_refusal,
    reasoning_refusal,
    retry_after_headers,
    status_of,
    truncated_response,
    vllm_error,
    vllm_refusal,
)
from vabench.llm_pool.heap import keep_trimmed
from vabench.llm_pool.limits import RateBudget
from vabench.llm_pool.policies import (
    PURE_REPLIES,
    Policy,
    PolicyError,
    PolicyReply,
    make_policy,
    pure_function,
    pure_reply,
)
from vabench.llm_pool.request_record import RequestRecord
from vabench.llm_pool.server_config import (
    PolicySpec,
    ServerConfig,
    policy_workers,
    serving_processes,
)
from vabench.llm_pool.server_processes import READY, ServingProcesses
from vabench.llm_pool.settings import DEFAULT_MAX_OUTPUT_TOKENS
from vabench.llm_pool.simulate import PromptCache, simulate_usage, truncated_usage
from vabench.llm_pool.tokens import CHARS_PER_TOKEN, block_tokens, text_tokens


class LocalServer:
    """The embedded server; start with `await start()` or `async with`."""

    def __init__(
        self,
        config: ServerConfig | None = None,
        *,
        policy: Policy | None = None,
        capture_bodies: bool = False,
    ):
        self.config = config or ServerConfig()
        self.processes = serving_processes(self.config)
        """Processes serving the routes (0: this event loop; see `server_processes`)."""
        if self.processes and (policy is not None or capture_bodies):
            raise ValueError(
                "server_processes: a policy object or captured bodies need the server in this "
                "process; set server_processes: 0"
            )
        self.bodies: list[tuple[str, bytes]] | None = [] if capture_bodies else None
        """With `capture_bodies`: (api, raw body) of every request, for tests that inspect
        exactly what a model would receive (the privilege-boundary test)."""
        rng = random.Random(self.config.seed)
        self._rng = random.Random(rng.random())
        self.faults = FaultPlan(self.config.faults, random.Random(rng.random()))
        self.policy = policy or make_policy(self.config.policy, **self.config.policy_options)
        self._model_policies = {
            name: make_policy(spec.policy, **spec.options)
            for name, spec in self.config.model_policies.items()
        }
        # (policy name, options) per requested model, for policies computed in processes
        default = (
            None
            if policy
            else PolicySpec(policy=self.config.policy, options=self.config.policy_options)
        )
        self._specs: dict[str | None, PolicySpec | None] = {None: default}
        self._specs.update(self.config.model_policies)
        self._workers: ProcessPoolExecutor | None = None
        self.cache = PromptCache() if self.config.simulate_cache else None
        self._requests = self._budget(self.config.rpm)
        self._tokens = self._budget(self.config.tpm)
        self.log: deque[RequestRecord] = deque(maxlen=self.config.log_size)
        self.counts: Counter[str] = Counter()
        self.process_index = 0
        """This process's index among the serving processes (0: the only one)."""
        self.on_record: Callable[[RequestRecord], None] | None = None
        """Told every finished request (a serving process sends its records to its parent)."""
        self._next_id = 0
        self._runner: web.AppRunner | None = None
        self._log_file: IO[str] | None = None
        self._processes: ServingProcesses | None = None
        self.host = "127.0.0.1"
        self.port = 0

    def _budget(self, limit: float | None) -> RateBudget | None:
        """Burst = period: the bucket never binds before the window; margin 0: the window is
        exactly one period. Enforcement is the strict sliding window, nothing more."""
        period = self.config.rate_period_s
        return RateBudget(limit, period, burst_s=period, margin=0.0) if limit else None

    # -- lifecycle ---------------------------------------------------------------------------
    def app(self) -> web.Application:
        app = web.Application(client_max_size=256 * 1024 * 1024)
        for adapter in ADAPTERS.values():
            app.router.add_post(adapter.route, self._handler(adapter))
        app.router.add_get("/v1/models", self._models)
        app.router.add_get("/health", self._health)
        app.router.add_get("/stats", self._stats)
        return app

    async def start(
        self, host: str = "127.0.0.1", port: int = 0, *, reuse_port: bool = False
    ) -> LocalServer:
        """Listen on host:port (port 0: a free port, see `.port`); `reuse_port`: share the port
        with other processes (SO_REUSEPORT)."""
        keep_trimmed()  # else a long run's read buffers hold heap pages (heap.py)
        if self.config.log_path:
            self._log_file = open(self.config.log_path, "a", encoding="utf-8")  # noqa: SIM115
        if self.processes:
            self._processes = ServingProcesses(
                self.config, self.processes, _serve_in_process, self._note
            )
            self.host, self.port = await asyncio.to_thread(self._processes.start, host, port)
            return self
        await self._start_workers()
        # handler_cancellation: a client that gives up (timeout) cancels our sleeping handler
        # instead of leaving it to finish for nobody.
        self._runner = web.AppRunner(self.app(), handler_cancellation=True, access_log=None)
        await self._runner.setup()
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if reuse_port:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
        site = web.SockSite(self._runner, sock, backlog=4096)
        await site.start()
        self.host, self.port = sock.getsockname()[:2]
        return self

    async def stop(self) -> None:
        if self._processes is not None:
            processes, self._processes = self._processes, None
            await asyncio.to_thread(processes.stop)
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._workers is not None:
            workers, self._workers = self._workers, None
            await asyncio.to_thread(workers.shutdown, True, cancel_futures=True)
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    async def __aenter__(self) -> LocalServer:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def base_url(self, api: str) -> str:
        """The `base_url` a `ModelEndpoint` of this API uses to reach this server."""
        return get_adapter(api).base_url_for(self.url)

    def endpoint_config(self, name: str, api: str, **fields: Any) -> dict[str, Any]:
        """A `models:` entry pointing at this server (extra fields are passed through)."""
        return {"name": name, "api": api, "base_url": self.base_url(api), **fields}

    @property
    def open_connections(self) -> int:
        """Client connections currently open to this server (served in this process only)."""
        if self.processes:
            raise RuntimeError("open_connections: known only with server_processes: 0")
        if self._runner is None or self._runner.server is None:
            return 0
        return len(self._runner.server.connections)

    async def _start_workers(self) -> None:
        """Start the policy worker processes (when asked and some policy is pure), each loading
        its policy's code once, before the first request."""
        n = policy_workers(self.config.policy_processes)
        pure = {s.policy for s in self._specs.values() if s and s.policy in PURE_REPLIES}
        if not n or not pure:
            return
        loop = asyncio.get_running_loop()
        self._workers = ProcessPoolExecutor(
            max_workers=n,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_policy_worker,
            initargs=(os.getpid(),),
        )
        with children_ignore_sigint():  # workers start on these first submissions
            loading = [
                loop.run_in_executor(self._workers, _load_pure, sorted(pure)) for _ in range(n)
            ]
        await asyncio.gather(*loading)

    # -- small routes ------------------------------------------------------------------------
    async def _models(self, request: web.Request) -> web.Response:
        traits = self.config.imitate
        if traits.served_model_name is not None:  # vLLM's card of the one model it serves
            name = traits.served_model_name
            card: dict[str, Any] = {"id": name, "object": "model", "owned_by": "vllm"}
            card |= {"root": name, "parent": None, "max_model_len": traits.max_model_len}
            return web.json_response({"object": "list", "data": [card]})
        names = ["vabench-local", *self.config.model_policies]
        data: list[dict[str, Any]] = [
            {"id": n, "object": "model", "owned_by": "vabench"} for n in names
        ]
        if traits.max_model_len is not None:
            data = [d | {"max_model_len": traits.max_model_len} for d in data]
        return web.json_response({"object": "list", "data": data})

    async def _health(self, request: web.Request) -> web.Response:
        return web.json_response({"ok": True})

    async def _stats(self, request: web.Request) -> web.Response:
        return web.json_response(
            {
                "requests": self._next_id,
                "counts": dict(self.counts),
                "open_connections": self.open_connections,
            }
        )

    # -- the API routes ----------------------------------------------------------------------
    def _handler(self, adapter: ApiAdapter):
        async def handle(request: web.Request) -> web.StreamResponse:
            loop = asyncio.get_running_loop()
            self._next_id += 1
            record = RequestRecord(self._next_id, adapter.name, loop.time(), self.process_index)
            self.log.append(record)
            try:
                response = await self._respond(request, adapter, record)
                record.status = response.status if record.fault != "drop" else None
                if not response.prepared:  # a truncated reply has sent its headers already
                    response.headers.update(adapter.response_headers())
                return response
            except asyncio.CancelledError:
                record.error = "client went away"
                raise
            finally:
                record.finished_s = loop.time()
                self._note(record, logged=True)

        return handle

    def _note(self, record: RequestRecord, logged: bool = False) -> None:
        """Count a finished request and append it to the JSONL log; `logged`: it is in `log`
        already (a request of a serving process is numbered and logged here when it ends)."""
        if not logged:
            self._next_id += 1
            record.id = self._next_id
            self.log.append(record)
        self.counts[f"status:{record.status}"] += 1
        if record.fault:
            self.counts[f"fault:{record.fault}"] += 1
        if self.on_record is not None:
            self.on_record(record)
        if self._log_file is not None:  # flushed: the log outlives a killed process
            self._log_file.write(json.dumps(dataclasses.asdict(record)) + "\n")
            self._log_file.flush()

    def _error(
        self, adapter: ApiAdapter, status: int, message: str, headers: dict[str, str] | None = None
    ) -> web.Response:
        return error_response(status, adapter.error_body(status, message), headers)

    async def _respond(
        self, request: web.Request, adapter: ApiAdapter, record: RequestRecord
    ) -> web.StreamResponse:
        raw = await request.read()
        record.body_bytes = len(raw)
        if self.bodies is not None:
            self.bodies.append((adapter.name, raw))
        key = self.config.api_key
        if key is not None and adapter.server_key(request.headers) != key.get_secret_value():
            record.error = "missing or wrong API key"
            return self._error(adapter, 401, "invalid API key")
        try:
            incoming = adapter.parse_request(raw, request.headers)
        except RequestShapeError as err:
            record.error = str(err)
            return self._error(adapter, 400, f"invalid request: {err}")
        record.model = incoming.model
        record.images = len(incoming.chat.images)

        counts = block_tokens(incoming.chat, adapter.image_tokens)
        options = incoming.chat.options
        max_output = options.resolved_max_output_tokens if options else DEFAULT_MAX_OUTPUT_TOKENS
        traits = self.config.imitate
        if traits.ignored_fields or traits.reasoning_model or traits.no_reasoning:
            fields = json.loads(raw)
            if traits.reasoning_model and (rejected := reasoning_refusal(fields)) is not None:
                record.error = "a parameter a reasoning model refuses"
                return rejected
            if traits.no_reasoning and (rejected := no_reasoning_refusal(fields)) is not None:
                record.error = "a reasoning option a model without reasoning refuses"
                return rejected
            if _limit_fields_ignored(fields, traits.ignored_fields):
                max_output = UNREAD_OUTPUT_LIMIT
        refused = vllm_refusal(
            incoming.model,
            traits.served_model_name,
            record.images,
            traits.max_images_per_prompt,
            sum(counts),
            max_output,
            traits.max_model_len,
        )
        if refused is not None:
            record.error = refused[1]
            return vllm_error(*refused)
        admitted, refusal = self._admit(adapter, sum(counts) + max_output)
        if refusal is not None:
            record.fault = "enforced_rate_limit"
            return refusal

        fault = self.faults.next()
        record.fault = fault
        if fault in IMMEDIATE_FAULTS:
            status = status_of(fault)
            headers = (
                retry_after_headers(self.config.faults.retry_after_s) if status == 429 else None
            )
            return self._error(adapter, status, f"injected fault: {fault}", headers)
        delay = (
            self.config.faults.slow_s if fault == "slow" else self.config.latency.sample(self._rng)
        )
        await asyncio.sleep(delay)
        if fault == "drop":
            return drop_connection(request)
        if fault == "server_error":
            return self._error(adapter, 500, "injected fault: server_error")

        try:
            reply = await self._reply(adapter, incoming, counts, max_output)
        except PolicyError as err:
            record.error = str(err)
            return self._error(adapter, err.status, str(err))
        record.input_tokens = reply.usage.prompt_tokens
        record.output_tokens = reply.usage.output_tokens
        if admitted is not None and self._tokens is not None:
            self._tokens.settle(admitted, reply.usage.total_tokens)
        body = reply.body if reply.body is not None else adapter.build_response(reply)
        if fault == "malformed":
            return malformed_response(body)
        if fault == "truncated":
            return await truncated_response(request, body)
        return web.json_response(body, headers=self._limit_headers(adapter))

    async def _reply(
        self, adapter: ApiAdapter, incoming: IncomingRequest, counts: list[int], max_output: int
    ) -> ServerReply:
        spec = self._specs.get(incoming.model, self._specs[None])
        if self._workers is not None and spec is not None and spec.policy in PURE_REPLIES:
            answer: str | PolicyReply = await asyncio.get_running_loop().run_in_executor(
                self._workers, pure_reply, spec.policy, spec.options, incoming
            )
        else:
            policy = self._model_policies.get(incoming.model, self.policy)
            answer = await policy.respond(incoming)
        reply = answer if isinstance(answer, PolicyReply) else PolicyReply(answer)
        usage, reasoning = simulate_usage(
            incoming, reply.text, counts, self.cache, adapter.prompt_caching
        )
        usage = truncated_usage(usage, self.config.imitate.num_ctx)
        text, finish = reply.text, reply.finish_reason
        if usage.output_tokens > max_output:  # cut the reply where max tokens would have
            reasoning_part = usage.output_tokens - text_tokens(text)
            text = text[: int(max(0, max_output - reasoning_part) * CHARS_PER_TOKEN)]
            usage = dataclasses.replace(usage, output_tokens=max_output)
            finish = "length"
        return ServerReply(
            text=text,
            finish_reason=finish,
            usage=usage,
            model=incoming.model,
            reasoning=reply.reasoning or reasoning,
            body=reply.body,
        )

    # -- rate limits -------------------------------------------------------------------------
    def _admit(self, adapter: ApiAdapter, tokens: int) -> tuple[Any, web.Response | None]:
        """Take one request and `tokens` from the windows, or a 429 saying how long to wait."""
        if self._requests is None and self._tokens is None:
            return None, None
        now = asyncio.get_running_loop().time()
        if self._tokens is not None and tokens > self._tokens.limit:
            message = f"a request of {tokens} tokens exceeds the limit of the whole period"
            return None, self._error(adapter, 429, message)
        waits = {
            name: budget.wait_time(amount, now)
            for name, budget, amount in (
                ("requests", self._requests, 1),
                ("tokens", self._tokens, tokens),
            )
            if budget is not None
        }
        wait = max(waits.values())
        if wait > 0:
            headers = self._limit_headers(adapter, waits)
            if self.config.retry_after_header:
                headers.update(retry_after_headers(wait))
            return None, self._error(adapter, 429, "rate limit exceeded", headers)
        if self._requests is not None:
            self._requests.take(1, now)
        entry = self._tokens.take(tokens, now) if self._tokens is not None else None
        return entry, None

    def _limit_headers(
        self, adapter: ApiAdapter, waits: dict[str, float] | None = None
    ) -> dict[str, str]:
        """The API's rate-limit headers; a limit with a pending wait reports 0 remaining and
        that wait as its reset, so the client can tell which limit ran out."""
        now = asyncio.get_running_loop().time()
        states: dict[str, LimitState] = {}
        for name, budget in (("requests", self._requests), ("tokens", self._tokens)):
            if budget is None:
                continue
            left, reset = budget.remaining(now)
            wait = (waits or {}).get(name, 0.0)
            limit = int(budget.limit)
            states[name] = (
                LimitState(limit, 0, wait) if wait > 0 else LimitState(limit, int(left), reset)
            )
        return adapter.rate_limit_headers(states)


UNREAD_OUTPUT_LIMIT = 1 << 30
"""The output limit of a request whose limit field the server does not read: none at all
(llama.cpp's `n_predict` -1: the reply runs to its end)."""


def _limit_fields_ignored(body: dict[str, Any], ignored: Sequence[str]) -> bool:
    """Whether every output-limit field the body sets is one the server does not read."""
    given = [f for f in ("max_completion_tokens", "max_tokens") if body.get(f) is not None]
    return bool(given) and all(f in ignored for f in given)


def _init_policy_worker(parent_pid: int) -> None:
    ignore_sigint()  # the server's process ends its workers (vabench.children)
    exit_with_parent(parent_pid)


def _load_pure(policies: list[str]) -> None:
    """Import the pure policies' code in a worker before its first request."""
    for name in policies:
        pure_function(name)


async def _serve_in_process(
    config: ServerConfig, index: int, host: str, port: int, records: Any, stop: Any
) -> None:
    """The server in one serving process (`ServingProcesses` runs it there): it shares the
    port, puts each finished request's record on `records` and READY once it listens, and stops
    when `stop` is set. Passed to the processes rather than imported by them: this module
    starts them."""
    server = LocalServer(config)
    server.process_index = index
    server.on_record = records.put
    await server.start(host, port, reuse_port=True)
    records.put(READY)
    try:
        await asyncio.to_thread(stop.wait)
    finally:
        await server.stop()
