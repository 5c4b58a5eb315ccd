"""What an endpoint's answers to the check mean: one `Line` per item, a fix on each problem.

Pure functions of what came back (a status and message, a usage, a model card), so each
server's habit is read in one place: vLLM's image-limit and context-length 400s, an
unknown key or model however a server or gateway words it, an output-limit field a server
rejects (reasoning models: `max_tokens`, `temperature`) or does not read (llama.cpp's
`max_completion_tokens`), a prompt counted far below what it holds (Ollama's `num_ctx`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vabench.agent.conversation import ContextLimits
from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.config import ModelEndpoint

ITEMS = (
    "reachable",
    "key",
    "model name",
    "images",
    "context",
    "prompt tokens",
    "output limit",
    "reasoning",
    "latency",
    "cost",
)
"""The items of a model's report, in the order they are printed."""

OUTPUT_PROBE_TOKENS = 16
"""The output limit of the probe that sees whether the server reads the limit's field."""


@dataclass(frozen=True)
class Line:
    """One item of one model's report; `fix` set: a problem, and what to do about it."""

    model: str
    item: str
    text: str
    fix: str | None = None
    value: float | None = None
    """The item's measured number where it has one (the latency's seconds)."""

    @property
    def problem(self) -> bool:
        return self.fix is not None

    def row(self) -> str:
        """The line in the model's report."""
        return f"  {self.item:<14}{'PROBLEM: ' if self.problem else ''}{self.text}"

    def problem_line(self) -> str:
        """The one line that names the problem and its fix."""
        return f"model {self.model!r}: {self.item}: {self.text}; fix: {self.fix}"


@dataclass(frozen=True)
class Where:
    """The model a line is about, and how to name its config fields."""

    endpoint: ModelEndpoint
    index: int

    @property
    def field(self) -> str:
        return f"models[{self.index}]"

    @property
    def name(self) -> str:
        return self.endpoint.name


_IMAGES = re.compile(r"image\(s\) may be provided|limit[-_]mm[-_]per[-_]prompt|too many images")
_CONTEXT = re.compile(
    r"maximum context length|context[ _]length|context window|prompt is too long"
    r"|exceeds? the (?:model's )?(?:maximum|context)|too many (?:input )?tokens"
)
_NO_MAX_TOKENS = re.compile(r"'?max_tokens'? is not supported|use 'max_completion_tokens'")
_NO_COMPLETION_FIELD = re.compile(
    r"max_completion_tokens.{0,40}(?:not supported|unrecognized|unknown|extra)"
    r"|(?:unrecognized|unknown|extra).{0,40}max_completion_tokens"
)
_REASONING = re.compile(
    r"(?:reasoning_effort|reasoning\.effort|'reasoning'|thinking).{0,60}"
    r"(?:not support|unsupported|unrecognized|unknown|not permitted|extra)"
    r"|(?:unrecognized|unsupported|unknown|extra).{0,60}(?:reasoning_effort|reasoning|thinking)"
)
_TEMPERATURE = re.compile(r"'?temperature'?.{0,60}(?:not support|unsupported|only the default)")
_KEY = re.compile(
    r"api[ _-]?key|unauthori[sz]ed|authenticat|invalid (?:access |auth |bearer )?token"
    r"|no connected db|permission denied"
)
_MODEL = re.compile(
    r"model.{0,80}(?:does not exist|not found|unknown|not served)|unknown model|no such model"
    r"|model_not_found|invalid model"
)


def server_message(message: str) -> str:
    """The server's own words from a failure line (`HTTP 400: {...}`), quoted short."""
    found = re.search(r'"message"\s*:\s*"((?:[^"\\]|\\.)*)"', message)
    # a body that is no JSON error: the line's own words, without its "HTTP 400: " (the
    # problem line names the status itself)
    text = found.group(1) if found else re.sub(r"^HTTP \d{3}:\s*", "", message.strip())
    return text if len(text) <= 200 else text[:197] + "..."


