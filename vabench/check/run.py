"""The check of a sweep's models: per model, its card, one real decision and an output probe.

Models run side by side. A model of the embedded server is not called: the sweep starts that
server itself, with none of the limits the check looks for. Every other model gets:

1. its card from `GET /v1/models` where the server lists one (vLLM's `max_model_len`);
2. one decision, the heaviest request of the sweep (`inputs.probe`), through the pool as an
   episode's would go (its key, headers, options, at most 3 attempts);
3. on Chat Completions, a text-only probe whose output limit is `judge.OUTPUT_PROBE_TOKENS`:
   a reply longer than that says the server does not read the limit's field;
4. where the server reports no context (no `max_model_len`), the model has no prices and the
   decision's prompt was counted whole, a long text-only prompt (`inputs.context_probe`): a
   server that cuts prompts without an error (Ollama's num_ctx) cuts it too, though the
   first step's request fit.

The answers become `judge.Line`s, ten items a model, a fix on every problem.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import aiohttp

from vabench.agent.generation import request_options
from vabench.check import judge, latency
from vabench.check.inputs import CONTEXT_PROBE_TOKENS, Probe, context_probe, probe
from vabench.check.judge import Line, Where
from vabench.config import SweepConfig
from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.config import GenerationOptions, ModelEndpoint
from vabench.llm_pool.errors import EndpointUnreachable, InfrastructureError, RequestRejected
from vabench.llm_pool.messages import ChatRequest, CompletionResult, Turn
from vabench.llm_pool.pool import LLMPool

CHECK_ATTEMPTS = 3
"""Attempts of each check call: a transient failure is retried, a sick endpoint found fast."""
CARD_TIMEOUT_S = 10.0
PROBE_PROMPT = "Count from 1 to 100 in words, separated by commas."


def models_url(endpoint: ModelEndpoint) -> str:
    """Where the endpoint's API lists its models (`/v1/models` beside its route)."""
    route = get_adapter(endpoint.api).url(endpoint.resolved_base_url)
    return route[: route.rfind("/v1/")] + "/v1/models"


async def model_card(endpoint: ModelEndpoint, key: str | None) -> dict[str, Any] | None:
    """The server's card of this model (`/v1/models` entry of its id), or None when it lists
    none (no such route, another model, no answer: the decision call says why)."""
    headers = {**endpoint.headers, **get_adapter(endpoint.api).headers(key)}
    timeout = aiohttp.ClientTimeout(total=CARD_TIMEOUT_S)
    try:
        async with (
            aiohttp.ClientSession(timeout=timeout) as session,
            session.get(models_url(endpoint), headers=headers) as resp,
        ):
            if resp.status != 200:
                return None
            body = await resp.json(content_type=None)
    except (aiohttp.ClientError, asyncio.TimeoutError, ValueError):
        return None
    data = body.get("data") if isinstance(body, dict) else None
    for card in data if isinstance(data, list) else []:
        if isinstance(card, dict) and card.get("id") == endpoint.provider_model:
            return card
    return None


def _for_the_check(endpoint: ModelEndpoint) -> ModelEndpoint:
    attempts = min(CHECK_ATTEMPTS, endpoint.retry.max_attempts)
    retry = endpoint.retry.model_copy(update={"max_attempts": attempts})
    return endpoint.model_copy(update={"retry": retry})


async def check_model(where: Where, request: Probe, environ: Mapping[str, str]) -> list[Line]:
    """The report of one (not embedded) model."""
    ep, name = where.endpoint, where.name
    if ep.api_key_env is not None and not environ.get(ep.api_key_env):
        return [
            Line(
                name,
                "key",
                f"environment variable {ep.api_key_env} is not set",
                f"export {ep.api_key_env} or put it in the .env file beside the config",
            )
        ]
    card = await model_card(ep, environ.get(ep.api_key_env) if ep.api_key_env else None)
    async with LLMPool([_for_the_check(ep)], environ=environ) as pool:
        try:
            # with the options an episode's requests carry (the benchmark's API defaults):
            # a server that refuses one is found here, not in every episode
            sent = dataclasses.replace(request.request, options=request_options(ep, None))
            result = await pool.complete(name, sent)
        except EndpointUnreachable as err:
            fix = err.hint or f"start the server at {ep.resolved_base_url} ({where.field}.base_url)"
            return [Line(name, "reachable", f"no ({err.message})", fix)]
        except InfrastructureError as err:
            return [
                Line(
                    name,
                    "reachable",
                    f"no answer in {err.attempts} attempts ({judge.server_message(err.message)})",
                    "check that the server is up and not overloaded (its log says why)",
                )
            ]
        except RequestRejected as err:
            refused = judge.rejection(
                where, err.status, err.message, request.images, request.images_why
            )
            probed = [p for p in await _output_probe(pool, where) if p.item != refused.item]
            return [Line(name, "reachable", f"yes (HTTP {err.status})"), refused, *probed]
        lines = _decision_lines(where, request, result, card)
        if _wants_context_probe(where, card, lines):
            lines = [line for line in lines if line.item != "context"]
            lines.append(await _context_probe(pool, where))
        lines += await _output_probe(pool, where)
        lines.append(_cost_line(where, result))
    return sorted(lines, key=lambda line: judge.ITEMS.index(line.item))


