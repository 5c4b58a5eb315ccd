"""Per-machine entries of a JSON file in the user's cache: figures that hold for one host
(the sweep's measured paces, the endpoint check's latencies), keyed by host name so that one
home directory shared by several machines keeps each machine's own.

Reading returns this host's entries, empty where the file is missing or unreadable; writing
merges entries into them and replaces the file atomically (a temporary file beside it, then
`os.replace`), and never raises: a cache must not fail the command that feeds it.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any


def cache_dir() -> Path:
    """vabench's folder of the user's cache (`XDG_CACHE_HOME`, else ~/.cache)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "vabench"


def read_host(path: Path) -> dict[str, Any]:
    """This machine's entries of `path` (empty where there are none)."""
    try:
        entries = json.loads(path.read_text(encoding="utf-8")).get(socket.gethostname(), {})
    except (OSError, ValueError, AttributeError):
        return {}
    return entries if isinstance(entries, dict) else {}


def write_host(path: Path, entries: Mapping[str, Any]) -> None:
    """Merge `entries` into this machine's entries of `path` (never raises)."""
    with contextlib.suppress(OSError, ValueError, TypeError):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            doc = {}
        doc.setdefault(socket.gethostname(), {}).update(entries)
        path.parent.mkdir(parents=True, exist_ok=True)
        part = path.with_name(f"{path.name}.{os.getpid()}.part")
        part.write_text(json.dumps(doc, indent=1), encoding="utf-8")
        part.replace(path)
