"""`python -m vabench.report.inspect_log RUN_DIR --out DIR`: a sweep's episodes as inspect_ai
logs, one per model and track, that inspect_ai's log reader and viewer open (`inspect view
--log-dir DIR`).

People who evaluate models already read inspect_ai's logs; this writes vabench's records in
that format (the optional extra `inspect`: `pip install 'vabench[inspect]'`), built from
inspect_ai's own log classes so that what it writes is what its reader takes:

- one log per (model, track): the task is `vabench/<track>`, the model `vabench/<model>`;
- a sample per scored episode (id `<task>:<seed>:<run>`, epoch = the run), its
  messages the conversation as recorded: each observation a user message with the frames the
  model saw (JPEG data URIs; `--no-images` leaves a line naming the frame instead, for
  smaller logs: a full suite's frames are gigabytes) and each reply an assistant message;
- its score `success` (1 or 0; the answer is the stop reason; progress and checkpoints in the
  score's metadata), its usage (input, cached input, cache writes, output, reasoning tokens,
  cost) and wall time;
- the log's results: the success rate over the scored episodes ("accuracy"), its stats the
  usage summed over the samples.

The prompts' text is not in the records (vabench logs what the model saw as frames and counts,
not the rendered prompt), so user messages carry the step and view, not the observation text.
"""

from __future__ import annotations

import argparse
import base64
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vabench.agent.records import read_events
from vabench.run_records import Record, ReportError, load_results

EXTRA_HINT = "pip install 'vabench[inspect]'"


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime(t))


def _messages(episode: Path, model: str, images: bool) -> list[Any]:
    from inspect_ai.model import ChatMessageAssistant, ChatMessageUser, ContentImage, ContentText

    out: list[Any] = []
    for event in read_events(episode):
        kind = event.get("type")
        if kind == "observation":
            view = event.get("view")
            content: list[Any] = [ContentText(text=f"step {event.get('step')}: view {view}")]
            for rel in event.get("frames", []):
                path = episode / rel
                if images and path.is_file():
                    data = base64.b64encode(path.read_bytes()).decode("ascii")
                    content.append(ContentImage(image=f"data:image/jpeg;base64,{data}"))
                else:
                    content.append(ContentText(text=f"[frame {rel}]"))
            out.append(ChatMessageUser(content=content))
        elif kind == "reply":
            out.append(ChatMessageAssistant(content=event.get("text") or "", model=model))
    return out


def _usage(records: Sequence[Record]) -> Any:
    from inspect_ai.model import ModelUsage

    def total(name: str) -> int:
        return sum(getattr(r.result.tokens, name) for r in records)

    fresh, cached, written = total("input"), total("cached_input"), total("cache_write")
    output = total("output")
    return ModelUsage(
        input_tokens=fresh + cached + written,
        output_tokens=output,
        total_tokens=fresh + cached + written + output,
        input_tokens_cache_read=cached,
        input_tokens_cache_write=written,
        reasoning_tokens=total("reasoning"),
        total_cost=sum(r.result.cost_usd for r in records),
    )


def _sample(run_dir: Path, record: Record, images: bool) -> Any:
    from inspect_ai.log import EvalSample
    from inspect_ai.model import ModelOutput
    from inspect_ai.scorer import Score

    r = record.result
    episode = run_dir / record.episode_dir
    return EvalSample(
        id=f"{r.task}:{r.seed}:{r.run}",
        epoch=r.run,
        input=f"{r.task}, seed {r.seed} ({r.protocol} camera protocol)",
        target="success",
        messages=_messages(episode, r.model, images) if record.episode_dir else [],
        output=ModelOutput(model=r.model),
        scores={
            "success": Score(
                value=1 if r.success else 0,
                answer=r.stop_reason,
                metadata={
                    "progress": r.progress,
                    "checkpoints": list(r.checkpoints_reached),
                    "n_checkpoints": r.n_checkpoints,
                },
            )
        },
        metadata={
            "task": r.task,
            "seed": r.seed,
            "track": record.track,
            "protocol": r.protocol,
            "steps_used": r.steps_used,
            "step_budget": r.step_budget,
            "robot_actions": r.robot_actions,
            "camera_actions": r.camera_actions,
            "invalid_outputs": r.invalid_outputs,
            "episode_dir": record.episode_dir,
        },
        model_usage={f"vabench/{r.model}": _usage([record])},
        total_time=r.wall_s,
        working_time=r.wall_s,
    )


def export(run_dir: Path | str, out: Path | str, images: bool = True) -> list[Path]:
    """Write RUN_DIR's scored episodes as one inspect_ai log per (model, track) into OUT;
    returns the paths written. Raises ReportError for a run directory without records and
    ImportError (naming the extra) without inspect_ai."""
    try:
        from inspect_ai.log import (
            EvalConfig,
            EvalDataset,
            EvalLog,
            EvalMetric,
            EvalResults,
            EvalScore,
            EvalSpec,
            EvalStats,
            write_eval_log,
        )
    except ImportError as err:
        raise ImportError(f"exporting to inspect_ai needs inspect_ai ({EXTRA_HINT})") from err
    run_dir, out = Path(run_dir), Path(out)
    results = load_results(run_dir)
    groups: dict[tuple[str, str], list[Record]] = defaultdict(list)
    for record in results.scored:
        groups[(record.result.model, record.track)].append(record)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for (model, track), records in sorted(groups.items()):
        records.sort(key=lambda x: (x.result.task, x.result.seed, x.result.run))
        starts = [x.result.started_at for x in records if x.result.started_at]
        ends = [x.result.started_at + x.result.wall_s for x in records if x.result.started_at]
        created = _iso(min(starts)) if starts else _iso(time.time())
        wins = sum(x.result.success for x in records)
        name = f"vabench/{model}"
        log = EvalLog(
            status="success",
            eval=EvalSpec(
                created=created,
                task=f"vabench/{track}",
                dataset=EvalDataset(name="VA-Bench", samples=len(records)),
                model=name,
                config=EvalConfig(),
                metadata={"run_dir": str(run_dir), "track": track},
            ),
            results=EvalResults(
                total_samples=len(records),
                completed_samples=len(records),
                scores=[
                    EvalScore(
                        name="success",
                        scorer="vabench",
                        metrics={
                            "accuracy": EvalMetric(name="accuracy", value=wins / len(records))
                        },
                    )
                ],
            ),
            stats=EvalStats(
                started_at=created,
                completed_at=_iso(max(ends)) if ends else created,
                model_usage={name: _usage(records)},
            ),
            samples=[_sample(run_dir, x, images) for x in records],
        )
        path = out / f"{_safe(model)}_{track}.eval"
        write_eval_log(log, str(path))
        written.append(path)
    return written


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "-" for c in name)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir")
    parser.add_argument("--out", required=True, help="the folder the logs are written to")
    parser.add_argument(
        "--no-images", action="store_true", help="name each frame instead of embedding it"
    )
    args = parser.parse_args(argv)
    try:
        paths = export(args.run_dir, args.out, images=not args.no_images)
    except (ReportError, ImportError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
