"""`python -m vabench.sweep CONFIG [--dry-run] [--out DIR] [--no-report] [--plain]`

Runs the sweep CONFIG plans; the flags below override the config for this invocation (`--model
NAME --model-base-url URL`: an OpenAI-compatible endpoint). `--dry-run` prints the plan, its
cost, what this machine runs it on and why, and a wall-time estimate. Each model's endpoint is
checked before the first episode (`vabench.check`). The same command again resumes, never
re-running a finished episode; a run directory of another plan (other overrides included) is
refused. Ctrl-C stops cleanly, a second press at once. Exit code 0 when every planned episode
is recorded, 1 when some ended unscored (listed), 2 for a bad config, a run directory of
another plan or an endpoint that refused the sweep's requests, 130 after Ctrl-C. More:
docs/SETUP.md, "The main job".
"""

from __future__ import annotations

import os
import signal
import sys
import time

_LOADING = time.monotonic()  # before the imports below (seconds on a small machine)


def _stopped_while_loading(signum: int, frame: object) -> None:
    """Ctrl-C while the modules below load (seconds on a small machine, before the sweep's own
    handler is installed): the same short exit as later; nothing was started or written."""
    print("stopped before the sweep started; nothing recorded", file=sys.stderr)
    os._exit(130)


if __name__ == "__main__":
    signal.signal(signal.SIGINT, _stopped_while_loading)
    from vabench.children import children_ignore_sigint

    # importing mujoco starts a `python -c` child (glfw asks its library's version): a press
    # reaching it mid-start prints "Fatal Python error"; blocked, the press lands here after
    with children_ignore_sigint():
        import mujoco  # noqa: F401

import argparse  # noqa: E402  (after the handler above: these imports take seconds)
import contextlib  # noqa: E402
import difflib  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, NoReturn  # noqa: E402

from vabench.check import plan_line, sweep_models  # noqa: E402
from vabench.check.latency import measured as check_latencies  # noqa: E402
from vabench.check.pace import estimate_lines, keep_pace, machine_paces  # noqa: E402
from vabench.children import process_age_s  # noqa: E402
from vabench.config import SweepConfig, SweepConfigError, load_config  # noqa: E402
from vabench.config.choices import apply_switches, choose  # noqa: E402
from vabench.config.keys import key_sources  # noqa: E402
from vabench.config.overrides import OverrideError, Overrides  # noqa: E402
from vabench.config.overrides import add_arguments as add_overrides  # noqa: E402
from vabench.run_layout import RunDir  # noqa: E402
from vabench.sim_mjx.backends import BackendUnavailable  # noqa: E402
from vabench.sweep.display import PLAIN_EVERY_S, Display, Status, Tally  # noqa: E402
from vabench.sweep.interrupt import EXIT_INTERRUPTED, CtrlC, Interrupted  # noqa: E402
from vabench.sweep.local_executor import run_local  # noqa: E402
from vabench.sweep.plan import EpisodeKey, estimate, format_estimate, plan  # noqa: E402
from vabench.sweep.results import (  # noqa: E402
    Key,
    Ledger,
    LedgerError,
    ledger_key,
    reopen_infrastructure_errors,
)
from vabench.sweep.rundir import RunDirMismatch, check_run_dir, run_dir_problem  # noqa: E402
from vabench.sweep.runner import SweepStopped  # noqa: E402
from vabench.tuning.engine_env import configure_jax  # noqa: E402

log = logging.getLogger("vabench.sweep")


