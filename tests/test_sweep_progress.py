"""Progress on a clock (vabench.sweep.display): without a terminal, one line every
`--progress-every` seconds with the same counts as the live table; episodes are counted as they
finish, by the local executor and by the processes executor (from the ledger as its thread
appends each line, not when a cell ends)."""

from __future__ import annotations

import io
import json
import re

from vabench.config import load_config
from vabench.config.choices import choose
from vabench.sweep.__main__ import main
from vabench.sweep.display import Counts, Display, Status, Tally, with_reports
from vabench.sweep.plan import EpisodeKey, plan
from vabench.sweep.process_executor import run_processes
from vabench.sweep.rundir import check_run_dir


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def status(done: int, planned: int = 110, calls: int = 0) -> Status:
    return Status(
        {
            ("m", "active"): Counts(planned=planned - 10, done=done, success=done, running=3),
            ("m", "passive"): Counts(planned=10),
        },
        calls=calls,
        tokens=12_345,
        cost=0.5,
        in_flight=3,
        limit=4,
        reason="decisions at 1.20x their unloaded time: growing",
    )


def test_plain_lines_come_on_the_clock_with_every_count():
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, every_s=15, out=out, clock=clock)
    display.update(status(0))  # the first update prints at once
    clock.now = 5
    display.update(status(5, calls=50))  # too soon: nothing
    clock.now = 10
    display.update(status(10, calls=100))
    clock.now = 15
    display.update(status(15, calls=150))
    lines = out.getvalue().splitlines()
    assert len(lines) == 2
    last = lines[-1]
    for words in (
        "all: episodes 15/110 (14%): 15 successes, 0 unscored, 0 retried, 3 running",
        "3 running (at most 4 at once)",
        "calls 10.0/s",
        "12,345 tokens, $0.50",
        "elapsed 15s, ETA 1m35s",  # 95 left at 1 episode/s
        "active 15/100, passive 0/10",
    ):
        assert words in last, last
    display.close(status(110))  # the end always prints
    assert "episodes 110/110 (100%)" in out.getvalue().splitlines()[-1]
    assert "ETA done" in out.getvalue().splitlines()[-1]


def test_a_limit_lowered_below_the_running_episodes_says_it_only_holds_back_new_ones():
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, out=out, clock=clock, verbose=True)
    lowered = status(5)
    lowered.tracks[("m", "active")].running = 6
    lowered.in_flight, lowered.limit = 6, 3
    display.update(lowered)
    # "in flight 3 (limit 1: ...)" read as a bug
    assert "6 running (limit now 3: decisions at 1.20x their unloaded time: growing; " in (
        out.getvalue()
    )
    assert "; the 3 above it finish before a new one starts)" in out.getvalue()
    display.update(status(6), force=True)  # 3 running under a limit of 4: nothing added
    last = out.getvalue().splitlines()[-1]
    assert "3 running (at most 4 at once: " in last and "above it" not in last
    unknown = status(6)
    unknown.in_flight, unknown.limit, unknown.reason = 0, 0, ""  # a worker stopped early
    display.update(unknown, force=True)
    assert "3 running (limit now 0; the 3 above it finish" in out.getvalue().splitlines()[-1]
    quiet = Display("all", live=False, out=out, clock=clock)  # without --verbose: the limit
    quiet.update(lowered, force=True)
    last = out.getvalue().splitlines()[-1]
    assert "6 running (limit now 3; the 3 above it finish before a new one starts) |" in last
    assert "decisions" not in last


def test_one_success_is_singular_and_the_eta_waits_for_a_pace():
    """A newcomer read "1 successes", and first ETAs of 33 h, 18 h, 9 h."""
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, out=out, clock=clock)
    display.update(status(1))
    assert "1 success, " in out.getvalue() and "ETA after 5 more episodes" in out.getvalue()
    clock.now = 30
    display.update(status(6), force=True)
    assert re.search(r"ETA \d+m\d+s", out.getvalue().splitlines()[-1])


def test_a_resumed_sweeps_clock_continues():
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, out=out, clock=clock, elapsed_before_s=3_600)
    clock.now = 15
    display.update(status(0))
    assert "elapsed 1h00m" in out.getvalue()


