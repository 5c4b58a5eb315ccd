"""The LLM pool: concurrent, rate-limit-aware clients for OpenAI Chat Completions, OpenAI
Responses and Anthropic Messages, and an embedded server speaking the same APIs.

    from vabench.llm_pool import ChatRequest, Image, LLMPool, Turn

    async with LLMPool(endpoints) as pool:  # endpoints: `models:` entries of a sweep
        result = await pool.complete("gpt-x", ChatRequest(
            system="You control a robot...",
            turns=[Turn.user("Step 1/50 ...", Image(jpeg_bytes))],
        ))
        result.text, result.usage, result.cost_usd

The embedded server lives in `vabench.llm_pool.server` (`python -m vabench.llm_pool.serve`);
it is not imported here so that the client side stays light. Nothing here imports JAX.
See docs/LLM_POOL.md.
"""

from vabench.llm_pool.config import (
    ConfigError,
    GenerationOptions,
    Limits,
    ModelEndpoint,
    Prices,
    RetryPolicy,
    load_endpoint,
    load_endpoints,
)
from vabench.llm_pool.errors import (
    InfrastructureError,
    LLMError,
    RequestRejected,
    ResponseFormatError,
)
from vabench.llm_pool.messages import ChatRequest, CompletionResult, Image, Turn, Usage
from vabench.llm_pool.pool import EndpointClient, EndpointStats, LLMPool

__all__ = [
    "ChatRequest",
    "CompletionResult",
    "ConfigError",
    "EndpointClient",
    "EndpointStats",
    "GenerationOptions",
    "Image",
    "InfrastructureError",
    "LLMError",
    "LLMPool",
    "Limits",
    "ModelEndpoint",
    "Prices",
    "RequestRejected",
    "ResponseFormatError",
    "RetryPolicy",
    "Turn",
    "Usage",
    "load_endpoint",
    "load_endpoints",
]