def rejection(where: Where, status: int, message: str, images: int, images_why: str) -> Line:
    """The problem a refused check request shows: which item, and its fix."""
    said = server_message(message)
    low = said.lower()
    ep, field = where.endpoint, where.field
    quoted = f'HTTP {status} "{said}"'
    if _IMAGES.search(low):
        return Line(
            where.name,
            "images",
            f"{images} images in one request refused ({quoted}); {images_why} carries that many",
            f"start vLLM with --limit-mm-per-prompt '{{\"image\": {images}}}' (image={images} "
            "before vLLM 0.10); other servers: raise their image limit per request",
        )
    if _CONTEXT.search(low):
        return Line(
            where.name,
            "context",
            f"the first step's request is longer than the server's context ({quoted})",
            f"give the server a longer context (vLLM --max-model-len, llama.cpp -c, Ollama "
            f"OLLAMA_CONTEXT_LENGTH) of at least {context_need(ep):,} tokens",
        )
    if _NO_MAX_TOKENS.search(low):
        return Line(
            where.name,
            "output limit",
            f"the server refuses max_tokens ({quoted})",
            f"set {field}.max_tokens_field: max_completion_tokens (reasoning models take "
            "only that field)",
        )
    if _NO_COMPLETION_FIELD.search(low):
        return Line(
            where.name,
            "output limit",
            f"the server refuses max_completion_tokens ({quoted})",
            f"set {field}.max_tokens_field: max_tokens",
        )
    if _REASONING.search(low):
        option = get_adapter(ep.api).reasoning_option
        return Line(
            where.name,
            "reasoning",
            f"the server refuses the benchmark's reasoning option ({quoted})",
            f"set {field}.generation.{option}: off (the model is then run without it, and "
            "the report says so)",
        )
    if _TEMPERATURE.search(low):
        return Line(
            where.name,
            "output limit",
            f"the server refuses the temperature ({quoted})",
            f"remove {field}.generation.temperature (reasoning models take only the default)",
        )
    if status in (401, 403) or _KEY.search(low):
        fix = (
            f"check the key in {ep.api_key_env} ({field}.api_key_env)"
            if ep.api_key_env
            else f"the endpoint wants a key: set {field}.api_key_env to the variable holding it"
        )
        return Line(where.name, "key", f"refused ({quoted})", fix)
    if status == 404 or _MODEL.search(low):
        return Line(
            where.name,
            "model name",
            f"{ep.provider_model!r} refused ({quoted})",
            f"check {field}.model (or its name) against the models the server lists at "
            f"{ep.resolved_base_url}/models",
        )
    return Line(
        where.name,
        "reachable",
        f"the request was refused ({quoted})",
        f"read the server's message: {field}.generation and max_tokens_field set what is sent",
    )


def context_window(endpoint: ModelEndpoint) -> int:
    """The context the sweep's conversations assume for `endpoint` (its `context_window`
    where the config sets one)."""
    window = getattr(endpoint, "context_window", None)
    return int(window) if window else ContextLimits().window_tokens


def context_need(endpoint: ModelEndpoint) -> int:
    """The most tokens an episode's request may hold: the conversation compacts above a share
    of the window (`ContextLimits.compact_above`), so a request reaches that plus its output."""
    limits = ContextLimits(window_tokens=context_window(endpoint))
    return limits.compact_above + endpoint.generation.resolved_max_output_tokens


def context_line(where: Where, max_model_len: int | None) -> Line:
    """The server's context (its `/v1/models` card's `max_model_len`) against the plan's need."""
    need = context_need(where.endpoint)
    if max_model_len is None:
        return Line(where.name, "context", "not reported (no max_model_len in /v1/models)")
    if max_model_len >= need:
        return Line(
            where.name,
            "context",
            f"{max_model_len:,} tokens (max_model_len) hold the {need:,} an episode may reach",
        )
    window = context_window(where.endpoint)
    return Line(
        where.name,
        "context",
        f"the server holds {max_model_len:,} tokens (max_model_len); an episode may reach "
        f"{need:,} (the conversation compacts near the {window:,}-token window it assumes)",
        f"set {where.field}.context_window: {max_model_len} (the conversation then compacts "
        f"within it), or start vLLM with --max-model-len of at least {need}",
    )


