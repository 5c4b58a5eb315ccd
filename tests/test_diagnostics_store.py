"""Annotations on a real smoke run: append-only judgments that supersede, withdrawals, the
activation rule of the gates, one clear message per bad input, malformed lines reported and
skipped, concurrent writers losing nothing, CSV export and import, the command line."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from diag_util import ACTIVE, PASSIVE, REPO, copy_run

from vabench.diagnostics.__main__ import main
from vabench.diagnostics.csv_io import CsvImportError, export_csv, import_csv
from vabench.diagnostics.episodes import RunIndex
from vabench.diagnostics.store import AnnotationError, AnnotationStore


@pytest.fixture
def run(tmp_path_factory, tmp_path):
    return copy_run(tmp_path_factory.getbasetemp(), tmp_path / "run")


@pytest.fixture
def store(run):
    return AnnotationStore(RunIndex.load(run))


def lines(store, annotator):
    return store.path(annotator).read_text().splitlines()


def test_later_judgments_supersede_and_nothing_is_rewritten(store):
    store.record("alice", ACTIVE, "TL", 1)
    first = lines(store, "alice")
    store.record("alice", ACTIVE, "TL", 0)
    assert store.state()[(ACTIVE, "alice", "TL")].value == 0
    store.record("alice", ACTIVE, "TL", None)  # withdrawn
    assert (ACTIVE, "alice", "TL") not in store.state()
    now = lines(store, "alice")
    assert now[:1] == first and len(now) == 3
    record = json.loads(now[1])
    assert record == {
        **record,
        "v": 1,
        "annotator": "alice",
        "episode": ACTIVE,
        "item": "TL",
        "value": 0,
        "rubric": "va-bench-rubric-1",
        "source": "human",
    }
    assert isinstance(record["time"], float)


def test_gates_activate_criteria(store):
    with pytest.raises(AnnotationError, match="criterion ED is not activated") as err:
        store.record("alice", ACTIVE, "ED", 1)
    assert err.value.field == "item"
    store.record("alice", ACTIVE, "gate_error", 1)
    store.record("alice", ACTIVE, "ED", 1)  # own gate
    with pytest.raises(AnnotationError, match="AE is not activated"):
        store.record("bob", ACTIVE, "AE", 0)
    store.record("bob", ACTIVE, "gate_error", 0)
    store.record("carol", ACTIVE, "gate_error", 1)
    store.record("bob", ACTIVE, "ED", 0)  # bob voted 0, but the majority (2 of 3) is 1
    store.record("bob", ACTIVE, "TL", 1)  # TL, SR, MS, MP, FG always apply


@pytest.mark.parametrize(
    ("args", "field", "words"),
    [
        (("alice", "nope/episode", "TL", 1), "episode", "unknown episode 'nope/episode'"),
        (("alice", ACTIVE, "XX", 1), "item", "unknown criterion or gate 'XX'"),
        (("alice", ACTIVE, "TL", 2), "value", "expected 0, 1 or null"),
        (("<b>eve</b>", ACTIVE, "TL", 1), "annotator", "not a plain name"),
        (("../eve", ACTIVE, "TL", 1), "annotator", "not a plain name"),
    ],
)
def test_bad_input_gets_one_message_naming_the_field(store, args, field, words):
    with pytest.raises(AnnotationError) as err:
        store.record(*args)
    assert err.value.field == field and words in str(err.value)
    assert not store.directory.exists() or not list(store.directory.iterdir())


def test_malformed_lines_are_reported_and_skipped(run, store, capsys):
    store.record("alice", ACTIVE, "TL", 1)
    store.record("alice", PASSIVE, "TL", 0)
    with open(store.path("alice"), "a") as f:
        f.write("{not json\n")
        f.write(
            json.dumps(
                {"annotator": "alice", "episode": ACTIVE, "item": "SR", "value": 7, "time": 1.0}
            )
            + "\n"
        )
        f.write(
            json.dumps(
                {"annotator": "bob", "episode": ACTIVE, "item": "SR", "value": 1, "time": 1.0}
            )
            + "\n"
        )
        f.write(
            json.dumps(
                {"annotator": "alice", "episode": "x/y", "item": "SR", "value": 1, "time": 1.0}
            )
            + "\n"
        )
        f.write('{"annotator": "alice", "episode"')  # a write cut short
    loaded = store.load()
    assert len(loaded.judgments) == 2
    problems = "\n".join(loaded.problems)
    assert len(loaded.problems) == 5
    for words in (
        "alice.jsonl:3: not valid JSON",
        "alice.jsonl:4: value: expected 0, 1",
        "alice.jsonl:5: annotator: 'bob' in the file of 'alice'",
        "alice.jsonl:6: episode: unknown episode 'x/y'",
        "alice.jsonl:7: a truncated last line",
    ):
        assert words in problems
    assert main([str(run)]) == 0  # the statistics still run
    out, err = capsys.readouterr()
    assert "| local | active | 1 | 100.00 |" in out and "alice.jsonl:4" in err


WRITER = """
import sys
from vabench.diagnostics.episodes import RunIndex
from vabench.diagnostics.store import AnnotationStore
store = AnnotationStore(RunIndex.load(sys.argv[1]))
for i in range(int(sys.argv[3])):
    store.record(sys.argv[2], sys.argv[4], "TL", i % 2)
