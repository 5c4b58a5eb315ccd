"""The run directory of a sweep: every file and folder name in it, and the paths they make.

A run directory is written by the sweep and its executors (on several hosts, over several
invocations) and read by the report, the viewer, the diagnostics and a resumed sweep. They all
build their paths here, so a name is spelled once; `tests/test_layers.py` fails on a run
directory name spelled anywhere else in vabench. docs/DESIGN.md, "Run directory", is the map:

    RUN_DIR/sweep.yaml                 CONFIG: the resolved config
    RUN_DIR/plan.json                  PLAN: the plan's identity, checked on resume
    RUN_DIR/results.jsonl              RESULTS: the ledger, one line per finished episode
    RUN_DIR/infrastructure.jsonl       INFRASTRUCTURE: each infrastructure failure run again
    RUN_DIR/results.duplicates.jsonl   DUPLICATES: second records of an episode (billed only)
    RUN_DIR/episodes/<model>/<track>/<task>/seed_<s>/run_<r>/   an `EpisodeDir`:
        events.jsonl                   EVENTS: the event log
        frames/step_<NNN>.jpg          FRAMES, `frame_path`: the images the model saw
        result.json                    RESULT: how the episode ended
        partial_<n>/                   an interrupted attempt's events and frames, set aside
        attempt_<n>/                   a finished attempt that is run again, set aside
    RUN_DIR/summaries/<model>/<family>.json   a learning session's result
    RUN_DIR/summaries/<model>/<family>.lock   held by the one process learning it
    RUN_DIR/summaries/<model>/<family>/       the session's records (an `EpisodeDir`, whose
                                              result is LEARNING_RESULT, learning.json)
    RUN_DIR/annotations/<annotator>.jsonl     judgments (`vabench.diagnostics.store`)
    RUN_DIR/report/                    report.md, report.html, <section>.md, <table>.csv,
                                       figures/*.png (`vabench.report.build`)
    RUN_DIR/logs/worker_<pid>.log      an engine worker process's log (the processes executor;
                                       a Ray engine's: worker_<host>-<pid>.log)
    RUN_DIR/logs/sweep.log             SWEEP_LOG: the command's whole log (the terminal shows
                                       the researcher's lines; statistics are kept here)
    RUN_DIR/logs/clock.json            CLOCK: the seconds the sweep's invocations have run

Paths are `Path`s; the one path recorded as text, the ledger's `episode_dir`, is
`episode_rel`'s POSIX string relative to the run directory, so a run directory moved or mounted
elsewhere still reads. The bottom layer: nothing here imports vabench.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

# The public str constants below are the names of the run directory (the layering test reads
# them from this module): file names, folder names, and prefixes of numbered folders and files
# (ending in "_"). Suffixes of names made from values (<family>.json) live in the functions.

CONFIG = "sweep.yaml"
PLAN = "plan.json"
RESULTS = "results.jsonl"
INFRASTRUCTURE = "infrastructure.jsonl"
DUPLICATES = "results.duplicates.jsonl"
EPISODES = "episodes"
SUMMARIES = "summaries"
ANNOTATIONS = "annotations"
REPORT = "report"
LOGS = "logs"
WORKER_LOG_PREFIX = "worker_"
SWEEP_LOG = "sweep.log"
CLOCK = "clock.json"

EVENTS = "events.jsonl"
RESULT = "result.json"
LEARNING_RESULT = "learning.json"
FRAMES = "frames"
SEED_PREFIX = "seed_"
RUN_PREFIX = "run_"
STEP_PREFIX = "step_"
PARTIAL_PREFIX = "partial_"
ATTEMPT_PREFIX = "attempt_"

REPORT_MD = "report.md"
REPORT_HTML = "report.html"
FIGURES = "figures"


def episode_rel(model: str, track: str, task: str, seed: int, run: int) -> str:
    """An episode's directory relative to the run directory, as the ledger records it."""
    return f"{EPISODES}/{model}/{track}/{task}/{SEED_PREFIX}{seed}/{RUN_PREFIX}{run}"


def episode_id(rel: str) -> str:
    """The viewer's and the annotations' id of an episode: `episode_rel` without `episodes/`."""
    return rel.removeprefix(f"{EPISODES}/")


def frame_path(step: int, view: str | None = None, index: int | None = None) -> str:
    """A model image's path relative to its episode directory, as the events record it:
    `frames/step_NNN.jpg` (NNN the step of the observation that showed it, the numbering the
    model uses in camera.history), or `frames/step_NNN_K_<view>.jpg` for image K of a passive
    bundle."""
    stem = f"{STEP_PREFIX}{step:03d}"
    name = f"{stem}.jpg" if index is None else f"{stem}_{index}_{view}.jpg"
    return f"{FRAMES}/{name}"