def context_probe_line(where: Where, reported: int, least: int) -> Line:
    """The context probe's count (a server that reports no context): a text prompt of at
    least `least` tokens counted far lower was cut, and an episode's later requests would be
    cut the same way, without an error."""
    need = context_need(where.endpoint)
    if reported <= 0:
        return Line(
            where.name, "context", "not reported (no max_model_len; the reply has no usage)"
        )
    if reported >= least:
        held = "" if least >= need else f" of the {need:,} an episode may reach"
        return Line(
            where.name,
            "context",
            f"not reported (no max_model_len); a prompt of {least:,}+ tokens{held} was counted "
            f"whole ({reported:,})",
        )
    return Line(
        where.name,
        "context",
        f"a text prompt of at least {least:,} tokens was counted as {reported:,}: the server "
        f"cuts prompts near {reported:,} tokens without an error, and an episode's requests "
        f"reach {need:,}",
        f"give the server a context of at least {need:,} tokens: Ollama cuts prompts to its "
        "num_ctx and its OpenAI endpoint ignores one in the request: start it with "
        f"OLLAMA_CONTEXT_LENGTH={need} (or PARAMETER num_ctx in a Modelfile); llama.cpp: -c "
        f"{need}; or set {where.field}.context_window below what it holds",
    )


def prompt_tokens_line(where: Where, reported: int, estimate: int, least: int) -> Line:
    """The prompt tokens the server counted against ours: far fewer than the request holds
    means the server cut it."""
    if reported <= 0:
        return Line(where.name, "prompt tokens", "not reported (the reply has no usage)")
    counted = f"{reported:,} counted, {estimate:,} estimated"
    if reported >= least:
        return Line(where.name, "prompt tokens", counted)
    return Line(
        where.name,
        "prompt tokens",
        f"{counted}: the request holds at least {least:,}, so the server cut the prompt",
        "give the server a context that holds the request: Ollama cuts prompts to its num_ctx "
        "(2,048-4,096 tokens unless set) without an error, and its OpenAI endpoint ignores a "
        "num_ctx in the request: start it with OLLAMA_CONTEXT_LENGTH=65536 (or PARAMETER "
        "num_ctx in a Modelfile); llama.cpp: -c",
    )


def output_limit_line(where: Where, output_tokens: int, finish: str) -> Line:
    """The probe's output against its limit: more means the limit's field went unread."""
    ep = where.endpoint
    sent = ep.max_tokens_field
    if output_tokens <= 0:
        return Line(where.name, "output limit", f"{sent} sent; the reply reports no usage")
    if output_tokens <= OUTPUT_PROBE_TOKENS:
        return Line(
            where.name,
            "output limit",
            f"{sent} read ({output_tokens} tokens for a limit of {OUTPUT_PROBE_TOKENS}, {finish})",
        )
    other = "max_tokens" if sent == "max_completion_tokens" else "max_completion_tokens"
    return Line(
        where.name,
        "output limit",
        f"{output_tokens} tokens for a limit of {OUTPUT_PROBE_TOKENS} in {sent}: the server "
        "does not read that field, so replies run to the server's own limit",
        f"set {where.field}.max_tokens_field: {other} (llama.cpp's server read only max_tokens "
        "until it took max_completion_tokens)",
    )


def reasoning_line(where: Where, reasoning: str | None, text: str) -> Line:
    """Whether thinking came apart from the answer (informational)."""
    if reasoning:
        return Line(
            where.name, "reasoning", f"returned apart from the answer ({len(reasoning):,} chars)"
        )
    if "</think>" in text:
        return Line(
            where.name,
            "reasoning",
            "inside the answer's text (<think> ... </think>): vLLM and SGLang return it apart "
            "when started with --reasoning-parser",
        )
    return Line(where.name, "reasoning", "none returned")