def main(argv: Sequence[str] | None = None, ctrl_c: CtrlC | None = None) -> int:
    """The command. `ctrl_c`: a handler installed for the process's life (so a press after `main`
    returns still exits at once); without one, `main` installs its own for the run and restores."""
    p = _Parser(
        prog="python -m vabench.sweep",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False,  # `--seed 2` taken silently as `--seeds 2` plans another sweep
    )
    p.add_argument("config", type=Path)
    p.add_argument(
        "--dry-run", action="store_true", help="print the plan, its cost and the choices made"
    )
    p.add_argument("--out", help="run directory (default: the config's out)")
    p.add_argument("--no-report", action="store_true")
    p.add_argument("--plain", action="store_true", help="progress lines instead of a live table")
    p.add_argument(
        "--progress-every",
        type=float,
        default=PLAIN_EVERY_S,
        metavar="SECONDS",
        help=f"seconds between plain progress lines (default {PLAIN_EVERY_S:.0f})",
    )
    p.add_argument(
        "--no-check",
        action="store_true",
        help="skip the check of each model's endpoint before the first episode (vabench.check)",
    )
    p.add_argument(
        "--no-retry-infrastructure",
        action="store_true",
        help="keep the episodes that ended as infrastructure errors (by default the same "
        "command runs them again, their earlier attempts kept in the record)",
    )
    p.add_argument(
        "--verbose",
        action="store_true",
        help="also show the engine's statistics (host load, stages, the episodes' limit and "
        f"why); they are always in {RunDir(Path('RUN_DIR')).sweep_log}",
    )
    add_overrides(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    _RESEARCHER_LINES.show_all = args.verbose
    for handler in logging.getLogger().handlers:  # the terminal's (not a test's capture)
        if type(handler) is logging.StreamHandler and _RESEARCHER_LINES not in handler.filters:
            handler.addFilter(_RESEARCHER_LINES)
    configuring = time.monotonic()
    try:
        given = Overrides.from_args(args)
        keys_from = key_sources(args.config, os.environ)
        config = load_config(
            args.config,
            environ=keys_from.environ,
            overrides={"out": args.out} if args.out else None,
            require_keys=not args.dry_run,  # a dry run warns of them (below)
            edit=given.edit,
        )
        choices = choose(config, effective=apply_switches(config))  # and for its children
    except OverrideError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except SweepConfigError as err:
        print(given.name_flags(err), file=sys.stderr)
        return 2
    except (BackendUnavailable, ValueError) as err:  # an explicit backend that cannot run here
        print(f"error: {args.config}: {err}", file=sys.stderr)
        return 2
    keys = given.limited(plan(config))
    run_dir = Path(config.out)
    if given.line() is not None:
        print(given.line())
    if args.dry_run:
        _print_lines(*keys_from.dry_run_lines(config.models))
        print(format_estimate(estimate(config, keys)))
        print("\nRuns with:\n" + "\n".join(f"  {line}" for line in choices.lines()))
        print(f"  {plan_line(config, {k.model for k in keys}, args.no_check)}")
        problem = run_dir_problem(run_dir, config, keys)  # what the run would refuse
        if problem is not None:
            print(f"error: {problem}", file=sys.stderr)
            return 2
        _print_where_and_how_long(config, keys, run_dir)
        return 0
    try:
        check_run_dir(run_dir, config, keys, config.document())
    except RunDirMismatch as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if not args.no_retry_infrastructure:
        reopened = reopen_infrastructure_errors(run_dir, {ledger_key(k) for k in keys})
        if reopened:
            log.info(
                "running again %d episodes that ended as infrastructure errors (their attempts "
                "are kept; --no-retry-infrastructure keeps them as they are)",
                len(reopened),
            )
    os.environ.update(keys_from.added())  # the pool and the processes it starts read them here
    if not args.no_check and _check_endpoints(config, keys):
        return 2
    configure_jax(choices.physics)
    layout = RunDir(run_dir)
    layout.logs.mkdir(parents=True, exist_ok=True)
    to_file = logging.FileHandler(layout.sweep_log, encoding="utf-8")
    to_file.setFormatter(logging.Formatter("%(asctime)s %(name)s %(message)s", "%H:%M:%S"))
    logging.getLogger().addHandler(to_file)
    tally = Tally(run_dir, keys)  # its spend: this invocation's records, for the last line
    recorded = tally.status().total().done
    log.info("%s", _start_line(configuring))
    for line in choices.lines():
        log.info(line)
    log.info("output:    %s%s", run_dir, " (new)" if recorded == 0 else "")
    if recorded:
        log.info("resuming:  %d of %d already recorded", recorded, len(keys))
    display = Display(
        config.name,
        live=False if args.plain else None,
        every_s=max(args.progress_every, 0.1),
        pricing=config.pricing(),
        verbose=args.verbose,
        elapsed_before_s=_clock_before(layout) if recorded else 0.0,
    )
    own_handler = ctrl_c is None
    if ctrl_c is None:
        ctrl_c = CtrlC()
        ctrl_c.install()
    last: list[Status] = [tally.status()]

    def show(status: Status) -> None:
        last[0] = status
        display.update(status)

    try:
        run = _executor(choices.executor.kind)
        records = run(config, keys, run_dir, choices, on_status=show, ctrl_c=ctrl_c)
        # every record in, the engines' spend kept
        last[0] = tally.ended(last[0], own_limit=choices.executor.kind == "local")
        display.close(last[0])
        return _conclude(records, keys, run_dir, args.no_report)
    except Interrupted:
        ctrl_c.stopped()
        display.close(last[0], show=False)  # the one line below says it
        done = Tally(run_dir, keys).status().total().done
        print(
            f"stopped; {done} of {len(keys)} episodes recorded; run the same command to resume",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except (LedgerError, SweepStopped) as err:  # e.g. a cell retried by Ray wrote twice
        display.close(last[0])
        print(f"{'stopped' if isinstance(err, SweepStopped) else 'error'}: {err}", file=sys.stderr)
        return 2
    finally:
        _keep_clock(layout, display.elapsed_s())
        keep_pace(run_dir, config)  # this machine's pace of each model kind, for dry runs
        logging.getLogger().removeHandler(to_file)
        to_file.close()
        if own_handler:
            ctrl_c.restore()


class _ResearcherLines(logging.Filter):
    """The log lines a terminal shows without --verbose: warnings, errors, this command's own and
    the demonstration summaries'; the engine's statistics go to the run directory's log only."""

    SHOWN = ("vabench.sweep", "vabench.agent.learning_stage")

    def __init__(self) -> None:
        super().__init__()
        self.show_all = False

    def filter(self, record: logging.LogRecord) -> bool:
        return self.show_all or record.levelno >= logging.WARNING or record.name in self.SHOWN


_RESEARCHER_LINES = _ResearcherLines()


def _clock_before(layout: RunDir) -> float:
    """The seconds earlier invocations ran (`logs/clock.json`); where it was never written
    (a process killed), the span of the recorded episodes."""
    try:
        return float(json.loads(layout.clock.read_text())["elapsed_s"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    spans = []
    for record in Ledger.open(layout.path).records.values():
        start = record.get("started_at")
        if isinstance(start, int | float):
            spans.append((start, start + float(record.get("wall_s") or 0.0)))
    return max(e for _, e in spans) - min(s for s, _ in spans) if spans else 0.0


def _keep_clock(layout: RunDir, elapsed_s: float) -> None:
    """The sweep's clock for the next invocation (written whole: a rename)."""
    part = layout.clock.with_suffix(".part")
    with contextlib.suppress(OSError):
        part.write_text(json.dumps({"elapsed_s": round(elapsed_s, 1)}))
        part.replace(layout.clock)


class _Parser(argparse.ArgumentParser):
    """argparse with the command's one form of error, "error: WHAT: WHY; FIX", and a "did you
    mean" for a flag it does not know (abbreviations included: they are refused)."""

    def error(self, message: str) -> NoReturn:
        unknown = message.removeprefix("unrecognized arguments: ")
        if unknown != message:
            flag = unknown.split()[0]
            known = [o for o in self._option_string_actions if o.startswith("--")]
            close = difflib.get_close_matches(flag.split("=")[0], known, n=1, cutoff=0.75)
            fix = f"did you mean {close[0]}?" if close else "see --help for the flags"
            message = f"{flag}: unknown flag (flags are written in full); {fix}"
        else:
            message = f"{message.removeprefix('argument ')}; see --help"
        self.exit(2, f"error: {message}\n")


def _start_line(configuring: float) -> str:
    """How long the command took to get here: starting Python, importing, configuring, planning."""
    now = time.monotonic()
    age = process_age_s()
    before = f"{age - (now - _LOADING):.1f} s starting Python, " if age is not None else ""
    return (
        f"started:   {before}{configuring - _LOADING:.1f} s importing, "
        f"{now - configuring:.1f} s reading the config, choosing and planning"
    )


def _check_endpoints(config: SweepConfig, keys: Sequence[EpisodeKey]) -> int:
    """The sweep's first step (`vabench.check`): 2, with one line per problem and its fix, when
    some model's endpoint cannot serve the sweep as configured."""
    models = sweep_models(config, {k.model for k in keys})
    if not models:
        return 0
    from vabench.check import check_sync, problems, report_text

    reports = check_sync(config, os.environ, models)
    for row in report_text(reports).splitlines():
        log.info(row)
    found = problems(reports)
    for problem in found:
        print(f"error: {problem.problem_line()}", file=sys.stderr)
    if found:
        print(
            "stopped before the first episode; nothing recorded (--no-check skips the check)",
            file=sys.stderr,
        )
    return 2 if found else 0


def _print_where_and_how_long(
    config: SweepConfig, keys: Sequence[EpisodeKey], run_dir: Path
) -> None:
    """The dry run's last lines: the output directory (and what it holds), each track's summary
    mode, the wall time at this machine's pace and the disk it takes (`check.pace`)."""
    done: dict[Key, dict[str, Any]] = {}
    if RunDir(run_dir).results.exists():
        done = Ledger.open(run_dir).records
        print(f"\noutput: {run_dir}: {len(done)} of {len(keys)} episodes already finished")
    else:
        print(f"\noutput: {run_dir} (new)")
    modes = ", ".join(f"{t.name}: {t.summaries}" for t in config.tracks)
    print(f"summaries: {modes}")
    left: dict[str, list[int]] = {}
    for k in keys:
        if ledger_key(k) not in done:
            left.setdefault(k.model, []).append(config.budget(k.task))
    if not left:
        print("wall time: nothing left to run")
        return
    _print_lines(*estimate_lines(config, left, run_dir, machine_paces(), check_latencies()))


def _print_lines(lines: Sequence[str], warnings: Sequence[str]) -> None:
    for line in lines:
        print(line)
    for line in warnings:
        print(line, file=sys.stderr)


def _executor(kind: str) -> Callable[..., dict[Key, dict[str, Any]]]:
    """The `run_*` of executor `kind`: each runs the sweep's engines under the one driver."""
    if kind == "ray":
        from vabench.sweep.ray_executor import run_ray

        return run_ray
    if kind == "processes":
        from vabench.sweep.process_executor import run_processes

        return run_processes
    return run_local


def _conclude(
    records: dict[Key, dict[str, Any]], keys: Sequence[EpisodeKey], run_dir: Path, no_report: bool
) -> int:
    missing = [k.as_id() for k in keys if ledger_key(k) not in records]
    unscored = [r for r in records.values() if r["status"] not in ("success", "failure")]
    for r in unscored:
        print(f"unscored: {r['episode_dir']}: {r['status']} ({r['stop_reason']}): {r['error']}")
    if missing:
        print(f"{len(missing)} planned episodes have no record: {missing[:5]} ...")
    if not no_report:
        from vabench.report import ReportError, make_report

        try:
            print(f"report: {make_report(run_dir)}")
        except ReportError as err:  # e.g. every episode unscored: nothing to tabulate
            print(f"no report: {err}", file=sys.stderr)
    return 0 if not unscored and not missing else 1


if __name__ == "__main__":
    handler = CtrlC()
    handler.install()
    try:
        status = main(ctrl_c=handler)
    except Interrupted:  # pressed before the sweep started (loading, checking the run dir)
        print("stopped; run the same command to resume", file=sys.stderr)
        status = EXIT_INTERRUPTED
    sys.exit(status)