def annotation_name(annotator: str) -> str:
    """The file name of an annotator's judgments in RUN_DIR/annotations/."""
    return f"{annotator}.jsonl"


def _numbered(directory: Path, prefix: str) -> Path:
    """`directory/<prefix><n>` for the first n from 1 that does not exist yet."""
    n = 1
    while (directory / f"{prefix}{n}").exists():
        n += 1
    return directory / f"{prefix}{n}"


@dataclass(frozen=True)
class EpisodeDir:
    """The directory an `EpisodeRecorder` writes: an episode's, or a learning session's."""

    path: Path

    @property
    def events(self) -> Path:
        return self.path / EVENTS

    @property
    def result(self) -> Path:
        return self.path / RESULT

    @property
    def learning_result(self) -> Path:
        return self.path / LEARNING_RESULT

    @property
    def frames(self) -> Path:
        return self.path / FRAMES

    def finished(self) -> bool:
        """Whether the attempt recorded here ended with a result (an episode's or a
        learning session's)."""
        return self.result.exists() or self.learning_result.exists()

    def next_partial(self) -> Path:
        """Where an interrupted attempt's events and frames go aside: `partial_<n>/`."""
        return _numbered(self.path, PARTIAL_PREFIX)

    def next_attempt(self) -> Path:
        """Where a finished attempt that is run again goes aside: `attempt_<n>/`."""
        return _numbered(self.path, ATTEMPT_PREFIX)

    @property
    def attempt_files(self) -> tuple[Path, ...]:
        """What an attempt leaves here: its result, events and frames."""
        return (self.result, self.events, self.frames)


@dataclass(frozen=True)
class RunDir:
    """A sweep's run directory (see the module docstring)."""

    path: Path

    @property
    def config(self) -> Path:
        return self.path / CONFIG

    @property
    def plan(self) -> Path:
        return self.path / PLAN

    @property
    def results(self) -> Path:
        return self.path / RESULTS

    @property
    def infrastructure(self) -> Path:
        return self.path / INFRASTRUCTURE

    @property
    def duplicates(self) -> Path:
        return self.path / DUPLICATES

    @property
    def episodes(self) -> Path:
        return self.path / EPISODES

    def episode(self, model: str, track: str, task: str, seed: int, run: int) -> EpisodeDir:
        return EpisodeDir(self.path / episode_rel(model, track, task, seed, run))

    @property
    def summaries(self) -> Path:
        return self.path / SUMMARIES

    def summary(self, model: str, family: str) -> Path:
        """The stored `LearningResult` of (model, family)."""
        return self.summaries / model / f"{family}.json"

    def summary_files(self) -> list[Path]:
        """Every stored `LearningResult` (`summary`), RUN_DIR/summaries/<model>/<family>.json,
        sorted. A model name may hold slashes (`vendor/model`: folders within folders), so a
        summary is not always one folder down; beside each lies its session's folder, whose
        results (`LEARNING_RESULT`, `RESULT` in set-aside attempts) are second copies of the same
        session: read, they would list every session twice. Those are the only other .json
        files under summaries/."""
        if not self.summaries.is_dir():
            return []
        copies = (LEARNING_RESULT, RESULT)
        return sorted(p for p in self.summaries.rglob("*.json") if p.name not in copies)

    def summary_lock(self, model: str, family: str) -> Path:
        """The file lock held by the one process learning (model, family)."""
        return self.summaries / model / f"{family}.lock"

    def learning_session(self, model: str, family: str) -> EpisodeDir:
        """The records of (model, family)'s learning session."""
        return EpisodeDir(self.summaries / model / family)

    @property
    def annotations(self) -> Path:
        return self.path / ANNOTATIONS

    def annotation_file(self, annotator: str) -> Path:
        return self.annotations / annotation_name(annotator)

    def annotation_files(self) -> list[Path]:
        """Every annotator's judgments, sorted."""
        return sorted(self.annotations.glob(annotation_name("*")))

    @property
    def report(self) -> Path:
        return self.path / REPORT

    @property
    def logs(self) -> Path:
        return self.path / LOGS

    @property
    def sweep_log(self) -> Path:
        return self.logs / SWEEP_LOG

    @property
    def clock(self) -> Path:
        return self.logs / CLOCK

    def worker_log(self, pid: int | str) -> Path:
        """The log of the engine worker process `pid` (its tasks' stage and host lines; a Ray
        engine's is named by its host and pid)."""
        return self.logs / f"{WORKER_LOG_PREFIX}{pid}.log"
