"""`python -m vabench.check CONFIG [--model NAME]`: each model's endpoint tried once, with the
sweep's real inputs, before a sweep spends anything (also the sweep's first step; its
`--no-check` skips it).

Per model, one decision carries the heaviest request the sweep sends it (`inputs`): the
longest first-step prompt, the passive bundle at its real size, the demonstration frames.
What came back is reported one line an item (`judge`): reachable; key accepted; model name
known; images per request accepted; context length where the server says it, against the
plan's need; the prompt tokens the server counted against our estimate; the output-limit
field read; a reasoning field; latency; the decision's cost. A problem carries its fix, and
the command exits 2 with one line per problem (`run`: how each model is called). Each check's
latency is kept per machine (`latency`); with the paces earlier sweeps measured here (`pace`)
it gives the dry run its expected wall time and disk.

    reports = asyncio.run(check_config(config, os.environ))
    print(report_text(reports))
    for line in problems(reports):
        print(line.problem_line(), file=sys.stderr)
"""

from __future__ import annotations

import asyncio
from collections.abc import Collection, Mapping, Sequence

from vabench.check.judge import Line
from vabench.check.run import check_config
from vabench.config import SweepConfig

__all__ = [
    "Line",
    "check_config",
    "check_sync",
    "plan_line",
    "problems",
    "report_text",
    "sweep_models",
]


def check_sync(
    config: SweepConfig, environ: Mapping[str, str], models: Sequence[str] | None = None
) -> dict[str, list[Line]]:
    """`check_config` from code without an event loop (the commands)."""
    return asyncio.run(check_config(config, environ, models))


def report_text(reports: Mapping[str, list[Line]]) -> str:
    """Every model's lines under its name."""
    out = []
    for model, lines in reports.items():
        out.append(f"check: model {model!r}")
        out += [line.row() for line in lines]
    return "\n".join(out)


def problems(reports: Mapping[str, list[Line]]) -> list[Line]:
    """The lines that carry a fix, in report order."""
    return [line for lines in reports.values() for line in lines if line.problem]


def sweep_models(config: SweepConfig, planned: Collection[str]) -> list[str]:
    """The models of `planned` a sweep's first step checks, in the config's order: none where
    all are the embedded server's (it has none of the limits the check looks for)."""
    if not set(planned) - set(config.embedded_models):
        return []
    return [m.name for m in config.models if m.name in planned]


def plan_line(config: SweepConfig, planned: Collection[str], skipped: bool) -> str:
    """The dry run's line on the sweep's first step."""
    if skipped:
        return "check:     skipped (--no-check)"
    models = set(planned) - set(config.embedded_models)
    if not models:
        return "check:     none needed (every model is the embedded server's)"
    return (
        f"check:     first, one decision for each of {len(models)} model(s) with the sweep's "
        "inputs (python -m vabench.check; --no-check skips it)"
    )
