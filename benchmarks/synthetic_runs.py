"""Synthetic run directories of any size, shaped exactly like a real sweep's, for the scale
benchmark (benchmarks/records_scale.py) and its test.

    make_run(root, episodes=200_000) -> SyntheticRun

A run of configs/all.yaml's shape (the embedded models, tracks active, passive, transfer and
long_horizon over the base suite, three runs) whose seed lists are stretched until the plan
holds about `episodes` episodes (exactly 2,160 = all.yaml at the default sizes: 20 seeds per
task), written as the sweep writes it:

- root/config.yaml, the config; RUN_DIR = root/run with plan.json and sweep.yaml written by the
  sweep's own `check_run_dir`, so a resumed sweep accepts the directory;
- results.jsonl: one ledger line per finished episode, built from a validated `EpisodeResult`
  (the ledger's envelope as `Ledger.add` writes it), in a shuffled finishing order; about 1 %
  end `infrastructure_error` after their retry rounds, 0.2 % `error`, the scored ones succeed
  at 30 %; infrastructure.jsonl holds the retried attempts;
- per finished episode: events.jsonl (the event log of a real 5-step smoke episode,
  benchmarks/synthetic_template/, with this episode's identity and ending), result.json
  (`model_dump_json(indent=1)`, as `EpisodeRecorder.finish`) and frames/ with every image its
  observations name;
- per unfinished episode, one in ten holds the events of an interrupted attempt (no result),
  as a killed sweep leaves them;
- annotations/<annotator>.jsonl: `annotated` of the scored episodes judged by three
  annotators (gates, then the criteria they activate), as the viewer writes them.

Images are shared: every frame is a hard link to one tiny JPEG (a fresh source every 60,000
links, under ext4's limit of 65,000 links a file), so 200,000 episodes take ~3 GB of events and
no image data. The generator is seeded: the same arguments give the same directory.
"""

from __future__ import annotations

import io
import json
import os
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

TEMPLATE = Path(__file__).resolve().parent / "synthetic_template"
LINKS_PER_SOURCE = 60_000
"""Hard links made to one source JPEG (ext4 allows 65,000 a file)."""
ANNOTATORS = ("alice", "bob", "judge-a")
TRACKS = ("active", "passive", "transfer", "long_horizon")
RUNS = 3
FIRST_SEED = 1000
STEP_BUDGET = 5
"""The template episodes' steps: the config caps every task's budget at it, so records, events
and plan agree."""


@dataclass(frozen=True)
class SyntheticRun:
    root: Path
    config: Path
    """A config file: `python -m vabench.sweep CONFIG` resumes RUN_DIR."""
    run_dir: Path
    planned: int
    finished: int
    annotated: int


def config_document(
    run_dir: Path, seeds: dict[str, list[int]], models: int, runs: int
) -> dict[str, Any]:
    return {
        "name": "synthetic",
        "out": str(run_dir),
        "models": [
            {"name": f"model-{i}", "api": "openai_chat", "base_url": "embedded"}
            for i in range(models)
        ],
        "embedded_server": {"policy": "random_action"},
        "tracks": list(TRACKS),
        "summaries": "none",
        "tasks": "base",
        "seeds": seeds,
        "runs": runs,
        "step_budget": STEP_BUDGET,
        "simulator": {"backend": "c"},
        "render": {"width": 320, "height": 240, "workers": 1},
        "executor": {"kind": "local"},
    }


def seed_lists(episodes: int, models: int, runs: int, run_dir: Path) -> dict[str, list[int]]:
    """Seeds per planned task so that the plan holds about `episodes` (at least one each): the
    same number for every task, then one more for tasks in plan order while it fits."""
    from vabench.config import load_config

    probe = _load(config_document(run_dir, {}, models, runs), load_config, seeds="verified")
    tasks = list(probe.all_tasks)
    per_seed = {t: 0 for t in tasks}
    for track in probe.tracks:
        for task in probe.track_tasks(track):
            per_seed[task] += models * runs
    total_per_seed = sum(per_seed.values())
    n = max(1, episodes // total_per_seed)
    counts = dict.fromkeys(tasks, n)
    total = n * total_per_seed
    for task in tasks:
        if total + per_seed[task] <= episodes:
            counts[task] += 1
            total += per_seed[task]
    return {t: list(range(FIRST_SEED, FIRST_SEED + counts[t])) for t in tasks}


def _load(doc: dict[str, Any], load_config: Any, seeds: Any = None) -> Any:
    """A config from a document (through a file: `load_config` reads paths)."""
    import tempfile

    if seeds is not None:
        doc = {**doc, "seeds": seeds}
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
        yaml.safe_dump(doc, f, sort_keys=False)
    try:
        return load_config(Path(f.name))
    finally:
        os.unlink(f.name)


def tiny_jpeg() -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (8, 8), (90, 120, 150)).save(buf, format="JPEG", quality=50)
    return buf.getvalue()


