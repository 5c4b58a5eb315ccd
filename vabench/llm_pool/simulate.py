"""What the embedded server simulates besides the reply: latency, usage and prompt caching.

Usage is counted with the same estimator the client uses for its TPM limiter
(`tokens.block_tokens`), so a client that settles to the reported usage and a server that
enforces TPM agree on every number. Prompt caching follows the provider's rule (the API's
`ApiAdapter.prompt_caching`) closely enough to exercise the accounting:

- "automatic" (OpenAI): a prompt prefix that ends at a turn boundary, was seen before and is
  at least 1,024 tokens long is read from the cache, in 128-token increments.
- "explicit" (Anthropic): only prefixes ending at a `cache_control` marker are cached; the
  longest one seen before is read, and the prefix up to the last marker, if new, is written.

A server with a small context that cuts prompts without a word (Ollama's `num_ctx`) reports
the cut prompt's tokens (`truncated_usage`).
"""

from __future__ import annotations

import math
import random
from collections import OrderedDict
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from vabench.llm_pool.apis.base import IncomingRequest, PromptCaching
from vabench.llm_pool.messages import Usage
from vabench.llm_pool.tokens import text_tokens

MIN_CACHED_PREFIX = 1024
OPENAI_CACHE_INCREMENT = 128
REASONING_TOKENS = {"none": 0, "minimal": 16, "low": 64, "medium": 256, "high": 1024}
THINKING_TOKENS = 256  # simulated thinking per Anthropic call, capped by the budget


class LatencyModel(BaseModel):
    """Seconds from a request's arrival to its reply (before any injected fault)."""

    model_config = ConfigDict(extra="forbid")
    mean_s: float = Field(default=0.0, ge=0)
    dist: Literal["fixed", "uniform", "exponential", "lognormal"] = "fixed"
    spread: float = Field(default=0.0, ge=0)
    """uniform: +- spread * mean; lognormal: sigma of the log; ignored otherwise."""

    def sample(self, rng: random.Random) -> float:
        if self.mean_s == 0:
            return 0.0
        if self.dist == "uniform":
            return max(
                0.0, rng.uniform(self.mean_s * (1 - self.spread), self.mean_s * (1 + self.spread))
            )
        if self.dist == "exponential":
            return rng.expovariate(1 / self.mean_s)
        if self.dist == "lognormal":  # mean preserved: mu = ln(mean) - sigma^2 / 2
            sigma = self.spread
            return rng.lognormvariate(math.log(self.mean_s) - sigma * sigma / 2, sigma)
        return self.mean_s


class PromptCache:
    """Prefix hashes a provider would hold in its prompt cache (least recently used evicted)."""

    def __init__(self, max_entries: int = 100_000):
        self.max_entries = max_entries
        self._entries: OrderedDict[int, None] = OrderedDict()

    def _seen(self, key: int) -> bool:
        if key in self._entries:
            self._entries.move_to_end(key)
            return True
        return False

    def _store(self, key: int) -> None:
        self._entries[key] = None
        self._entries.move_to_end(key)
        while len(self._entries) > self.max_entries:
            self._entries.popitem(last=False)

    def split(
        self, request: IncomingRequest, counts: list[int], caching: PromptCaching
    ) -> tuple[int, int]:
        """(cache-read tokens, cache-write tokens) of a request's prompt."""
        blocks = request.chat.blocks
        ends = self._candidate_ends(request, caching)
        if not ends:
            return 0, 0
        prefix_tokens = _prefix_sums(counts)
        # Providers keep caches per model (and we per API, which share no cache either).
        digests = _prefix_digests(f"{request.api}/{request.model}", blocks, ends)
        read = 0
        for end in reversed(ends):
            if prefix_tokens[end] >= MIN_CACHED_PREFIX and self._seen(digests[end]):
                read = prefix_tokens[end]
                break
        write = 0
        if caching == "explicit":
            last = ends[-1]
            if prefix_tokens[last] >= MIN_CACHED_PREFIX and prefix_tokens[last] > read:
                write = prefix_tokens[last] - read
        else:
            read = read // OPENAI_CACHE_INCREMENT * OPENAI_CACHE_INCREMENT
        for end in ends:
            if prefix_tokens[end] >= MIN_CACHED_PREFIX:
                self._store(digests[end])
        return read, write

    @staticmethod
    def _candidate_ends(request: IncomingRequest, caching: PromptCaching) -> list[int]:
        """Block indexes where a cacheable prefix may end."""
        if caching == "explicit":
            return sorted(set(request.cache_breakpoints))
        ends, index = [], 0
        if request.chat.system:
            ends.append(0)
            index = 1
        for turn in request.chat.turns:
            index += len(turn.content)
            ends.append(index - 1)
        return ends


def _prefix_sums(counts: list[int]) -> list[int]:
    sums, total = [], 0
    for c in counts:
        total += c
        sums.append(total)
    return sums


def _prefix_digests(scope: str, blocks: list, ends: list[int]) -> dict[int, int]:
    """A chained hash per prefix. Python's own string hash (64-bit SipHash, randomised per
    process, which suits a cache that lives in one process) is several times faster than
    hashlib over the half-megabyte of base64 a request carries."""
    digest = hash(scope)
    wanted = set(ends)
    digests: dict[int, int] = {}
    for i, block in enumerate(blocks[: max(ends) + 1]):
        digest = hash((digest, block if isinstance(block, str) else block.b64))
        if i in wanted:
            digests[i] = digest
    return digests


def simulate_usage(
    request: IncomingRequest,
    reply_text: str,
    counts: list[int],
    cache: PromptCache | None,
    caching: PromptCaching,
) -> tuple[Usage, str | None]:
    """The usage a provider would report for `reply_text`, and simulated reasoning text;
    `counts` are the request's `tokens.block_tokens` under the API's image rule, `caching`
    its API's prompt caching. Reasoning tokens are None unless reasoning was asked for (an
    adapter writes them as its API does: OpenAI's as 0, Anthropic's not at all)."""
    prompt = sum(counts)
    read, write = cache.split(request, counts, caching) if cache is not None else (0, 0)
    options = request.chat.options
    reasoning_tokens: int | None = None
    reasoning_text: str | None = None
    if options is not None and options.sent_reasoning_effort is not None:
        reasoning_tokens = REASONING_TOKENS[options.sent_reasoning_effort]
    if options is not None and options.sent_thinking_budget is not None:
        thinking = min(options.sent_thinking_budget, THINKING_TOKENS)
        reasoning_text = "thinking " * (thinking // 2)  # ~2 tokens per word of it
        reasoning_tokens = thinking
    output = text_tokens(reply_text) + (reasoning_tokens or 0)
    usage = Usage(
        input_tokens=prompt - read - write,
        cached_input_tokens=read,
        cache_write_tokens=write,
        output_tokens=output,
        reasoning_tokens=reasoning_tokens,
    )
    return usage, reasoning_text


def truncated_usage(usage: Usage, num_ctx: int | None) -> Usage:
    """`usage` as a server that keeps only `num_ctx` tokens of a prompt reports it: the prompt
    counted at most `num_ctx` (Ollama's `prompt_eval_count` after its "truncating input
    prompt"), the cached share first."""
    if num_ctx is None or usage.prompt_tokens <= num_ctx:
        return usage
    cached = min(usage.cached_input_tokens, num_ctx)
    return Usage(
        input_tokens=num_ctx - cached,
        cached_input_tokens=cached,
        output_tokens=usage.output_tokens,
        reasoning_tokens=usage.reasoning_tokens,
    )
