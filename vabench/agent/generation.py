"""The benchmark's API defaults, under the user's settings: `reasoning_effort: medium` on the
OpenAI APIs (Chat Completions and Responses), Anthropic extended thinking with a 1,024-token
budget (spec PROTOCOL_FACTS.md 7: the reference harness sends them on every call).

A request's options override its endpoint's (`GenerationOptions.merge`), so the harness sends
a default only for a field the model's config leaves unset: whatever a user writes in the
model's `generation` wins, and the run directory's plan records it (docs/PROTOCOL.md). The
thinking budget is not defaulted where the model's output limit leaves no room for it.
"""

from __future__ import annotations

from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.config import ModelEndpoint
from vabench.llm_pool.settings import GenerationOptions, ReasoningEffort

REASONING_EFFORT: ReasoningEffort = "medium"
THINKING_BUDGET = 1024


def protocol_defaults(endpoint: ModelEndpoint) -> GenerationOptions:
    """The defaults `endpoint`'s config leaves unset (empty options where it sets them all)."""
    own = endpoint.generation
    option = get_adapter(endpoint.api).reasoning_option
    if option == "reasoning_effort" and own.reasoning_effort is None:
        return GenerationOptions(reasoning_effort=REASONING_EFFORT)
    if (
        option == "thinking_budget"
        and own.thinking_budget is None
        and own.resolved_max_output_tokens > THINKING_BUDGET
    ):
        return GenerationOptions(thinking_budget=THINKING_BUDGET)
    return GenerationOptions()


def request_options(
    endpoint: ModelEndpoint, harness: GenerationOptions | None
) -> GenerationOptions:
    """The options the harness sends with each request to `endpoint`: the protocol's defaults
    for what the model's config leaves unset, then the harness's own (`EngineSettings`)."""
    return protocol_defaults(endpoint).merge(harness)
