"""`RequestRecord`: one request as the embedded server saw it, the entry of its request log.

The server fills one per request (`server.LocalServer`); a serving process sends each of its
records to the parent through a pipe (`server_processes.ServingProcesses`), which the server
starts. The record sits below both, so the processes need not import the server for it (else
the two would import each other).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class RequestRecord:
    """One request as the server saw it. No headers, no keys, no content."""

    id: int
    api: str
    received_s: float
    process: int = 0
    """Which of the server's processes answered (`ServerConfig.server_processes`; 0 for one)."""
    body_bytes: int = 0
    model: str | None = None
    images: int = 0
    fault: str | None = None
    status: int | None = None
    """HTTP status sent; None while in flight or when the client went away first."""
    input_tokens: int = 0
    output_tokens: int = 0
    finished_s: float | None = None
    error: str | None = None
