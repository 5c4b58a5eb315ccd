"""The endpoint check's decision latency, kept per machine and per API model kind, so that a
dry run can time a real model no sweep has measured on this machine yet.

Each check of an API model that answers without a problem writes its latency to
`latency_file()` (the user's cache, keyed by host name, the latest check of a kind replacing
the one before); `check.pace` reads it where it has no measured pace of that kind. A kind is
`api_kind`: the API, the provider's model and the image size, as the sweep's pace keys it
(the check's request carries the sweep's heaviest images, so another size is another kind).
Writing never fails a check.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

from vabench.config import SweepConfig
from vabench.machine_cache import cache_dir, read_host, write_host


def latency_file() -> Path:
    """Where this user's check latencies live (every host's, keyed by host name)."""
    return cache_dir() / "check_latency.json"


def api_kind(config: SweepConfig, model: str) -> str:
    """What decides an API model's pace: its API, the provider's model, the image size."""
    m = config.model(model)
    return f"{m.api} {m.provider_model} at {config.render.width}x{config.render.height}"


@dataclass(frozen=True)
class CheckLatency:
    """One check's decision: its latency and when it was measured."""

    latency_s: float
    checked_at: float

    @property
    def when(self) -> str:
        return time.strftime("%Y-%m-%d %H:%M", time.localtime(self.checked_at))


def keep(kind: str, latency_s: float, path: Path | None = None) -> None:
    """Write one check's latency of `kind` to this machine's entries (never raises)."""
    entry = asdict(CheckLatency(round(latency_s, 3), time.time()))
    write_host(path or latency_file(), {kind: entry})


def measured(path: Path | None = None) -> dict[str, CheckLatency]:
    """This machine's check latencies by kind (empty where none)."""
    try:
        return {kind: CheckLatency(**v) for kind, v in read_host(path or latency_file()).items()}
    except TypeError:  # an entry of another version's fields
        return {}