"""


def test_concurrent_writers_lose_nothing(run, store):
    n = 60
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(run), who, str(n), ep], cwd=REPO)
        for who, ep in (("alice", ACTIVE), ("alice", PASSIVE), ("bob", ACTIVE))
    ]
    assert [p.wait(timeout=120) for p in procs] == [0, 0, 0]
    loaded = store.load()
    assert loaded.problems == [] and len(loaded.judgments) == 3 * n
    assert len(lines(store, "alice")) == 2 * n
    assert store.state()[(ACTIVE, "bob", "TL")].value == (n - 1) % 2


def test_csv_round_trip(tmp_path, run, store, tmp_path_factory):
    store.record("alice", ACTIVE, "gate_error", 1)
    store.record("alice", ACTIVE, "ED", 1)
    store.record("bob", PASSIVE, "MS", 0)
    text = export_csv(store)
    assert text.splitlines()[0] == "annotator,episode,item,value,time,source,rubric,note"
    path = tmp_path / "a.csv"
    path.write_text(text)
    other = AnnotationStore(
        RunIndex.load(copy_run(tmp_path_factory.getbasetemp(), tmp_path / "other"))
    )
    assert import_csv(other, path) == (3, 0)
    assert {k: j.value for k, j in other.state().items()} == {
        k: j.value for k, j in store.state().items()
    }
    assert import_csv(other, path) == (0, 3)  # idempotent
    assert main(["export", str(run), "--out", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "b.csv").read_text() == text


def test_csv_import_checks_every_row_and_writes_nothing_on_error(tmp_path, store):
    path = tmp_path / "bad.csv"
    path.write_text(
        "annotator,episode,item,value\n"
        f"alice,{ACTIVE},TL,1\n"
        f"alice,{ACTIVE},OC,1\n"
        f"alice,nope,TL,1\n"
        f"alice,{ACTIVE},TL,yes\n"
    )
    with pytest.raises(CsvImportError) as err:
        import_csv(store, path)
    text = str(err.value)
    assert "row 3: item: criterion OC is not activated" in text
    assert "row 4: episode: unknown episode 'nope'" in text
    assert "row 5: value: expected 0, 1 or null, got 'yes'" in text
    assert not store.directory.exists()
    (tmp_path / "cols.csv").write_text("who,episode,item,value\n")
    with pytest.raises(CsvImportError, match="no 'annotator' column"):
        import_csv(store, tmp_path / "cols.csv")


def test_command_line_bad_input(tmp_path, run, capsys):
    assert main([str(tmp_path / "nowhere")]) == 2
    assert "nowhere: no such directory" in capsys.readouterr().err
    assert main([str(run)]) == 1
    assert "no annotations in" in capsys.readouterr().err
    assert main(["judge", str(run), "--model", "nope"]) == 2
    assert "--model: 'nope' is not in" in capsys.readouterr().err
    assert main(["judge", str(run), "--model", "local", "--episodes", "x/y"]) == 2
    assert "unknown episode 'x/y'" in capsys.readouterr().err
