"""Annotations as CSV, one row per annotator x episode x item, for spreadsheets and for
annotation done elsewhere.

Columns: annotator, episode, item, value (0, 1, or empty for a withdrawn judgment), time
(seconds since the epoch; empty on import means now), source, rubric, note.

Export writes the judgments in force (or, with `history`, every line ever written). Import
checks every row first (unknown episode, unknown item, bad value, a criterion its gate does
not activate...) and writes nothing unless all rows are good; each problem names the row and
the column. A row equal to the judgment already in force is skipped, so importing the same
file twice changes nothing.
"""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

from vabench.diagnostics.store import AnnotationError, AnnotationStore, Judgment, current

COLUMNS = ("annotator", "episode", "item", "value", "time", "source", "rubric", "note")
REQUIRED = ("annotator", "episode", "item", "value")


class CsvImportError(ValueError):
    def __init__(self, problems: list[str]):
        shown = problems[:20] + (
            [f"... and {len(problems) - 20} more"] if len(problems) > 20 else []
        )
        super().__init__("nothing imported:\n  " + "\n  ".join(shown))
        self.problems = problems


def export_csv(store: AnnotationStore, history: bool = False) -> str:
    loaded = store.load()
    rows = loaded.judgments if history else list(current(loaded.judgments).values())
    rows = sorted(rows, key=lambda j: (j.episode, j.annotator, j.time, j.line))
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    for j in rows:
        value = "" if j.value is None else j.value
        writer.writerow(
            [j.annotator, j.episode, j.item, value, repr(j.time), j.source, j.rubric, j.note or ""]
        )
    return buf.getvalue()


def import_csv(store: AnnotationStore, path: Path) -> tuple[int, int]:
    """Check every row of `path`, then append them; returns (written, skipped as already in
    force). Raises CsvImportError listing every problem (and writes nothing) otherwise."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as err:
        raise CsvImportError([f"{path}: cannot read: {err.strerror or err}"]) from None
    reader = csv.DictReader(io.StringIO(text))
    missing = [c for c in REQUIRED if c not in (reader.fieldnames or [])]
    if missing:
        raise CsvImportError([f"{path}: missing column {missing[0]!r} (columns: {list(COLUMNS)})"])
    now = time.time()
    parsed: list[tuple[int, dict[str, str], float]] = []
    problems: list[str] = []
    for n, row in enumerate(reader, 2):  # row 1 is the header
        raw_time = (row.get("time") or "").strip()
        try:
            t = float(raw_time) if raw_time else now
        except ValueError:
            problems.append(f"{path}:row {n}: time: {raw_time!r} is not a number")
            continue
        parsed.append((n, row, t))
    state = current(store.load().judgments)
    batch: list[Judgment] = []
    skipped = 0
    for n, row, t in sorted(parsed, key=lambda p: (p[2], p[0])):  # gates before what they gate
        raw = (row.get("value") or "").strip()
        value: object = None if raw == "" else int(raw) if raw in ("0", "1") else raw
        try:
            j = store.check(row.get("annotator"), row.get("episode"), row.get("item"), value, state)
        except AnnotationError as err:
            problems.append(f"{path}:row {n}: {err}")
            continue
        key = (j.episode, j.annotator, j.item)
        held = state.get(key)
        if held is not None and held.value == j.value and held.time == t:
            skipped += 1
            continue
        j = Judgment(
            j.annotator,
            j.episode,
            j.item,
            j.value,
            t,
            row.get("rubric") or j.rubric,
            row.get("source") or "import",
            row.get("note") or None,
        )
        if j.value is None:
            state.pop(key, None)
        else:
            state[key] = j
        batch.append(j)
    if problems:
        raise CsvImportError(problems)
    store.append(batch)
    return len(batch), skipped