def test_the_last_line_is_not_printed_twice():
    """Issue 34: the sweep's last update and `close` printed the same line twice."""
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, every_s=15, out=out, clock=clock)
    display.update(status(0))
    display.close(status(0))
    assert len(out.getvalue().splitlines()) == 1
    clock.now = 1
    display.close(status(1))  # a different line still comes
    assert len(out.getvalue().splitlines()) == 2


def test_log_lines_print_above_the_live_table_not_through_it(capsys):
    """Issue 34: on a terminal the first status block showed twice: log lines (the handler
    `logging.basicConfig` made before the table, holding the real stderr) were written past
    rich's live table, which left a copy of it on screen. While the table is up they go
    through rich, which prints them above it; the handler gets its stream back at the end."""
    import logging
    import sys

    handler = logging.StreamHandler(sys.stderr)  # as basicConfig makes it, before the table
    root = logging.getLogger()
    root.addHandler(handler)
    level, root.level = root.level, logging.INFO
    try:
        out = io.StringIO()
        display = Display("all", live=True, out=out, clock=Clock())
        display.update(status(0))
        logging.getLogger("vabench.test").info("embedded server on http://127.0.0.1:1")
        display.update(status(1))
        display.close(status(2))
        assert "embedded server on" in out.getvalue()  # printed by rich, above the table
        assert "embedded server on" not in capsys.readouterr().err
        assert handler.stream is sys.stderr
    finally:
        root.removeHandler(handler)
        root.level = level