class _Frames:
    """Hard links to a rotating source JPEG (see `LINKS_PER_SOURCE`)."""

    def __init__(self, directory: Path):
        self.directory = directory
        directory.mkdir(parents=True, exist_ok=True)
        self.data = tiny_jpeg()
        self.links = LINKS_PER_SOURCE
        self.source = ""
        self.sources = 0

    def link(self, target: str) -> None:
        if self.links >= LINKS_PER_SOURCE:
            self.source = str(self.directory / f"frame_{self.sources}.jpg")
            Path(self.source).write_bytes(self.data)
            self.sources += 1
            self.links = 0
        os.link(self.source, target)
        self.links += 1


class _Events:
    """A real episode's event log per protocol, re-stamped with each episode's identity."""

    def __init__(self) -> None:
        self.logs: dict[str, tuple[dict[str, Any], str, dict[str, Any], list[str]]] = {}
        for protocol in ("active", "passive"):
            lines = (TEMPLATE / f"{protocol}.events.jsonl").read_text().splitlines()
            events = [json.loads(line) for line in lines]
            frames = [f for e in events if e["type"] == "observation" for f in e["frames"]]
            middle = "".join(line + "\n" for line in lines[1:-1])
            self.logs[protocol] = (events[0], middle, events[-1], frames)

    def text(self, record: dict[str, Any], partial: bool = False) -> str:
        start, middle, end, _ = self.logs[record["protocol"]]
        head = {**start, **{k: record[k] for k in ("task", "seed", "model", "protocol", "run")}}
        head["step_budget"] = record["step_budget"]
        if partial:
            return json.dumps(head) + "\n" + middle
        tail = {**end, **{k: record[k] for k in ("status", "stop_reason", "success", "error")}}
        return json.dumps(head) + "\n" + middle + json.dumps(tail) + "\n"

    def frames(self, protocol: str) -> list[str]:
        return self.logs[protocol][3]


def _write(path: str, data: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, data.encode("utf-8"))
    finally:
        os.close(fd)


def _result(key: Any, protocol: str, checkpoints: tuple[str, ...], rng: random.Random) -> Any:
    """A validated `EpisodeResult` of a plausible outcome."""
    from vabench.agent.records import EpisodeResult

    u = rng.random()
    n = len(checkpoints)
    if u < 0.01:
        status, reason, error = "infrastructure_error", "infrastructure_error", "HTTP 503"
    elif u < 0.012:
        status, reason, error = "error", "harness_error", "RuntimeError: synthetic"
    elif u < 0.012 + 0.3 * 0.988:
        status, reason, error = "success", "success", None
    else:
        status = "failure"
        reason = rng.choice(("budget_exhausted", "model_stop", "invalid_output"))
        error = None
    success = status == "success"
    progress = n if success else rng.randint(0, n - 1) if status == "failure" else 0
    steps = rng.randint(2, STEP_BUDGET) if success else STEP_BUDGET
    calls = steps + rng.randint(0, 2)
    fresh = rng.randint(5_000, 15_000)
    return EpisodeResult(
        task=key.task,
        seed=key.seed,
        model=key.model,
        protocol=protocol,
        run=key.run,
        status=status,
        success=success,
        stop_reason=reason,
        error=error,
        steps_used=steps,
        step_budget=STEP_BUDGET,
        robot_actions=steps - rng.randint(0, 1),
        camera_actions=rng.randint(0, 2) if protocol == "active" else 0,
        invalid_outputs=rng.randint(0, 1),
        invalid_actions=rng.randint(0, 1),
        tool_calls=rng.randint(0, 2),
        model_calls=calls,
        checkpoints_reached=list(checkpoints[:progress]),
        progress=progress,
        n_checkpoints=n,
        tokens={
            "input": fresh,
            "cached_input": rng.randint(0, 15_000),
            "cache_write": 0,
            "output": calls * rng.randint(20, 40),
            "reasoning": 0,
        },
        cost_usd=round(fresh * 2.5e-6, 6),
        wall_s=round(rng.uniform(3, 30), 3),
        started_at=round(1795710460.0 + rng.uniform(0, 86_400), 3),
    )


def _judgments(episode: str, rng: random.Random, t: float) -> dict[str, list[dict[str, Any]]]:
    """Each annotator's judgments of one episode: both gates, then every criterion its own
    gate votes activate (stage one of the rubric)."""
    from vabench.diagnostics.criteria import CRITERIA, GATES, RUBRIC_VERSION

    out: dict[str, list[dict[str, Any]]] = {}
    for annotator in ANNOTATORS:
        votes = {g: int(rng.random() < 0.5) for g in GATES}
        items = [(g, v) for g, v in votes.items()]
        items += [
            (c, int(rng.random() < 0.5))
            for c, spec in CRITERIA.items()
            if spec.gate is None or votes[spec.gate] == 1
        ]
        source = f"judge:{annotator}" if annotator.startswith("judge") else "human"
        out[annotator] = [
            {
                "v": 1,
                "annotator": annotator,
                "episode": episode,
                "item": item,
                "value": value,
                "time": round(t + i * 0.5, 3),
                "rubric": RUBRIC_VERSION,
                "source": source,
            }
            for i, (item, value) in enumerate(items)
        ]
    return out


