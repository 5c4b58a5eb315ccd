"""Getting votes in: a plain votes file imports in any row order, twice changes
nothing with or without times, a missing gate is explained in words, the import's work grows
with the rows (not rows x store), and `python -m vabench.diagnostics agreement VOTES.csv`
computes the agreement table from the file alone.

The run directories here are hand-made results.jsonl files (RunIndex needs nothing else), so
the tests run in seconds without a sweep."""

from __future__ import annotations

import json
import sys
from fractions import Fraction
from pathlib import Path

import pytest

from vabench.diagnostics import aggregate as agg
from vabench.diagnostics.__main__ import main
from vabench.diagnostics.csv_io import CsvImportError, export_csv, import_csv
from vabench.diagnostics.episodes import RunIndex
from vabench.diagnostics.store import AnnotationStore

TASK = "grasp_single_cube"
ITEMS = ("gate_error", "gate_ambiguity", "TL", "AE", "SR", "MS", "MP", "FG", "ED", "OC", "PF")


def episode(k: int) -> str:
    return f"m/active/{TASK}/seed_{1000 + k}/run_1"


def make_run(path: Path, n_episodes: int) -> Path:
    """A run directory of `n_episodes` scored episodes of model m, track active."""
    path.mkdir(parents=True)
    lines = [
        {
            "v": 1,
            "track": "active",
            "episode_dir": f"episodes/{episode(k)}",
            "task": TASK,
            "seed": 1000 + k,
            "model": "m",
            "protocol": "active",
            "run": 1,
            "status": "failure",
            "success": False,
            "stop_reason": "budget_exhausted",
            "step_budget": 5,
            "n_checkpoints": 2,
        }
        for k in range(n_episodes)
    ]
    (path / "results.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    return path


def store_of(run: Path) -> AnnotationStore:
    return AnnotationStore(RunIndex.load(run))


def lines_on_disk(store: AnnotationStore) -> int:
    return sum(len(p.read_text().splitlines()) for p in store.directory.glob("*.jsonl"))


def write_csv(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text(header + "\n" + "".join(r + "\n" for r in rows))
    return path


@pytest.fixture
def run(tmp_path):
    return make_run(tmp_path / "run", 4)


# -- import ---------------------------------------------------------------------------------


def test_a_plain_votes_file_imports_with_criteria_before_their_gates(tmp_path, run):
    # `criterion` for `item`, and ED listed before the error gate that activates it
    path = write_csv(
        tmp_path / "votes.csv",
        "annotator,episode,criterion,value",
        [
            f"a1,{episode(0)},ED,1",
            f"a1,{episode(0)},TL,1",
            f"a1,{episode(0)},gate_error,1",
            f"a2,{episode(0)},ed,0",  # codes in any case
            f"a2,{episode(0)},gate_error,0",  # a2 saw no error; the majority (2 of 3) did
            f"a3,{episode(0)},gate_error,1",
        ],
    )
    store = store_of(run)
    assert import_csv(store, path) == (6, 0)
    state = {(a, i): j.value for (_, a, i), j in store.state().items()}
    assert state == {
        ("a1", "ED"): 1,
        ("a1", "TL"): 1,
        ("a1", "gate_error"): 1,
        ("a2", "ED"): 0,
        ("a2", "gate_error"): 0,
        ("a3", "gate_error"): 1,
    }


@pytest.mark.parametrize("with_time", [False, True])
def test_importing_a_file_twice_changes_nothing(tmp_path, run, with_time):
    header = "annotator,episode,item,value" + (",time" if with_time else "")
    rows = [
        f"a1,{episode(k)},TL,{k % 2}" + (f",{100.0 + k}" if with_time else "") for k in (0, 1, 2)
    ]
    path = write_csv(tmp_path / "votes.csv", header, rows)
    store = store_of(run)
    assert import_csv(store, path) == (3, 0)
    assert import_csv(store, path) == (0, 3)
    assert lines_on_disk(store) == 3


def test_a_history_export_imports_twice_into_the_same_state(tmp_path, run):
    source = store_of(run)
    source.record("a1", episode(0), "TL", 1)
    source.record("a1", episode(0), "TL", 0)  # supersedes
    source.record("a1", episode(1), "SR", 1)
    source.record("a1", episode(1), "SR", None)  # withdrawn
    path = tmp_path / "history.csv"
    path.write_text(export_csv(source, history=True))
    other = store_of(make_run(tmp_path / "other", 4))
    assert import_csv(other, path) == (4, 0)
    assert import_csv(other, path) == (0, 4)
    assert lines_on_disk(other) == 4
    assert {k: j.value for k, j in other.state().items()} == {(episode(0), "a1", "TL"): 0}


def test_rows_without_time_the_last_of_a_key_counts(tmp_path, run):
    path = write_csv(
        tmp_path / "votes.csv",
        "annotator,episode,item,value",
        [f"a1,{episode(0)},TL,1", f"a1,{episode(0)},TL,0"],  # a correction further down
    )
    store = store_of(run)
    assert import_csv(store, path) == (1, 1)
    assert import_csv(store, path) == (0, 2)
    assert store.state()[(episode(0), "a1", "TL")].value == 0 and lines_on_disk(store) == 1


def test_a_missing_gate_is_explained_in_words(tmp_path, run):
    path = write_csv(
        tmp_path / "votes.csv",
        "annotator,episode,item,value",
        [f"a1,{episode(0)},ED,1", f"a1,{episode(1)},gate_error,0", f"a1,{episode(1)},OC,1"],
    )
    with pytest.raises(CsvImportError) as err:
        import_csv(store_of(run), path)
    text = str(err.value)
    assert "majority of 0 vote(s): None" not in text and "no vote yet" not in text
    assert (
        f"row 2: item: criterion ED is not activated for episode '{episode(0)}': nobody has "
        "voted its gate gate_error (Observable execution error (g_e)) yet; add a row "
        f"a1,{episode(0)},gate_error,1 if the answer to 'Does the episode contain an "
        "observable execution error?' is yes (rows may come in any order)"
    ) in text
    assert "row 4: item: criterion OC is not activated" in text
    assert "a1 voted 0, and 0 of 1 vote(s) are 1, no majority" in text


def test_missing_columns_are_named_with_what_they_hold(tmp_path, run):
    path = write_csv(tmp_path / "votes.csv", "who,episode,criterion,score", [])
    with pytest.raises(CsvImportError) as err:
        import_csv(store_of(run), path)
    text = str(err.value)
    assert "no 'annotator' column (who gave each judgment)" in text
    assert "no 'value' column (1 = yes, 0 = no; empty or NA: no judgment)" in text
    assert "the header holds 'who', 'episode', 'criterion', 'score'" in text


def test_unknown_episodes_get_an_example_of_the_runs_ids(tmp_path, run):
    path = write_csv(tmp_path / "votes.csv", "annotator,episode,item,value", ["a1,ep-17,TL,1"])
    with pytest.raises(CsvImportError) as err:
        import_csv(store_of(run), path)
    assert "row 2: episode: unknown episode 'ep-17'" in str(err.value)
    assert f"episode ids of {run.resolve()} look like '{episode(0)}'" in str(err.value)


def _opcodes(fn) -> int:
    """Bytecodes executed by `fn()`: a measure of work that, unlike a time, is the same on a
    busy machine and an idle one."""
    count = 0

    def local(frame, event, arg):
        nonlocal count
        count += event == "opcode"
        return local

    def tracer(frame, event, arg):
        frame.f_trace_opcodes = True
        return local

    sys.settrace(tracer)
    try:
        fn()
    finally:
        sys.settrace(None)
    return count


def _import_work(base: Path, n_episodes: int) -> int:
    run = make_run(base / f"run{n_episodes}", n_episodes)
    rows = [
        f"a{a},{episode(k)},{item},{1 if item.startswith('gate') else (k + a) % 2}"
        for k in range(n_episodes)
        for a in (1, 2, 3)
        for item in ITEMS
    ]
    path = write_csv(base / f"votes{n_episodes}.csv", "annotator,episode,item,value", rows)
    store = store_of(run)
    store.load()  # reading the (empty) store and importing modules are not the work measured
    work = _opcodes(lambda: import_csv(store, path))
    assert lines_on_disk(store) == len(rows)
    return work


def test_import_work_grows_linearly_with_the_rows(tmp_path):
    # Twice the rows, twice the work (give or take the fixed cost): a gated row must not
    # rescan every judgment already there (that made 108,000 rows take 92 s).
    small, large = _import_work(tmp_path, 16), _import_work(tmp_path, 32)
    assert large / small < 2.4, (small, large)


# -- agreement from a votes file alone ---------------------------------------------------------


def skewed_votes(unit_column: str, criterion_column: str) -> tuple[str, list[str]]:
    """TL on 20 units: 18 unanimous 1 and two 2-1 splits (the skewed set of
    test_diagnostics_stats: 90 % unanimity, kappa < 0 < 0.9 < AC1); rows in any order."""
    rows = []
    for k in range(20):
        for a in ("x", "y", "z"):
            rows.append(f"{a},u{k},TL,{0 if (k >= 18 and a == 'z') else 1}")
    return f"annotator,{unit_column},{criterion_column},value", rows[::-1]


@pytest.mark.parametrize(("unit", "criterion"), [("episode", "item"), ("item", "criterion")])
def test_agreement_of_a_votes_file_alone(tmp_path, capsys, unit, criterion):
    header, rows = skewed_votes(unit, criterion)
    path = write_csv(tmp_path / "votes.csv", header, rows)
    assert main(["agreement", str(path), "--out", str(tmp_path / "agreement.csv")]) == 0
    out = capsys.readouterr().out
    pa = (18 + 2 * Fraction(1, 3)) / 20
    pi1 = (18 + 2 * Fraction(2, 3)) / 20
    pe_k = pi1**2 + (1 - pi1) ** 2
    kappa = (pa - pe_k) / (1 - pe_k)
    ac1 = (pa - 2 * pi1 * (1 - pi1)) / (1 - 2 * pi1 * (1 - pi1))
    assert f"| SPU | TL | 20 | 90.00 | 1.000 | {float(kappa):.3f} | {float(ac1):.3f} |" in out
    assert "votes.csv: 60 judgments in force by 3 annotators (x, y, z) on 20 episodes" in out
    assert (tmp_path / "agreement.csv").read_text().startswith("module,criterion,n,")


def test_agreement_without_gates_and_with_na_by_gate(tmp_path, capsys):
    # u0: ED judged by all three, no gate rows: applicable (the annotators judged it).
    # u1: ED judged, but the error gate's majority is 0: NA, its 3 judgments left out.
    # u2: ED left empty / NA by everyone: not judged, not in n.
    rows = [f"{a},u0,ED,1" for a in "xyz"] + [f"{a},u1,ED,{int(a == 'x')}" for a in "xyz"]
    rows += [f"{a},u1,gate_error,{int(a == 'x')}" for a in "xyz"]
    rows += ["x,u2,ED,", "y,u2,ED,NA", "z,u2,ED,na"]
    path = write_csv(tmp_path / "votes.csv", "annotator,episode,criterion,value", rows)
    assert main(["agreement", str(path)]) == 0
    out = capsys.readouterr().out
    assert "| ER | ED | 1 | 100.00 | 1.000 |" in out
    assert "3 episode-criterion items NA (majority gate 0), 3 judgments on them left out" in out
    assert "gate votes on 1 of 2 episodes decide there by majority" in out


def test_agreement_of_a_file_names_its_bad_rows(tmp_path, capsys):
    path = write_csv(
        tmp_path / "votes.csv",
        "annotator,item,criterion,value",
        ["x,u0,TL,1", "x,u1,XX,1", ",u2,TL,1", "x,u3,TL,yes"],
    )
    assert main(["agreement", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no agreement computed:")
    assert "row 3: criterion: unknown criterion or gate 'XX'" in err
    assert "row 4: annotator: empty" in err
    assert "row 5: value: expected 0, 1 or null, got 'yes'" in err


def test_a_runs_export_gives_the_runs_agreement_table(tmp_path):
    # the file alone and the run directory agree, gates included
    run = make_run(tmp_path / "run", 6)
    store = store_of(run)
    for k in range(6):
        for a in (1, 2, 3):
            error = int(k < 3 or a == 1)  # u3..u5: majority 0, a1's ED dropped
            store.record(f"a{a}", episode(k), "gate_error", error)
            for item in ("TL", "SR", "ED"):
                if item != "ED" or error or k < 3:
                    store.record(f"a{a}", episode(k), item, (k * a + len(item)) % 2)
    path = tmp_path / "export.csv"
    path.write_text(export_csv(store))
    from vabench.diagnostics.sections import agreement_of
    from vabench.diagnostics.votes_file import agreement_from_csv

    index = RunIndex.load(run)
    from_run = agreement_of(agg.collect(index, store.state()))
    from_file = agreement_from_csv(path)
    assert from_file.tables[0].rows == from_run.tables[0].rows
