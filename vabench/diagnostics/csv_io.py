"""Annotations as CSV, one row per annotator x episode x item, for spreadsheets and for
annotation done elsewhere.

Columns: annotator, episode, item, value (0, 1, or empty for a withdrawn judgment), time
(seconds since the epoch; empty or absent on import means now), source, rubric, note.

Reading is lenient about the shape of a votes file made elsewhere (`read_rows`): headers in
any case; `criterion` for `item`; and where a `criterion` column names the criterion, `item`
for `episode` (the rated unit, in the words of agreement statistics). A value of `NA` reads
as no judgment, like an empty one. Criterion and gate codes in any case.

Export writes the judgments in force (or, with `history`, every line ever written). Import
checks every row first (unknown episode, unknown item, bad value, a criterion its gate does
not activate...) and writes nothing unless all rows are good; each problem names the row and
the column. Rows may come in any order: a gated criterion is checked against the gates as they
stand once the whole file is in, not against the rows above it. Importing the same file twice
changes nothing, with or without a `time` column: a row with a time is skipped when the same
judgment with the same time is already on disk; a row without one, when the judgment in force
has its value already (of several rows without a time for one annotator, episode and item, the
last counts, as the store's later line does). The work is one pass over the store and one over
the file (gate votes are indexed once, `GateVotes`), so 100,000 rows import in seconds.
"""

from __future__ import annotations

import csv
import io
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from vabench.diagnostics.criteria import GATES, ITEMS, RUBRIC_VERSION, gate_of
from vabench.diagnostics.store import (
    AnnotationError,
    AnnotationStore,
    GateVotes,
    Judgment,
    Key,
    check_annotator,
    current,
    inactive_reason,
)

COLUMNS = ("annotator", "episode", "item", "value", "time", "source", "rubric", "note")
NO_JUDGMENT = frozenset({"", "na", "n/a"})
"""Values that record no judgment (on import: withdraw one, if any is in force)."""
_ITEM_BY_LOWER = {code.lower(): code for code in ITEMS}
_SHOWN = 20
Problem = tuple[int, str]
"""(row, message naming the file, the row and the column)."""


class CsvImportError(ValueError):
    """Rows that cannot be read or imported: every problem, by row and column."""

    def __init__(self, problems: list[str], hints: list[str] | None = None, lead: str = ""):
        shown = problems[:_SHOWN] + (
            [f"... and {len(problems) - _SHOWN} more"] if len(problems) > _SHOWN else []
        )
        lead = lead or "nothing imported"
        super().__init__(f"{lead}:\n  " + "\n  ".join(shown + (hints or [])))
        self.problems = problems


@dataclass(frozen=True)
class CsvRow:
    n: int
    """The row's line in the file (1 is the header), for messages."""
    annotator: str
    episode: str
    item: str
    value: int | None
    time: float | None
    source: str
    rubric: str
    note: str | None

    @property
    def key(self) -> Key:
        return (self.episode, self.annotator, self.item)


@dataclass(frozen=True)
class _Columns:
    annotator: str
    episode: str
    item: str
    value: str
    extra: dict[str, str]
    """time, source, rubric, note -> the header that holds it, where present."""


def _columns(path: Path, header: list[str]) -> _Columns:
    """Which header holds what; CsvImportError saying what is missing, in plain words."""
    named = {h.strip().lower(): h for h in header}
    item = "criterion" if "criterion" in named else "item"
    episode = "episode" if "episode" in named else "item" if item == "criterion" else "episode"
    problems = []
    if "annotator" not in named:
        problems.append("no 'annotator' column (who gave each judgment)")
    if episode not in named:
        problems.append(
            "no 'episode' column (the episode each row judges; a column named 'item' is read "
            "as it when a 'criterion' column names the criterion)"
        )
    if item not in named:
        problems.append(
            "no 'item' or 'criterion' column (what each row judges: one of "
            + ", ".join(ITEMS)
            + ")"
        )
    elif item == "criterion" and episode == "episode" and "item" in named:
        problems.append(
            "both 'item' and 'criterion' columns beside 'episode': rename the one that is not "
            "the criterion"
        )
    if "value" not in named:
        problems.append("no 'value' column (1 = yes, 0 = no; empty or NA: no judgment)")
    if problems:
        found = ", ".join(repr(h) for h in header) or "nothing (an empty file?)"
        raise CsvImportError(
            [f"{path}: {p}" for p in problems], [f"the header holds {found}"], "cannot read"
        )
    extra: dict[str, str] = {
        c: named[c] for c in ("time", "source", "rubric", "note") if c in named
    }
    return _Columns(named["annotator"], named[episode], named[item], named["value"], extra)