def make_run(
    root: Path | str,
    episodes: int,
    *,
    models: int = 1,
    runs: int = RUNS,
    finished: float = 0.9,
    annotated: float = 0.02,
    seed: int = 0,
    annotate_run: int | None = None,
) -> SyntheticRun:
    """Write a synthetic run of about `episodes` planned episodes under `root` (see the module
    docstring); `finished` of them in the ledger, `annotated` of the scored ones annotated.
    `annotate_run`: annotate only that run's episodes of the active track (the paper annotates
    one complete base run per condition)."""
    from vabench.config import load_config
    from vabench.run_layout import RunDir, episode_id
    from vabench.sweep.plan import plan
    from vabench.sweep.rundir import check_run_dir
    from vabench.tasks import REGISTRY

    root = Path(root)
    run_dir = root / "run"
    root.mkdir(parents=True, exist_ok=True)
    seeds = seed_lists(episodes, models, runs, run_dir)
    doc = config_document(run_dir, seeds, models, runs)
    config_path = root / "config.yaml"
    config_path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    config = load_config(config_path)
    keys = plan(config)
    check_run_dir(run_dir, config, keys, config.document())
    files = RunDir(run_dir)

    rng = random.Random(seed)
    order = list(keys)
    rng.shuffle(order)
    done = order[: round(finished * len(order))]
    pending = order[len(done) :]
    frames = _Frames(root / "frame-sources")
    events = _Events()
    protocol = {t.name: t.protocol for t in config.tracks}
    checkpoints = {name: tuple(REGISTRY[name].checkpoints) for name in config.all_tasks}
    made: set[str] = set()

    def episode_dir(k: Any) -> str:
        path = str(run_dir / k.rel_dir)
        parent = os.path.dirname(path)
        if parent not in made:
            os.makedirs(parent, exist_ok=True)
            made.add(parent)
        os.mkdir(path)
        os.mkdir(os.path.join(path, "frames"))
        for name in events.frames(protocol[k.track]):
            frames.link(os.path.join(path, name))
        return path

    ledger: list[str] = []
    infra: list[str] = []
    scored: list[str] = []
    for k in done:
        result = _result(k, protocol[k.track], checkpoints[k.task], rng)
        dumped = result.model_dump()
        envelope = {"v": dumped["v"], "track": k.track, "episode_dir": k.rel_dir, **dumped}
        retries = 3 if result.status == "infrastructure_error" else int(rng.random() < 0.02)
        infra += [json.dumps({**envelope, "status": "infrastructure_error"})] * retries
        ledger.append(json.dumps(envelope))
        path = episode_dir(k)
        _write(os.path.join(path, "events.jsonl"), events.text(dumped))
        _write(os.path.join(path, "result.json"), result.model_dump_json(indent=1))
        if result.scored and (annotate_run is None or (k.run, k.track) == (annotate_run, "active")):
            scored.append(episode_id(k.rel_dir))
    for k in pending[: len(pending) // 10]:  # interrupted attempts: events, no result
        stand_in = {**k.__dict__, "protocol": protocol[k.track], "step_budget": STEP_BUDGET}
        _write(os.path.join(episode_dir(k), "events.jsonl"), events.text(stand_in, True))
    files.results.write_text("".join(line + "\n" for line in ledger), encoding="utf-8")
    if infra:
        files.infrastructure.write_text("".join(line + "\n" for line in infra), "utf-8")

    chosen = sorted(rng.sample(scored, round(annotated * len(scored))))
    by_annotator: dict[str, list[str]] = {a: [] for a in ANNOTATORS}
    for i, episode in enumerate(chosen):
        for annotator, lines in _judgments(episode, rng, 1795800000.0 + i).items():
            by_annotator[annotator] += [json.dumps(line) for line in lines]
    if chosen:
        files.annotations.mkdir(exist_ok=True)
        for annotator, lines in by_annotator.items():
            files.annotation_file(annotator).write_text(
                "".join(line + "\n" for line in lines), encoding="utf-8"
            )
    return SyntheticRun(root, config_path, run_dir, len(keys), len(done), len(chosen))


if __name__ == "__main__":
    import argparse
    import sys
    import time

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", type=Path)
    p.add_argument("--episodes", type=int, default=2160)
    p.add_argument("--models", type=int, default=1)
    p.add_argument("--finished", type=float, default=0.9)
    p.add_argument("--annotated", type=float, default=0.02)
    p.add_argument("--annotate-run", type=int, help="annotate only this run's active track")
    args = p.parse_args()
    t0 = time.perf_counter()
    run = make_run(
        args.root,
        args.episodes,
        models=args.models,
        finished=args.finished,
        annotated=args.annotated,
        annotate_run=args.annotate_run,
    )
    print(
        f"{run.run_dir}: {run.planned} planned, {run.finished} finished, "
        f"{run.annotated} annotated ({time.perf_counter() - t0:.1f} s)"
    )
