"""The ways a call can fail, typed by what the caller should do about them.

- `InfrastructureError`: the endpoint stayed unhealthy (rate limits, 5xx, timeouts, dropped
  connections, malformed bodies) through every attempt the retry policy allows. The engine
  re-runs the episode later; it is never scored.
- `RequestRejected`: the endpoint refused the request itself (a 4xx other than 408/409/429).
  Retrying cannot help. When the refusal is the endpoint's, not the episode's (`fatal`: a
  wrong key 401/403, an unknown model 404, or a 400 before the endpoint ever answered, i.e.
  parameters it does not take), the sweep stops and records nothing for the episodes it
  touched; otherwise (a 400 or 413 of one episode's request) the episode ends with that
  reason. A body that names the key or an unknown model is read the same whatever its status
  (`retry.meaning_of`: a gateway sends 400 or 500 for them), and is fatal like a 401 or a 404;
  so is a bare text 500 to a call sent without a key before any success (a LiteLLM proxy's
  answer to a missing key).
  A rejection whose body says the request exceeds the model's context window
  (`context_exceeded`) is never fatal, even on the first call: it is the episode's own
  failure (the engine compacts and retries once, then scores it `context_exceeded`).
- `SpendCapReached`: a `RequestRejected` never sent, because its cost could cross a spend cap
  (`limits.max_cost_usd`); fatal.
- `EndpointUnreachable`: a `RequestRejected` that is always fatal: no connection could be made
  (refused, DNS, TLS), a gateway answered that its upstream is unreachable, or every attempt
  timed out (`retry.request_timeout_s`), at an endpoint that has not answered once since the
  pool opened, i.e. nothing serves its `base_url` (a local server not started, a typo in the
  host, a gateway's provider down). Retrying
  would only turn every episode into an infrastructure error; once the endpoint has answered,
  the same errors are transient (a server restarting) and retried as before.
- `ResponseFormatError`: a body that is not what the API documents. Raised by the parsers,
  retried by the pool, and named in the final `InfrastructureError` if it persists.

Model behaviour (a refusal, hitting max tokens, an empty answer) is not an error: it is a
`CompletionResult` with its finish reason.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # a value only carried here; spend.py does not import this module either
    from vabench.llm_pool.spend import CapReached


_CONTEXT_MARKERS = re.compile(
    r"context[_ ]length[_ ]exceeded|exceed_context_size_error|maximum context length"
    r"|context (?:window|length|size)|available context size|prompt is too long"
    r"|input is too long|maximum input length|input exceeds|too many (?:input )?tokens"
    r"|tokens? exceed|request too large|longer than the model's",
    re.I,
)
"""How servers word a request too long for the model's context: OpenAI
(`context_length_exceeded`, "maximum context length"), vLLM ("This model's maximum context
length is N tokens"), SGLang ("longer than the model's context length"), llama.cpp
(`exceed_context_size_error`, "available context size"), Anthropic ("prompt is too long"), and
the other markers the benchmark's reference harness reads as one (PROTOCOL_FACTS 8)."""


def context_exceeded(status: int, message: str) -> bool:
    """Whether a 400/413 (or a 422, as some local servers answer) says the request does not
    fit the model's context window."""
    return status in (400, 413, 422) and _CONTEXT_MARKERS.search(message) is not None


class LLMError(Exception):
    """Base of every error a pool call raises."""

    def __init__(self, endpoint: str, message: str, *, attempts: int, elapsed_s: float):
        super().__init__(f"{endpoint}: {message}")
        self.endpoint = endpoint
        self.message = message
        self.attempts = attempts
        self.elapsed_s = elapsed_s


class InfrastructureError(LLMError):
    """Transient failures outlasted the retry policy; re-run the episode, do not score it."""

    def __init__(
        self,
        endpoint: str,
        message: str,
        *,
        attempts: int,
        elapsed_s: float,
        failures: tuple[str, ...] = (),
    ):
        super().__init__(endpoint, message, attempts=attempts, elapsed_s=elapsed_s)
        self.failures = failures
        """One line per failed attempt, oldest first."""


class RequestRejected(LLMError):
    """A non-retryable 4xx: the request itself is wrong (or the key, or the model name)."""

    def __init__(
        self,
        endpoint: str,
        message: str,
        *,
        status: int,
        attempts: int,
        elapsed_s: float,
        fatal: bool = False,
        hint: str = "",
        meaning: str | None = None,
    ):
        super().__init__(endpoint, message, attempts=attempts, elapsed_s=elapsed_s)
        self.status = status
        self.meaning = meaning
        """What the error body named (`retry.meaning_of`: key, model), whatever the status."""
        self.fatal = fatal
        """The endpoint cannot serve this sweep as configured: stop, record nothing."""
        self.hint = hint
        """What to check (the key's environment variable, the model id, the parameters)."""

    verdict = "its endpoint refused the sweep's requests"
    """How a sweep stopped by this error says what happened (before the failure line)."""

    @property
    def context_exceeded(self) -> bool:
        """The request does not fit the model's context window (`context_exceeded`): the
        episode's own failure, never the endpoint's (the engine compacts and retries once)."""
        return context_exceeded(self.status, self.message)

    @property
    def kind(self) -> str:
        """auth (401/403, or a body naming the key), not_found (404, or a body naming an
        unknown model), too_large (413) or bad_request (other 4xx)."""
        if self.meaning in ("key", "model"):
            return "auth" if self.meaning == "key" else "not_found"
        return {401: "auth", 403: "auth", 404: "not_found", 413: "too_large"}.get(
            self.status, "bad_request"
        )


class SpendCapReached(RequestRejected):
    """A call not sent: its cost could cross `limits.max_cost_usd` (`reached` says whose cap and
    at what spend). Fatal like a wrong key: the episodes it stops get no record, and the same
    command with a higher cap resumes them."""

    def __init__(self, endpoint: str, reached: CapReached):
        super().__init__(
            endpoint,
            str(reached),
            status=0,
            attempts=0,
            elapsed_s=0.0,
            fatal=True,
            hint="raise limits.max_cost_usd and run the same command to resume",
        )
        self.reached = reached


class EndpointUnreachable(RequestRejected):
    """No connection to an endpoint that never answered: fatal, with status 0 (no HTTP)."""

    verdict = "nothing answered at its endpoint"

    def __init__(self, endpoint: str, message: str, *, attempts: int, elapsed_s: float, hint: str):
        super().__init__(
            endpoint,
            message,
            status=0,
            attempts=attempts,
            elapsed_s=elapsed_s,
            fatal=True,
            hint=hint,
        )

    @property
    def kind(self) -> str:
        return "unreachable"


class ResponseFormatError(ValueError):
    """A response body that does not match the API's documented shape; names the problem."""
