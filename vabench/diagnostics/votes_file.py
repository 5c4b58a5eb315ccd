"""The agreement table of a votes file alone, without a run directory:
`python -m vabench.diagnostics agreement VOTES.csv`.

Annotation done elsewhere (another tool, a spreadsheet, the paper's own judgments) need not
match the episodes of a run, so this reads nothing but the file. Its rows are read as an
import reads them (`csv_io.read_rows`: `annotator`, `episode` or `item`, `item` or
`criterion`, `value`, optional `time`), in any order; of several rows for one annotator,
episode and item the latest counts (by `time`, then the later row). The table is the run's
(`sections.agreement_of`, the paper's rules, docs/DIAGNOSTICS.md), with one difference the
file's shape allows: gates are optional. Where an episode has votes on a gate, their majority
decides as always (0: its criteria are NA, judgments on them left out); where it has none, a
gated criterion counts wherever it was judged, and a criterion nobody judged (an empty or NA
value) is NA (`aggregate.collect_votes`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

from vabench.diagnostics import aggregate as agg
from vabench.diagnostics.criteria import CRITERIA, GATE_CODES
from vabench.diagnostics.csv_io import CsvImportError, in_file_order, read_rows
from vabench.diagnostics.sections import agreement_of
from vabench.diagnostics.store import Judgment, Key, current
from vabench.tables import Section

LEAD = "no agreement computed"


def agreement_from_csv(path: Path) -> Section:
    """The agreement section of the votes in `path`; CsvImportError naming every bad row."""
    rows, problems = read_rows(path, LEAD)
    if problems:
        raise CsvImportError(in_file_order(problems), lead=LEAD)
    judgments = [
        Judgment(
            r.annotator,
            r.episode,
            r.item,
            r.value,
            math.inf if r.time is None else r.time,  # no time: after every timed row
            line=r.n,
        )
        for r in rows
    ]
    state = current(judgments)
    if not state:
        raise CsvImportError([f"{path}: no judgment (no row with a value of 0 or 1)"], lead=LEAD)
    votes = agg.votes_of(state)
    collected = agg.collect_votes(votes, gates_optional=True)
    return agreement_of(collected, _notes(path, len(rows), state, votes, collected))


def _notes(
    path: Path,
    n_rows: int,
    state: Mapping[Key, Judgment],
    votes: agg.Votes,
    collected: agg.Collected,
) -> list[str]:
    annotators = sorted({a for _, a, _ in state})
    notes = [
        f"{path.name}: {len(state)} judgments in force by {len(annotators)} annotators "
        f"({', '.join(annotators)}) on {len(votes)} episodes"
    ]
    if (not_counted := n_rows - len(state)) > 0:
        notes.append(
            f"{not_counted} rows not counted: withdrawn (empty or NA) or superseded by a later "
            "row of the same annotator, episode and item"
        )
    gated = sorted({c.gate for c in CRITERIA.values() if c.gate is not None})
    with_gates = sum(any(g in judged for g in GATE_CODES) for judged in votes.values())
    rule = "a gated criterion (" + "; ".join(
        f"{g}: {', '.join(k for k, c in CRITERIA.items() if c.gate == g)}" for g in gated
    )
    if not with_gates:
        notes.append(f"no gate votes: {rule}) counts wherever it was judged")
    elif with_gates == len(votes):
        notes.append("gate votes on every episode: their majority decides, 0 makes NA")
    else:
        notes.append(
            f"gate votes on {with_gates} of {len(votes)} episodes decide there by majority; "
            f"elsewhere {rule}) counts wherever it was judged"
        )
    na = sum(i.status == "na" for i in collected.items)
    if na:
        notes.append(
            f"{na} episode-criterion items NA (majority gate 0), {collected.dropped} judgments "
            "on them left out"
        )
    return notes
