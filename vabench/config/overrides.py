"""Command-line overrides of a sweep config, for quick trials without editing YAML.

Each flag edits the loaded YAML document before it is checked (`load_config(edit=...)`), so a
bad value gets the schema's one-line error naming the field, to which `name_flags` adds the
flag that set it. The overridden config is the sweep's config: its run directory's plan.json
and sweep.yaml record it, and resuming with other overrides is refused like a changed file
(`vabench.sweep.rundir`). `--limit` is the one flag that is no config field: it keeps the first
N episodes of the plan's order (task > model > track > run > seed, `vabench.sweep.plan`), and
plan.json records exactly those episodes, so a resume with another limit is refused too.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from vabench.config.problems import Problem, SweepConfigError

T = TypeVar("T")


class OverrideError(ValueError):
    """A flag that cannot apply to this config (an unknown model name, flags that need another
    flag); its message is one line naming the flag."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The override flags, as one group of `parser`."""
    g = parser.add_argument_group(
        "quick trials",
        "override the config's values for this invocation (the run directory records the result)",
    )
    g.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="NAME",
        help="keep only this model of the config (repeatable); with --model-base-url, an "
        "endpoint of that name instead",
    )
    g.add_argument(
        "--model-base-url",
        metavar="URL",
        help="the --model names are OpenAI-compatible endpoints (api openai_chat) at URL, e.g. "
        "http://127.0.0.1:8000/v1, replacing the config's models (a NAME with '/' is the "
        "provider's id; the part after the last '/' names the model)",
    )
    g.add_argument("--model-key-env", metavar="VAR", help="environment variable holding their key")
    g.add_argument("--tasks", metavar="A,B", help="these tasks only")
    g.add_argument("--tracks", metavar="A,B", help="these tracks only (active, passive, ...)")
    g.add_argument("--seeds", metavar="N", help="the first N verified seeds of each task")
    g.add_argument("--runs", metavar="N", help="runs per seed")
    g.add_argument(
        "--limit",
        metavar="N",
        help="at most N episodes: the first N of the plan's order (task, model, track, run, seed)",
    )
    g.add_argument(
        "--max-episodes", metavar="N", help="episodes in flight per process (executor.max_episodes)"
    )
    g.add_argument(
        "--max-connections",
        metavar="N",
        help="concurrent requests per model (each model's limits.max_concurrency)",
    )


def _number(text: str) -> int | str:
    """A whole number where the text is one, else the text (the schema names what is wrong)."""
    try:
        return int(text)
    except ValueError:
        return text


def _names(text: str) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()]


