"""One HTTP exchange with an endpoint, and what its outcome means for the call.

A `Transport` holds what every attempt at an endpoint shares: its aiohttp session (one
connection pool sized to the endpoint's concurrency, opened on first use), its API's URL and
headers, and its key. `post` sends one encoded body and returns the parsed reply or a
`Failure`: a line for the record and the retry decision. HTTP error statuses are classified by
`retry.decide`; timeouts, dropped connections and malformed 2xx bodies are transient. A
connection that could not be made at all (refused, DNS, TLS handshake) is marked `unreachable`:
the pool decides whether that is transient (the endpoint answered before) or fatal. Only
cancellation propagates.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass

import aiohttp
from pydantic import SecretStr

from vabench.llm_pool.apis import ApiAdapter
from vabench.llm_pool.apis.base import error_message, error_words
from vabench.llm_pool.config import ModelEndpoint
from vabench.llm_pool.errors import ResponseFormatError
from vabench.llm_pool.messages import ParsedResponse
from vabench.llm_pool.retry import ErrorMeaning, RetryDecision, decide, meaning_of


@dataclass(frozen=True)
class Failure:
    """A failed attempt: its line for the record, whether and how to retry, its HTTP status."""

    line: str
    decision: RetryDecision
    status: int | None = None
    unreachable: bool = False
    """No connection was made (refused, DNS, TLS), or a gateway answered that it could not
    reach its upstream: nothing that serves the model answered."""
    meaning: ErrorMeaning | None = None
    """What the error body says beyond its status (`retry.meaning_of`)."""
    timed_out: bool = False


def _is_json(raw: bytes) -> bool:
    try:
        json.loads(raw)
    except ValueError:
        return False
    return True


class Transport:
    """HTTP to one endpoint; created by `EndpointClient`."""

    def __init__(self, config: ModelEndpoint, adapter: ApiAdapter, api_key: SecretStr | None):
        self.adapter = adapter
        self.url = adapter.url(config.resolved_base_url)
        self._key = api_key.get_secret_value() if api_key is not None else None
        self._headers = {
            "Content-Type": "application/json",
            **config.headers,
            **adapter.headers(self._key),
        }
        self._connections = config.limits.max_concurrency
        self._session: aiohttp.ClientSession | None = None

    def _get_session(self) -> aiohttp.ClientSession:
        if self._session is None:
            connector = aiohttp.TCPConnector(limit=self._connections, limit_per_host=0)
            self._session = aiohttp.ClientSession(
                connector=connector, timeout=aiohttp.ClientTimeout(total=None)
            )
        return self._session

    async def post(self, body: bytes, timeout: float) -> ParsedResponse | Failure:
        """One HTTP exchange; transport problems become `Failure`s, cancellation propagates."""
        try:
            async with self._get_session().post(
                self.url,
                data=body,
                headers=self._headers,
                timeout=aiohttp.ClientTimeout(total=timeout),
            ) as resp:
                raw = await resp.read()
                status, headers = resp.status, resp.headers
        except asyncio.TimeoutError:
            line = f"timeout after {timeout:.1f} s"
            return self._failure(line, RetryDecision("transient", "timeout"), timed_out=True)
        except aiohttp.ClientError as err:
            line = f"{type(err).__name__}: {err}"
            # ClientConnectorError covers refused connections, DNS (ClientConnectorDNSError)
            # and TLS handshakes (ClientSSLError); a drop after connecting is not one.
            unreachable = isinstance(err, aiohttp.ClientConnectorError)
            return self._failure(line, RetryDecision("transient", "connection"), None, unreachable)
        if 200 <= status < 300:
            try:
                return self.adapter.parse_response(raw)
            except ResponseFormatError as err:
                return self._failure(str(err), RetryDecision("transient", "malformed"), status)
        line = f"HTTP {status}: {error_message(raw)}"
        meaning = meaning_of(status, error_words(raw))
        if meaning is None and status == 500 and not self._key and not _is_json(raw):
            # A LiteLLM proxy installed with pip answers a call without a key with a bare
            # text 500 (its key check fails on a missing database client): the one thing
            # the reply says is that a call sent without a key failed. Fatal only before
            # any success (`EndpointClient`), as for a 500 naming the key.
            meaning = "key"
            line += " (the request carried no API key)"
        unreachable = meaning == "upstream"
        return self._failure(line, decide(status, headers), status, unreachable, meaning)

    def _failure(
        self,
        line: str,
        decision: RetryDecision,
        status: int | None = None,
        unreachable: bool = False,
        meaning: ErrorMeaning | None = None,
        *,
        timed_out: bool = False,
    ) -> Failure:
        # Providers sometimes echo (part of) a key in errors; never let it reach a record.
        if self._key:
            line = line.replace(self._key, "[redacted]")
        return Failure(line, decision, status, unreachable, meaning, timed_out)

    async def close(self) -> None:
        if self._session is not None:
            await self._session.close()
            self._session = None