def test_a_call_count_that_goes_backwards_never_reads_as_a_negative_rate():
    """An H100 processes sweep's last line read "calls -878.5/s": its call count fell from
    millions to 0. A drop is left out of the rate (what the window counted either side of it
    stays), and the rate is the true pace again once the window is past it."""
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, every_s=10, out=out, clock=clock)
    for t in range(0, 310, 10):  # 45 calls/s for five minutes
        clock.now = t
        display.update(status(t // 10, calls=45 * t))
    for t in range(310, 420, 10):  # the count starts again from 0, at the same pace
        clock.now = t
        display.update(status(t // 10, calls=45 * (t - 310)))
    rates = [float(r) for r in re.findall(r"calls (-?[\d.]+)/s", out.getvalue())]
    assert len(rates) == 42 and min(rates) >= 0, rates
    assert rates[31] > 30  # at the drop: the calls before it, not 0 and not negative
    assert rates[-1] == 45.0  # the window is past the drop
    clock.now = 430
    display.close(status(43, calls=0))  # and a last line fallen to 0
    assert "calls -" not in out.getvalue().splitlines()[-1]


def _seconds(eta: str) -> int:
    """'1h03m' / '4m05s' / '12s' -> seconds."""
    m = re.fullmatch(r"(?:(\d+)h)?(?:(\d+)m)?(?:(\d+)s)?", eta)
    assert m and eta, eta
    h, mins, secs = (int(g) if g else 0 for g in m.groups())
    return 3600 * h + 60 * mins + secs


def test_the_eta_holds_steady_when_episodes_finish_in_bursts():
    """A small machine finishes a few episodes a minute, several at once (a batch's slots end
    together): 10 every 50 s here, a true pace of 0.2 episodes/s. Over one minute that is 10 or
    20 episodes, an ETA that doubles and halves; it reaches back to the last 30 episodes."""
    clock, out = Clock(), io.StringIO()
    display = Display("all", live=False, every_s=15, out=out, clock=clock)
    for t in range(0, 1_000, 5):
        clock.now = t
        display.update(status(10 * (t // 50), planned=2_000))
    later = []  # (ETA, episodes left) from the fourth minute on
    for line in out.getvalue().splitlines():
        if "ETA after" in line:  # the first episodes: no pace yet
            continue
        m = re.search(r"episodes (\d+)/(\d+).* elapsed (\S+), ETA (\S+) \|", line)
        assert m, line
        done, planned, elapsed, eta = m.groups()
        if _seconds(elapsed) >= 240:
            later.append((_seconds(eta), int(planned) - int(done)))
    assert len(later) > 40
    ratios = [eta * 0.2 / left for eta, left in later]  # 1.0: the true pace
    assert max(ratios) <= 1.5 * min(ratios), ratios
    assert all(0.7 < r < 1.5 for r in ratios), ratios


def ledger_line(key: EpisodeKey, status: str = "success") -> str:
    record = {
        "model": key.model,
        "track": key.track,
        "task": key.task,
        "seed": key.seed,
        "run": key.run,
        "status": status,
        "success": status == "success",
        "model_calls": 4,
        "tokens": {"input": 100, "output": 10},
        "cost_usd": 0.01,
    }
    return json.dumps(record) + "\n"


def test_the_tally_counts_whole_lines_as_they_are_appended(tmp_path):
    keys = [EpisodeKey("m", "active", "t", seed, 1) for seed in range(4)]
    ledger = tmp_path / "results.jsonl"
    ledger.write_text(ledger_line(keys[0]))  # before this invocation: counted, not spent here
    tally = Tally(tmp_path, keys)
    assert tally.status().total().done == 1 and tally.status().tokens == 0
    line = ledger_line(keys[1], "failure")
    with ledger.open("a") as f:
        f.write(line[:20])  # a line being appended is not counted yet
    tally.refresh()
    assert tally.status().total().done == 1
    with ledger.open("a") as f:
        f.write(line[20:] + ledger_line(keys[1]) + ledger_line(keys[2], "error"))
    tally.refresh()
    total = tally.status().total()
    assert (total.done, total.success, total.unscored) == (3, 1, 1)  # a second record: once
    assert tally.status().calls == 8 and tally.status().tokens == 220  # spent here


CONFIG = """\
name: progress
models:
  - {{name: local, api: openai_chat, base_url: embedded}}
embedded_server: {{policy: conversation_hash, latency: {{mean_s: 0.2}}}}
tracks: [active]
summaries: none
tasks: [grasp_single_cube]
seeds: {{verified: 5}}
runs: 1
step_budget: 3
simulator: {{backend: c}}
render: {{width: 64, height: 48, workers: 1}}
executor: {executor}
"""
LINE = re.compile(r"progress: episodes (\d+)/5 ")


def test_plain_progress_lines_count_episodes_as_they_finish(tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(executor="{kind: local}"))
    out = tmp_path / "out"
    args = [str(cfg), "--out", str(out), "--plain", "--no-report", "--progress-every", "0.5"]
    assert main(args) == 0
    text = capsys.readouterr().out
    counts = [int(m.group(1)) for m in LINE.finditer(text)]
    assert counts[0] == 0 and counts[-1] == 5 and counts == sorted(counts), text
    assert any(0 < c < 5 for c in counts), text  # lines came while the sweep ran
    last = text.strip().splitlines()[-1]
    for words in ("successes", "unscored", "retried", "running", "calls", "tokens", "ETA"):
        assert words in last, last


def test_the_processes_executor_counts_each_episode_when_its_line_arrives(tmp_path):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(executor="{kind: processes, max_tasks: 1}"))
    out = tmp_path / "out"
    config = load_config(cfg, overrides={"out": str(out)})
    keys = plan(config)
    check_run_dir(out, config, keys, config.document())
    seen: list[Status] = []
    records = run_processes(config, keys, out, choose(config), on_status=seen.append)
    assert len(records) == 5
    done = [s.total().done for s in seen]
    assert done == sorted(done) and done[-1] == 5
    # one cell of five episodes: the display moved while it ran, not only when it ended
    assert any(0 < d < 5 for d in done), done
    # the worker's status lines: episodes running, the in-flight limit and why, the spend
    assert any(s.total().running > 0 and s.limit for s in seen)
    assert any(s.reason and "unloaded" in s.reason for s in seen) or all(
        s.reason is None or s.reason.startswith("starting") for s in seen
    )
    assert seen[-1].calls >= 5 and seen[-1].tokens > 0


def test_chunks_of_one_cell_running_at_once_are_all_counted(tmp_path):
    """A cell cut into two chunks running in two engines: both engines' running episodes,
    calls and in-flight counts add up in the display (the two halves of each cell must not
    hide each other)."""
    keys = [EpisodeKey("m", "active", "t", seed, 1) for seed in range(4)]
    reports = []
    for running, calls in ((2, 10), (1, 7)):
        status = {"running": {"m/active": running}, "in_flight": running, "limit": 4}
        status |= {"reason": "r", "calls": calls, "tokens": 5, "cost": 0.0, "calls_in_flight": 1}
        reports.append(status)
    shown = with_reports(Tally(tmp_path, keys).status(), reports, reports, "worker processes")
    assert shown.total().running == 3 and shown.in_flight == 3 and shown.limit == 8
    assert shown.calls == 17 and shown.tokens == 10 and shown.calls_in_flight == 2


def test_the_spend_shown_never_drops_below_the_ledgers_when_reporters_go_quiet():
    """A Ray engine closed at the end of a sweep reports no spend: the last line read "0
    tokens" after 4 episodes had recorded 4,593 (seen walking docs/RAY.md's steps, 2026-11-26).
    The ledger's records of this invocation are the floor; live reports above it win."""

    def ledger() -> Status:
        return Status({}, calls=12, tokens=4593, cost=0.5)

    quiet = with_reports(ledger(), [], [], "engines")
    assert (quiet.calls, quiet.tokens, quiet.cost) == (12, 4593, 0.5)
    report = {"calls": 20, "tokens": 9000, "cost": 0.75, "calls_in_flight": 3}
    report |= {"in_flight": 4, "limit": 8, "reason": "r"}
    live = with_reports(ledger(), [report], [report], "engines")
    assert (live.calls, live.tokens, live.cost, live.calls_in_flight) == (20, 9000, 0.75, 3)


def test_the_last_status_keeps_the_spend_shown_with_the_ledgers_final_counts(tmp_path):
    """Once the processes have ended, the last line has every record's episode (none running)
    and the spend of the last status shown: the workers' reports, above the ledger's records.
    It was a fresh Tally's, whose spend starts at 0: "0 tokens" after 1.5 billion."""
    keys = [EpisodeKey("m", "active", "t", seed, 1) for seed in range(4)]
    ledger = tmp_path / "results.jsonl"
    ledger.write_text(ledger_line(keys[0]))  # an earlier invocation's: not spent here
    tally = Tally(tmp_path, keys)
    with ledger.open("a") as f:
        f.write(ledger_line(keys[1]) + ledger_line(keys[2], "failure"))
    shown = Status(
        {("m", "active"): Counts(planned=4, done=2, running=2)}, calls=30, tokens=5000, cost=0.2
    )
    shown.in_flight, shown.limit = 2, 4
    last = tally.ended(shown)
    total = last.total()
    assert (total.done, total.success, total.running) == (3, 2, 0)
    assert (last.calls, last.tokens, last.cost) == (30, 5000, 0.2)
    assert last.in_flight is None and last.limit is None
    # reporters that said less than the ledger holds (a Ray engine closed early): the ledger's
    quiet = tally.ended(Status())
    assert (quiet.calls, quiet.tokens, quiet.cost) == (8, 220, 0.02)


def test_the_last_plain_line_of_a_processes_sweep_keeps_its_calls_and_tokens(tmp_path, capsys):
    """`python -m vabench.sweep --plain` with the processes executor: the line printed once
    every worker has ended shows the whole run's tokens (it read "0 tokens", and a negative
    calls rate, on an H100)."""
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(CONFIG.format(executor="{kind: processes, max_tasks: 1}"))
    out = tmp_path / "out"
    args = [str(cfg), "--out", str(out), "--plain", "--no-report", "--progress-every", "0.5"]
    assert main(args) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "progress: episodes" in line]
    tokens = [int(m.group(1).replace(",", "")) for m in map(SPEND.search, lines) if m]
    rates = [float(m.group(1)) for m in map(RATE.search, lines) if m]
    assert len(tokens) == len(rates) == len(lines), lines
    assert "episodes 5/5" in lines[-1] and "0 running" in lines[-1], lines[-1]
    assert tokens[-1] > 0 and tokens[-1] == max(tokens), lines
    assert min(rates) >= 0, lines


SPEND = re.compile(r" ([\d,]+) tokens")
RATE = re.compile(r"calls (-?[\d.]+)/s")