def _decision_lines(
    where: Where, request: Probe, result: CompletionResult, card: dict[str, Any] | None
) -> list[Line]:
    ep, name = where.endpoint, where.name
    max_len = card.get("max_model_len") if card is not None else None
    retried = f" after {result.attempts} attempts" if result.attempts > 1 else ""
    renamed = result.model and result.model != ep.provider_model
    alias = f" as {result.model!r}" if renamed else ""
    return [
        Line(name, "reachable", f"yes ({ep.resolved_base_url}{retried})"),
        Line(name, "key", f"accepted ({ep.api_key_env})" if ep.api_key_env else "none needed"),
        Line(name, "model name", f"{ep.provider_model!r} served{alias}"),
        Line(
            name,
            "images",
            f"{request.images} in one request accepted, as {request.images_why} carries; "
            f"the prompt of {request.where}",
        ),
        judge.context_line(where, max_len if isinstance(max_len, int) else None),
        judge.prompt_tokens_line(
            where, result.usage.prompt_tokens, request.estimate(ep.api), request.least_tokens
        ),
        judge.reasoning_line(where, result.reasoning, result.text),
        Line(name, "latency", f"{result.latency_s:.2f} s for one decision", value=result.latency_s),
    ]


def _wants_context_probe(where: Where, card: dict[str, Any] | None, lines: list[Line]) -> bool:
    """A context the server does not report, on an endpoint without prices (a paid provider
    states its window, and the probe's long prompt costs there), where the first step's prompt
    was not already found cut."""
    reported = card is not None and isinstance(card.get("max_model_len"), int)
    cut = any(line.problem for line in lines if line.item == "prompt tokens")
    return not reported and where.endpoint.prices is None and not cut


async def _context_probe(pool: LLMPool, where: Where) -> Line:
    least = min(CONTEXT_PROBE_TOKENS, judge.context_need(where.endpoint))
    request, floor = context_probe(least)
    try:
        result = await pool.complete(where.name, request)
    except RequestRejected as err:
        line = judge.rejection(where, err.status, err.message, 0, "")
        return line if line.item == "context" else Line(where.name, "context", "not reported")
    except InfrastructureError:
        return Line(where.name, "context", "not reported (no max_model_len; the probe failed)")
    return judge.context_probe_line(where, result.usage.prompt_tokens, floor)


async def _output_probe(pool: LLMPool, where: Where) -> list[Line]:
    """Chat Completions only: whether the server reads the output limit's field (the other
    APIs have one field, which their servers read)."""
    if not get_adapter(where.endpoint.api).output_field_choice:
        return []
    options = GenerationOptions(max_output_tokens=judge.OUTPUT_PROBE_TOKENS)
    request = ChatRequest(turns=(Turn.user(PROBE_PROMPT),), options=options)
    try:
        result = await pool.complete(where.name, request)
    except RequestRejected as err:
        line = judge.rejection(where, err.status, err.message, 0, "")
        return [line] if line.item == "output limit" else []
    except InfrastructureError:
        return []  # the decision's line says how the endpoint fares
    return [judge.output_limit_line(where, result.usage.output_tokens, result.finish_reason)]


def _cost_line(where: Where, result: CompletionResult) -> Line:
    if where.endpoint.prices is None:
        return Line(where.name, "cost", f"price not set ({where.field}.prices)")
    return Line(where.name, "cost", f"${result.cost_usd:.4f} for one decision")


def selected(config: SweepConfig, models: Sequence[str] | None) -> list[Where]:
    """The models to check (`models` names, default every one), with their config index."""
    names = [m.name for m in config.models]
    unknown = [m for m in models or () if m not in names]
    if unknown:
        raise ValueError(f"--model {unknown[0]!r}: not a model of the config; models: {names}")
    return [Where(m, i) for i, m in enumerate(config.models) if models is None or m.name in models]


async def check_config(
    config: SweepConfig, environ: Mapping[str, str], models: Sequence[str] | None = None
) -> dict[str, list[Line]]:
    """Every selected model's report, by name, in config order."""
    wheres = selected(config, models)
    embedded = set(config.embedded_models)

    async def one(where: Where) -> list[Line]:
        if where.name in embedded:
            return [Line(where.name, "reachable", "the embedded server: nothing to check")]
        request = await asyncio.to_thread(probe, config, where.name)
        lines = await check_model(where, request, environ)
        timed = [line.value for line in lines if line.item == "latency" and line.value]
        if timed and not any(line.problem for line in lines):
            latency.keep(latency.api_kind(config, where.name), timed[0])  # the dry run's pace
        return lines

    reports = await asyncio.gather(*(one(w) for w in wheres))
    return {w.name: lines for w, lines in zip(wheres, reports, strict=True)}