@dataclass(frozen=True)
class Overrides:
    """The override flags given, in a fixed order (`line`)."""

    models: tuple[str, ...] = ()
    base_url: str | None = None
    key_env: str | None = None
    tasks: tuple[str, ...] | None = None
    tracks: tuple[str, ...] | None = None
    seeds: int | str | None = None
    runs: int | str | None = None
    limit: int | None = None
    max_episodes: int | str | None = None
    max_connections: int | str | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Overrides:
        """The flags of `args`; `OverrideError` for one that needs another or a bad limit."""
        if args.model_base_url and not args.model:
            raise OverrideError("--model-base-url needs --model NAME (the endpoint's name)")
        if args.model_key_env and not args.model_base_url:
            raise OverrideError("--model-key-env is only used with --model-base-url")
        limit: int | None = None
        if args.limit is not None:
            number = _number(args.limit)
            if not isinstance(number, int) or number < 1:
                raise OverrideError(f"--limit: expected a whole number >= 1, got {args.limit!r}")
            limit = number

        def opt(text: str | None) -> int | str | None:
            return None if text is None else _number(text)

        return cls(
            models=tuple(args.model),
            base_url=args.model_base_url,
            key_env=args.model_key_env,
            tasks=None if args.tasks is None else tuple(_names(args.tasks)),
            tracks=None if args.tracks is None else tuple(_names(args.tracks)),
            seeds=opt(args.seeds),
            runs=opt(args.runs),
            limit=limit,
            max_episodes=opt(args.max_episodes),
            max_connections=opt(args.max_connections),
        )

    def _flags(self) -> list[tuple[str, tuple[str, ...]]]:
        """(the flag as given, the fields it sets) of each flag given."""
        out: list[tuple[str, tuple[str, ...]]] = []
        if self.models:
            text = ", ".join(f"--model {m}" for m in self.models)
            if self.base_url:
                text += f", --model-base-url {self.base_url}"
            if self.key_env:
                text += f", --model-key-env {self.key_env}"
            out.append((text, ("models",)))
        if self.tasks is not None:
            out.append((f"--tasks {','.join(self.tasks)}", ("tasks", "seeds")))
        if self.tracks is not None:
            out.append((f"--tracks {','.join(self.tracks)}", ("tracks",)))
        for flag, value, field in (
            ("--seeds", self.seeds, "seeds"),
            ("--runs", self.runs, "runs"),
            ("--max-episodes", self.max_episodes, "executor.max_episodes"),
            ("--max-connections", self.max_connections, "models[*].limits"),
        ):
            if value is not None:
                out.append((f"{flag} {value}", (field,)))
        if self.limit is not None:
            out.append((f"--limit {self.limit}", ()))
        return out

    def line(self) -> str | None:
        """`overrides: --tasks a, --runs 1` (None: no flag given)."""
        flags = [text for text, _ in self._flags()]
        return f"overrides: {', '.join(flags)}" if flags else None

    def edit(self, doc: dict[str, Any]) -> dict[str, Any]:
        """The YAML document with the flags applied (before it is checked)."""
        doc = dict(doc)
        models = doc.get("models")
        if self.models and self.base_url:
            doc["models"] = [self._endpoint(name) for name in self.models]
        elif self.models:
            entries = models if isinstance(models, list) else []
            names = [str(m.get("name")) for m in entries if isinstance(m, dict)]
            for name in self.models:
                if name not in names:
                    raise OverrideError(
                        f"--model {name}: no model {name!r} in the config; its models: "
                        f"{', '.join(names)} (or add --model-base-url URL for an endpoint)"
                    )
            doc["models"] = [m for m in entries if isinstance(m, dict) and m["name"] in self.models]
        if self.tasks is not None:
            doc["tasks"] = list(self.tasks)
        if self.tracks is not None:
            written = {t.get("name"): t for t in doc.get("tracks") or [] if isinstance(t, dict)}
            doc["tracks"] = [written.get(name, name) for name in self.tracks]
        if self.seeds is not None:
            doc["seeds"] = {"verified": self.seeds}
        if self.runs is not None:
            doc["runs"] = self.runs
        if self.max_episodes is not None:
            executor = doc.get("executor")
            doc["executor"] = {**(executor if isinstance(executor, dict) else {})}
            doc["executor"]["max_episodes"] = self.max_episodes
        if self.max_connections is not None and isinstance(doc.get("models"), list):
            doc["models"] = [self._connections(m) for m in doc["models"]]
        return doc

    def _endpoint(self, name: str) -> dict[str, Any]:
        """A `models:` entry for an OpenAI-compatible endpoint at `--model-base-url`."""
        entry: dict[str, Any] = {"name": name.rsplit("/", 1)[-1], "api": "openai_chat"}
        if "/" in name:
            entry["model"] = name
        entry["base_url"] = self.base_url
        if self.key_env:
            entry["api_key_env"] = self.key_env
        return entry

    def _connections(self, model: Any) -> Any:
        if not isinstance(model, dict):
            return model  # the schema names it
        limits = model.get("limits")
        limits = {**(limits if isinstance(limits, dict) else {})}
        limits["max_concurrency"] = self.max_connections
        return {**model, "limits": limits}

    def name_flags(self, err: SweepConfigError) -> SweepConfigError:
        """`err` with each problem of a field a flag set ending in `(from --flag value)`."""
        flags = self._flags()
        problems = []
        for p in err.problems:
            setters = [text for text, fields in flags if any(_sets(f, p.path) for f in fields)]
            message = f"{p.message} (from {'; '.join(setters)})" if setters else p.message
            problems.append(Problem(p.path, message))
        return SweepConfigError(err.file, problems)

    def limited(self, keys: Sequence[T]) -> list[T]:
        """The first `--limit` episodes of the plan (all of them without one)."""
        return list(keys if self.limit is None else keys[: self.limit])


def _sets(field: str, path: str) -> bool:
    """Whether `path` (a problem's) lies in `field` (a flag's; `models[*]` any entry)."""
    if field.startswith("models[*]"):
        rest = re.escape(field.removeprefix("models[*]"))
        return re.fullmatch(rf"models\[\d+\]{rest}([.\[].*)?", path) is not None
    return path == field or path.startswith((field + ".", field + "["))
