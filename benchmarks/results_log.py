"""Dated benchmark figures: one JSON file a topic under benchmarks/results/.

A file is `{"topic": NAME, "records": [RECORD, ...]}`. A record names its `figure`, `value`,
`unit`, `machine`, `date` (YYYY-MM-DD), `command` and a one-line `note`; it may carry the
`baseline` it was measured against, the `ratio` value / baseline, and the `commit`.
docs/PERFORMANCE.md shows the newest figure of each thing; `benchmarks/history.py` prints the
history. A benchmark's `--record` flag calls `append`, which checks the record and replaces the
file atomically (a temporary file beside it, then `os.replace`), so a reader never sees half a
file and a bad record never lands.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

RESULTS_DIR = Path(__file__).resolve().parent / "results"
REQUIRED = ("figure", "value", "unit", "machine", "date", "command", "note")
OPTIONAL = ("baseline", "ratio", "commit")
_TOPIC = re.compile(r"[a-z][a-z0-9_]*")
_COMMIT = re.compile(r"[0-9a-f]{7,40}")


class RecordError(ValueError):
    """A record or results file that does not follow the format above."""


def _text(record: dict, field: str, where: str) -> None:
    value = record[field]
    if not isinstance(value, str) or not value.strip() or "\n" in value:
        raise RecordError(f"{where}: {field!r} must be one non-empty line of text, got {value!r}")


def _number(record: dict, field: str, where: str) -> None:
    value = record[field]
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok:
        raise RecordError(f"{where}: {field!r} must be a finite number, got {value!r}")


def check_record(record: Any, where: str = "record") -> dict:
    """The record itself if it follows the format; else RecordError naming the field."""
    if not isinstance(record, dict):
        raise RecordError(f"{where}: a record is a JSON object, got {type(record).__name__}")
    missing = [f for f in REQUIRED if f not in record]
    if missing:
        raise RecordError(f"{where}: missing {', '.join(map(repr, missing))}; required: {REQUIRED}")
    unknown = sorted(set(record) - set(REQUIRED) - set(OPTIONAL))
    if unknown:
        raise RecordError(
            f"{where}: unknown field {unknown[0]!r}; the fields are {REQUIRED + OPTIONAL}"
        )
    for field in ("figure", "unit", "machine", "command", "note"):
        _text(record, field, where)
    _number(record, "value", where)
    try:
        datetime.date.fromisoformat(record["date"])
    except (TypeError, ValueError):
        raise RecordError(
            f"{where}: 'date' must be YYYY-MM-DD (the day measured), got {record['date']!r}"
        ) from None
    if record.get("baseline") is not None:
        _text(record, "baseline", where)
    if record.get("ratio") is not None:
        _number(record, "ratio", where)
        if record.get("baseline") is None:
            raise RecordError(f"{where}: a 'ratio' needs the 'baseline' it is measured against")
    commit = record.get("commit")
    if commit is not None and not (isinstance(commit, str) and _COMMIT.fullmatch(commit)):
        raise RecordError(f"{where}: 'commit' must be 7-40 hex digits or null, got {commit!r}")
    return record


def read_topic(path: Path) -> list[dict]:
    """The checked records of one results file."""
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise RecordError(f"{path}: not JSON ({err})") from None
    if not isinstance(data, dict) or data.get("topic") != Path(path).stem:
        raise RecordError(f"{path}: must be an object whose 'topic' is {Path(path).stem!r}")
    records = data.get("records")
    if not isinstance(records, list):
        raise RecordError(f"{path}: 'records' must be a list")
    return [check_record(r, f"{path}, record {i}") for i, r in enumerate(records)]


def append(topic: str, record: dict, results_dir: Path = RESULTS_DIR) -> Path:
    """Add one record to results_dir/<topic>.json, checked first, written atomically."""
    if not isinstance(topic, str) or not _TOPIC.fullmatch(topic):
        raise RecordError(f"topic must be lower-case letters, digits and '_', got {topic!r}")
    check_record(record, f"{topic}: new record")
    results_dir = Path(results_dir)
    results_dir.mkdir(parents=True, exist_ok=True)
    path = results_dir / f"{topic}.json"
    records = read_topic(path) if path.exists() else []
    records.append(record)
    text = json.dumps({"topic": topic, "records": records}, indent=1, ensure_ascii=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=results_dir, prefix=f".{topic}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def this_machine() -> str:
    """A short description of the machine running the benchmark: cores, CPU, GPU if any."""
    gpu = ""
    try:
        names = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.split("\n")
        names = [n.strip() for n in names if n.strip()]
        if names:
            gpu = f", {len(names)} x {names[0]}"
    except (OSError, subprocess.SubprocessError):
        pass
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()}-core {cpu}{gpu or ', no GPU'}"


def this_commit() -> str | None:
    """The checkout's commit (short), or None outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            cwd=Path(__file__).resolve().parent,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    return commit if out.returncode == 0 and _COMMIT.fullmatch(commit) else None


def this_command() -> str:
    return shlex.join(["python", *sys.argv])


def record(figure: str, value: float, unit: str, note: str, **extra: Any) -> dict:
    """A record of this run: today's date (UTC), this machine, command and commit."""
    out = {
        "figure": figure,
        "value": value,
        "unit": unit,
        "machine": this_machine(),
        "date": datetime.datetime.now(datetime.timezone.utc).date().isoformat(),
        "command": this_command(),
        "note": note,
        "commit": this_commit(),
    }
    out.update(extra)
    return out
