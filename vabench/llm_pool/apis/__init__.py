"""The model APIs vabench speaks, one module per API, and their registry (`base` holds the
contract and the steps they share, `openai_common` what the two OpenAI APIs share).

`ADAPTERS` is the one place an API is registered; everything else that differs per API is
derived from it: the config schema's `ApiName`, default base URLs and option checks
(`config.py`), the embedded server's routes (`server.py`) and its prompt-cache simulation
(`simulate.py`), and the dry-run's cost estimate (`sweep/plan.py`). docs/LLM_POOL.md, "Adding
a model API", says how to add one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

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

if TYPE_CHECKING:  # a type checker cannot read a Literal built at run time
    ApiName = str
else:
    ApiName = Literal[tuple(ADAPTERS)]
"""The name of a registered API: the type of `ModelEndpoint.api`, so that a config naming
another fails validation with the list of valid names."""


def get_adapter(api: str) -> ApiAdapter:
    try:
        return ADAPTERS[api]
    except KeyError:
        raise KeyError(f"unknown api {api!r}; valid apis: {sorted(ADAPTERS)}") from None


__all__ = [
    "ADAPTERS",
    "ApiAdapter",
    "ApiName",
    "IncomingRequest",
    "LimitState",
    "RequestShapeError",
    "ServerReply",
    "get_adapter",
]
