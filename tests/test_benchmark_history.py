"""The benchmark history (benchmarks/results_log.py, benchmarks/history.py) and the figures
page's references: records written with the writer read back through history's functions, a
bad record refused with the field named, every shipped results file well formed, and every
`docs/PERFORMANCE.md, "Section"` in the repository naming a heading of the page."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import history  # noqa: E402
import results_log  # noqa: E402


def _record(**changes):
    base = {
        "figure": "pool calls/s at L = 5 s, C = 1,000",
        "value": 199.9,
        "unit": "calls/s",
        "machine": "2-core CPU",
        "date": "2026-11-21",
        "command": "python benchmarks/llm_pool.py --concurrency 1000",
        "note": "one line",
        "baseline": "ideal C/L",
        "ratio": 0.9995,
    }
    base.update(changes)
    return base


def test_records_written_are_read_back_in_date_order(tmp_path):
    results_log.append("llm_pool", _record(date="2026-11-25", value=180.0), tmp_path)
    results_log.append("llm_pool", _record(date="2026-11-21"), tmp_path)
    results_log.append(
        "limits", _record(figure="busiest window", unit="x limit", value=1.0), tmp_path
    )

    records = history.load(tmp_path)
    assert {r["topic"] for r in records} == {"llm_pool", "limits"}
    found = history.matching(records, "POOL CALLS")
    assert [(r["date"], r["value"]) for r in found] == [
        ("2026-11-21", 199.9),
        ("2026-11-25", 180.0),
    ]
    assert history.figure_names(records) == [
        ("limits", "busiest window", 1),
        ("llm_pool", "pool calls/s at L = 5 s, C = 1,000", 2),
    ]
    rows = history.table(found).splitlines()
    assert len(rows) == 3 and rows[1].startswith("2026-11-21") and "199.9 calls/s" in rows[1]
    assert "1x ideal C/L" in rows[1]  # the ratio, then its baseline


def test_the_command_prints_matches_and_lists_figures(tmp_path, capsys):
    results_log.append("llm_pool", _record(), tmp_path)
    assert history.main(["C = 1,000", "--dir", str(tmp_path), "--verbose"]) == 0
    out = capsys.readouterr().out
    assert "$ python benchmarks/llm_pool.py --concurrency 1000" in out
    assert history.main(["--list", "--dir", str(tmp_path)]) == 0
    assert "llm_pool" in capsys.readouterr().out
    assert history.main(["no such figure", "--dir", str(tmp_path)]) == 1
    assert "--list" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"value": "fast"}, "'value' must be a finite number"),
        ({"value": float("nan")}, "'value' must be a finite number"),
        ({"date": "27 Nov"}, "'date' must be YYYY-MM-DD"),
        ({"note": "two\nlines"}, "'note' must be one non-empty line"),
        ({"speed": 3}, "unknown field 'speed'"),
        ({"baseline": None}, "a 'ratio' needs the 'baseline'"),
        ({"commit": "HEAD"}, "'commit' must be 7-40 hex digits"),
    ],
)
def test_a_malformed_record_is_refused_naming_its_field(tmp_path, changes, message):
    with pytest.raises(results_log.RecordError, match=re.escape(message)):
        results_log.append("llm_pool", _record(**changes), tmp_path)
    assert not (tmp_path / "llm_pool.json").exists()  # nothing written


def test_a_missing_field_is_named(tmp_path):
    record = _record()
    del record["machine"]
    with pytest.raises(results_log.RecordError, match="missing 'machine'"):
        results_log.append("llm_pool", record, tmp_path)


def test_a_refused_record_leaves_the_file_as_it_was(tmp_path):
    path = results_log.append("llm_pool", _record(), tmp_path)
    before = path.read_text()
    with pytest.raises(results_log.RecordError):
        results_log.append("llm_pool", _record(unit=""), tmp_path)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["llm_pool.json"]  # no temporary left


def test_a_broken_results_file_is_named(tmp_path):
    (tmp_path / "llm_pool.json").write_text(json.dumps({"topic": "llm_pool", "records": [{}]}))
    with pytest.raises(results_log.RecordError, match=r"llm_pool\.json, record 0: missing"):
        history.load(tmp_path)


def test_every_shipped_results_file_parses_with_the_required_fields():
    paths = sorted((ROOT / "benchmarks" / "results").glob("*.json"))
    assert paths, "benchmarks/results/ holds the history of the figures page"
    for path in paths:
        records = results_log.read_topic(path)  # raises naming the file and record
        assert records, f"{path.name} has no records"
        for record in records:
            assert all(field in record for field in results_log.REQUIRED), path.name


PAGE = ROOT / "docs" / "PERFORMANCE.md"
REFERENCE = re.compile(r"PERFORMANCE\.md(?:\]\([^)]*\))?\)?[\s#,]*([\"'])([^\"'\n]+)\1")
"""`docs/PERFORMANCE.md, "Section"`, `[PERFORMANCE.md](PERFORMANCE.md), "Section"`,
`docs/PERFORMANCE.md "Section"` or with single quotes, across a comment's line break too."""


def _headings() -> set[str]:
    return {
        line.lstrip("#").strip() for line in PAGE.read_text().splitlines() if line.startswith("#")
    }


def _references() -> list[tuple[str, str]]:
    found = []
    paths = [ROOT / "README.md", ROOT / "CHANGELOG.md"]
    for folder, pattern in [
        ("vabench", "*.py"),
        ("docs", "*.md"),
        ("benchmarks", "*.py"),
        ("benchmarks", "*.sh"),
        ("tests", "*.py"),
        ("configs", "*.yaml"),
    ]:
        paths.extend(sorted((ROOT / folder).rglob(pattern)))
    for path in paths:
        if path in (PAGE, Path(__file__).resolve()) or not path.is_file():
            continue
        text = path.read_text(errors="replace")
        for match in REFERENCE.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            found.append((f"{path.relative_to(ROOT)}:{line}", match.group(2)))
    return found


def test_the_reference_pattern_reads_each_form():
    text = (
        'docs/PERFORMANCE.md, "Renderer"; [PERFORMANCE.md](PERFORMANCE.md), "Soak" and '
        "(docs/PERFORMANCE.md\n    # 'Episode engine')"
    )
    assert [m.group(2) for m in REFERENCE.finditer(text)] == ["Renderer", "Soak", "Episode engine"]


def test_every_reference_to_the_figures_page_names_one_of_its_headings():
    headings = _headings()
    references = _references()
    assert references, "the code cites the figures page by section"
    wrong = [f"{where}: {name!r}" for where, name in references if name not in headings]
    assert not wrong, "sections not on docs/PERFORMANCE.md:\n" + "\n".join(wrong)
