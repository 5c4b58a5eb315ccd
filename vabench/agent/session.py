"""What an evaluation episode and a learning session share: how one ends, what its model calls
cost, and how a model reply is logged.

Both are conversations with a model under budgets (`vabench.agent.engine`,
`vabench.agent.learning`); both end by raising `SessionEnd` from inside their loop, count every
model call in a `Spend` (summaries of a compaction included) and log each reply with the same
fields (`reply_fields`), so the report and the bill read them the same way.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from vabench.agent.records import TokenTotals
from vabench.llm_pool.messages import CompletionResult, Usage


class SessionEnd(Exception):
    """Ends a session from inside its loop: the result's status, stop reason and error."""

    def __init__(self, status: str, reason: str, error: str | None = None):
        super().__init__(reason)
        self.status, self.reason, self.error = status, reason, error


@dataclass
class Spend:
    """The model calls of one session: how many, their usage and cost."""

    calls: int = 0
    usage: Usage = field(default_factory=Usage)
    cost: float = 0.0

    def add(self, result: CompletionResult) -> None:
        self.calls += 1
        self.usage = self.usage + result.usage
        self.cost += result.cost_usd

    def tokens(self) -> TokenTotals:
        u = self.usage
        return TokenTotals(
            input=u.input_tokens,
            cached_input=u.cached_input_tokens,
            cache_write=u.cache_write_tokens,
            output=u.output_tokens,
            reasoning=u.reasoning_tokens or 0,
        )


def reply_fields(result: CompletionResult) -> dict[str, Any]:
    """The fields of a "reply" event: the text and what the call took."""
    return {
        "text": result.text,
        "finish_reason": result.finish_reason,
        "latency_s": round(result.latency_s, 4),
        "attempts": result.attempts,
        "usage": dataclasses.asdict(result.usage),
        "cost_usd": result.cost_usd,
    }
