"""Command line of the behavioural diagnostics.

    python -m vabench.diagnostics RUN_DIR
        the nine criteria per condition and task, the agreement table and the vote-rule
        sensitivity, from RUN_DIR/annotations/ (malformed lines are reported and skipped)
    python -m vabench.diagnostics judge RUN_DIR --model NAME [--judges 3] [--config FILE]
        an automatic annotator through the LLM pool; models come from --config (a sweep config
        or a models file) or the run's own sweep.yaml; a model with `base_url: embedded` is
        answered by the embedded server's `rubric_judge` stand-in, without keys
    python -m vabench.diagnostics export RUN_DIR [--out FILE] [--history]
    python -m vabench.diagnostics import RUN_DIR FILE
        rows in any order; importing a file again changes nothing
    python -m vabench.diagnostics agreement VOTES.csv [--out FILE]
        the agreement table of a votes file alone (annotator, episode or item, item or
        criterion, value), no run directory needed; gate rows optional

Exit status: 0 done, 1 nothing to report (no annotations) or some judge conversations failed,
2 bad input (the message names it).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Sequence
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

import yaml

from vabench.diagnostics.episodes import RunDirError, RunIndex
from vabench.run_layout import RunDir

COMMANDS = ("judge", "export", "import", "agreement")


def _summary(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.diagnostics",
        description="Diagnostics tables from a run's annotations. Subcommands: "
        + ", ".join(COMMANDS)
        + " (python -m vabench.diagnostics judge -h).",
    )
    parser.add_argument("run_dir", type=Path)
    args = parser.parse_args(argv)
    from vabench.diagnostics import sections as diagnostics
    from vabench.tables import section_markdown

    index = RunIndex.load(args.run_dir)
    data = diagnostics.load(args.run_dir, index)
    if data is None:
        print(
            f"no annotations in {RunDir(index.run_dir).annotations}: annotate with "
            f"`python -m vabench.view {args.run_dir}` or run the judge",
            file=sys.stderr,
        )
        return 1
    for problem in data.problems:
        print(f"warning: {problem}", file=sys.stderr)
    for section in diagnostics.sections(data):
        print(section_markdown(section))
    return 0


def load_models(path: Path) -> tuple[list[Any], set[str]]:
    """The `models:` of a YAML file, and the names of those served by the embedded server."""
    from vabench.llm_pool.config import ConfigError, load_endpoints

    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(str(path), f"cannot read: {err}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("models"), list):
        raise ConfigError(str(path), "no top-level 'models:' list")
    embedded: set[str] = {
        str(m.get("name"))
        for m in doc["models"]
        if isinstance(m, dict) and m.get("base_url") == "embedded"
    }
    entries = [
        {**m, "base_url": "http://embedded.invalid"} if m.get("name") in embedded else m
        for m in doc["models"]
    ]
    return list(load_endpoints(entries, where=f"{path}: models")), embedded


async def _judge(args: argparse.Namespace, index: RunIndex) -> int:
    from vabench.diagnostics.judge import run_judges
    from vabench.llm_pool import LLMPool
    from vabench.llm_pool.server import LocalServer, ServerConfig

    config = args.config or RunDir(index.run_dir).config
    if not Path(config).is_file():
        print(
            f"error: --config: {config} not found (give a YAML file with a models: list)",
            file=sys.stderr,
        )
        return 2
    endpoints, embedded = load_models(Path(config))
    names = [e.name for e in endpoints]
    if args.model not in names:
        print(
            f"error: --model: {args.model!r} is not in {config}; models: {names}", file=sys.stderr
        )
        return 2
    endpoint = next(e for e in endpoints if e.name == args.model)
    for episode in args.episodes or []:
        index.get(episode)  # an unknown id stops here with a clear message
    async with AsyncExitStack() as stack:
        if args.model in embedded:
            server = await stack.enter_async_context(
                LocalServer(ServerConfig(policy="rubric_judge"))
            )
            endpoint = endpoint.model_copy(update={"base_url": server.base_url(endpoint.api)})
        pool = await stack.enter_async_context(LLMPool([endpoint]))
        report = await run_judges(
            index,
            pool,
            args.model,
            judges=args.judges,
            episodes=args.episodes,
            max_images=args.max_images,
            redo=args.redo,
        )
    print(
        f"{report.judged} episode judgments by {args.judges} judge(s) of {args.model}: "
        f"{report.written} labels written to {RunDir(index.run_dir).annotations}; "
        f"{report.skipped} already judged (--redo judges them again)"
    )
    for failure in report.failures:
        print(f"failed: {failure}", file=sys.stderr)
    return 1 if report.failures else 0


def _agreement(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vabench.diagnostics agreement",
        description="The inter-annotator agreement table of a votes CSV alone: columns "
        "annotator, episode (or item), item (or criterion), value (0, 1; empty or NA: no "
        "judgment), optional time; gate rows optional, rows in any order.",
    )
    parser.add_argument("csv", type=Path, help="the votes file")
    parser.add_argument("--out", type=Path, help="also write the table as CSV (long format)")
    args = parser.parse_args(argv)
    from vabench.diagnostics.votes_file import agreement_from_csv
    from vabench.tables import section_markdown, to_csv

    section = agreement_from_csv(args.csv)
    print(section_markdown(section))
    if args.out:
        args.out.write_text(to_csv(section.csvs[0]), encoding="utf-8")
        print(f"wrote {args.out}")
    return 0


def _command(name: str, argv: Sequence[str]) -> int:
    if name == "agreement":
        return _agreement(argv)
    parser = argparse.ArgumentParser(prog=f"python -m vabench.diagnostics {name}")
    parser.add_argument("run_dir", type=Path)
    if name == "judge":
        parser.add_argument("--model", required=True, help="a model name of the config")
        parser.add_argument("--judges", type=int, default=3, help="independent judges (3)")
        parser.add_argument("--config", type=Path, help="YAML with models: (default: the run's)")
        parser.add_argument("--episodes", nargs="+", help="episode ids (default: all scored)")
        parser.add_argument("--max-images", type=int, default=8, help="images per episode")
        parser.add_argument("--redo", action="store_true", help="judge judged episodes again")
    elif name == "export":
        parser.add_argument("--out", type=Path, help="CSV file (default: standard output)")
        parser.add_argument("--history", action="store_true", help="every line, not only current")
    else:
        parser.add_argument("csv", type=Path)
    args = parser.parse_args(argv)
    if name == "judge" and not 1 <= args.judges <= 16:
        parser.error(f"--judges: {args.judges} is not in 1..16")
    index = RunIndex.load(args.run_dir)
    if name == "judge":
        return asyncio.run(_judge(args, index))
    from vabench.diagnostics.csv_io import export_csv, import_csv
    from vabench.diagnostics.store import AnnotationStore

    store = AnnotationStore(index)
    if name == "export":
        text = export_csv(store, args.history)
        if args.out:
            args.out.write_text(text, encoding="utf-8")
            print(f"wrote {text.count(chr(10)) - 1} rows to {args.out}")
        else:
            sys.stdout.write(text)
        return 0
    written, skipped = import_csv(store, args.csv)
    print(
        f"imported {written} judgments into {store.directory} ({skipped} rows skipped: "
        "recorded already)"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from vabench.diagnostics.csv_io import CsvImportError
    from vabench.diagnostics.episodes import UnknownEpisode
    from vabench.diagnostics.stats import MissingDependency
    from vabench.llm_pool.config import ConfigError

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in COMMANDS:
            return _command(argv[0], argv[1:])
        return _summary(argv)
    except (RunDirError, ConfigError, CsvImportError, MissingDependency) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except UnknownEpisode as err:
        print(f"error: --episodes: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
