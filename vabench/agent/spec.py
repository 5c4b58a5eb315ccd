"""What an episode runs: `EpisodeSpec`, one seed of one task against one model.

It is its own module, below both the engine (`engine.Episode` runs a spec) and the task's
services (`services.TaskServices.on_decision` is told the spec of each decision it times): the
engine imports the services, which would import the engine back for it. Callers
outside the package take it from `vabench.agent.engine`, with the engine that runs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vabench import protocol as P
from vabench.agent.records import SummaryStatus


@dataclass(frozen=True)
class EpisodeSpec:
    """What to run: one seed of one task against one model."""

    task: str
    seed: int
    model: str
    protocol: P.ObservationProtocol = "active"
    run: int = 0
    out_dir: Path | None = None
    demonstration_summary: str | dict[str, Any] | None = None
    summary_mode: str = "none"
    summary_from: str | None = None
    """Where `demonstration_summary` came from, for the record (`EpisodeResult.summary_*`)."""
    summary_status: SummaryStatus = "none"
    step_budget: int | None = None
    """Override of the task's step budget for smoke runs and benchmarks (None: the task's;
    the record states the budget used)."""
    frames: str = "all"
    """Which episodes keep their frames on disk: all, failed, none (`records.frames`)."""