def read_rows(path: Path, lead: str = "") -> tuple[list[CsvRow], list[Problem]]:
    """Every row of a votes file that reads, and the problems of the rows that do not
    (`file:row N: column: problem`). Raises CsvImportError when the file cannot be read or
    lacks a column."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise CsvImportError([f"{path}: cannot read: {err}"], lead=lead or "cannot read") from None
    reader = csv.DictReader(io.StringIO(text))
    cols = _columns(path, list(reader.fieldnames or []))
    rows: list[CsvRow] = []
    problems: list[Problem] = []
    for n, raw in enumerate(reader, 2):  # row 1 is the header
        where = f"{path}:row {n}"

        def cell(column: str | None, raw: dict[str, str] = raw) -> str:
            return "" if column is None else (raw.get(column) or "").strip()

        annotator, episode = cell(cols.annotator), cell(cols.episode)
        item_text, value_text = cell(cols.item), cell(cols.value)
        time_text = cell(cols.extra.get("time"))
        bad = []
        if not annotator:
            bad.append("annotator: empty (who gave this judgment?)")
        if not episode:
            bad.append(f"{cols.episode}: empty (which episode does this row judge?)")
        item = _ITEM_BY_LOWER.get(item_text.lower())
        if item is None:
            bad.append(f"{cols.item}: unknown criterion or gate {item_text!r}; valid: {ITEMS}")
        value: int | None = None
        if value_text in ("0", "1"):
            value = int(value_text)
        elif value_text.lower() not in NO_JUDGMENT:
            bad.append(
                f"value: expected 0, 1 or null, got {value_text!r} (null: empty or NA, no judgment)"
            )
        t: float | None = None
        if time_text:
            try:
                t = float(time_text)
            except ValueError:
                bad.append(f"time: {time_text!r} is not a number (seconds since the epoch)")
        if bad:
            problems += [(n, f"{where}: {b}") for b in bad]
            continue
        assert item is not None
        rows.append(
            CsvRow(
                n,
                annotator,
                episode,
                item,
                value,
                t,
                cell(cols.extra.get("source")) or "import",
                cell(cols.extra.get("rubric")),
                cell(cols.extra.get("note")) or None,
            )
        )
    return rows, problems


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
    """Check every row of `path`, then append them; returns (written, skipped: recorded
    already). Raises CsvImportError listing every problem (and writes nothing) otherwise."""
    rows, problems = read_rows(path)
    good, hints = _known(store, path, rows, problems)
    loaded = store.load().judgments
    written, skipped = _new_judgments(loaded, good)
    final = current([*loaded, *(j for _, j in written)])
    problems += _inactive(path, written, final)
    if problems:
        raise CsvImportError(in_file_order(problems), hints)
    store.append(j for _, j in written)
    return len(written), skipped


def _known(
    store: AnnotationStore, path: Path, rows: list[CsvRow], problems: list[Problem]
) -> tuple[list[CsvRow], list[str]]:
    """The rows of plain annotator names and scored episodes of the run; the others' problems
    go to `problems`, with an example of the run's episode ids when one is unknown."""
    good: list[CsvRow] = []
    hints: list[str] = []
    for r in rows:
        try:
            check_annotator(r.annotator)
            store.check_episode(r.episode)
        except AnnotationError as err:
            problems.append((r.n, f"{path}:row {r.n}: {err}"))
            if err.field == "episode" and not hints and store.index.episodes:
                example = next(iter(store.index.episodes))
                hints.append(f"episode ids of {store.index.run_dir} look like {example!r}")
            continue
        good.append(r)
    return good, hints


def _new_judgments(
    loaded: list[Judgment], rows: list[CsvRow]
) -> tuple[list[tuple[CsvRow, Judgment]], int]:
    """The judgments the rows add to `loaded` (the store's), and how many rows add nothing: a
    timed row whose very line is there, an untimed row whose value is in force already or that
    a later untimed row of the same key supersedes."""
    on_disk = {(j.annotator, j.episode, j.item, j.value, j.time) for j in loaded}
    first_line = max((j.line for j in loaded), default=0) + 1
    written: list[tuple[CsvRow, Judgment]] = []
    skipped = 0

    def add(r: CsvRow, t: float) -> None:
        line = first_line + len(written)  # after every line on disk: the later one in a tie
        rubric = r.rubric or RUBRIC_VERSION
        j = Judgment(r.annotator, r.episode, r.item, r.value, t, rubric, r.source, r.note, line)
        written.append((r, j))

    for r in sorted((r for r in rows if r.time is not None), key=lambda r: (r.time, r.n)):
        assert r.time is not None
        identity = (r.annotator, r.episode, r.item, r.value, r.time)
        if identity in on_disk:
            skipped += 1
            continue
        on_disk.add(identity)
        add(r, r.time)
    untimed: dict[Key, CsvRow] = {}
    for r in rows:
        if r.time is None:
            skipped += r.key in untimed
            untimed[r.key] = r
    if untimed:
        state = current([*loaded, *(j for _, j in written)])
        now = time.time()
        for r in untimed.values():
            held = state.get(r.key)
            if (None if held is None else held.value) == r.value:
                skipped += 1
            else:
                add(r, now)
    return written, skipped


def _inactive(
    path: Path, written: list[tuple[CsvRow, Judgment]], final: Mapping[Key, Judgment]
) -> list[Problem]:
    """Rows of gated criteria that the gates do not activate once the file is in."""
    gates = GateVotes(final)
    problems = []
    for r, j in written:
        gate = gate_of(j.item)
        if gate is None or j.value is None or final.get(r.key) is not j:
            continue  # always applicable, a withdrawal, or superseded: nothing to activate
        remedy = (
            f"add a row {r.annotator},{r.episode},{gate},1 if the answer to "
            f"{GATES[gate].question!r} is yes (rows may come in any order)"
        )
        votes = gates.of(j.episode, gate)
        if why := inactive_reason(j.item, j.episode, j.annotator, votes, remedy):
            problems.append((r.n, f"{path}:row {r.n}: item: {why}"))
    return problems


def in_file_order(problems: list[Problem]) -> list[str]:
    """The messages, by row (problems are found in several passes)."""
    return [text for _, text in sorted(problems, key=lambda p: p[0])]
