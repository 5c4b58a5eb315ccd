"""Provider API adapters, one module per API, registered by their config name (`base` holds
the steps they share, `openai_common` what the two OpenAI APIs share)."""

from __future__ import annotations

from vabench.llm_pool.apis.anthropic import Anthropic
from vabench.llm_pool.apis.base import (
    ApiAdapter,
    IncomingRequest,
    LimitState,
    RequestShapeError,
    ServerReply,
)
from vabench.llm_pool.apis.openai_chat import OpenAIChat
from vabench.llm_pool.apis.openai_responses import OpenAIResponses

ADAPTERS: dict[str, ApiAdapter] = {
    a.name: a for a in (OpenAIChat(), OpenAIResponses(), Anthropic())
}


def get_adapter(api: str) -> ApiAdapter:
    try:
        return ADAPTERS[api]
    except KeyError:
        raise KeyError(f"unknown api {api!r}; valid apis: {sorted(ADAPTERS)}") from None


__all__ = [
    "ADAPTERS",
    "ApiAdapter",
    "IncomingRequest",
    "LimitState",
    "RequestShapeError",
    "ServerReply",
    "get_adapter",
]
