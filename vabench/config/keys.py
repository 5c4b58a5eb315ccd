"""Where a sweep's API keys come from: the environment, else a `.env` file beside the config.

A user coming from other harnesses keeps keys in a `.env` file rather than exporting them. The
file beside the config (`configs/.env` for `configs/smoke.yaml`) is read once, by the command,
before the config is checked: `NAME=VALUE` lines, `#` comments and blank lines, an optional
leading `export `, a value optionally in single or double quotes (taken as written, no escapes);
an unquoted value ends at ` #` (a comment after it). A variable already set (non-empty) in the
environment wins over the file, so an export overrides the file for one run.

Values never leave this module's result except into the environment of the run itself (the
pool reads keys from there, and processes the sweep starts inherit them): nothing here logs or
formats a value, and a malformed line is reported by its number, never its text.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from vabench.config.problems import Problem, SweepConfigError
from vabench.llm_pool.config import ModelEndpoint

DOTENV = ".env"
_LINE = re.compile(r"(?:export\s+)?([A-Za-z_][A-Za-z0-9_]*)\s*=\s*(.*)")


@dataclass(frozen=True)
class KeySources:
    """The environment a sweep's keys are read from, and which names came from the file."""

    environ: Mapping[str, str]
    """The process environment with the file's variables added where the environment has none."""
    from_file: tuple[str, ...]
    """Names taken from the `.env` file (never their values)."""
    file: Path

    def unset(self, models: Sequence[ModelEndpoint]) -> list[tuple[str, str]]:
        """(model, variable) of every model whose `api_key_env` is set nowhere."""
        return [
            (m.name, m.api_key_env)
            for m in models
            if m.api_key_env is not None and not self.environ.get(m.api_key_env)
        ]

    def dry_run_lines(self, models: Sequence[ModelEndpoint]) -> tuple[list[str], list[str]]:
        """(lines, warnings) of the dry run on keys: which variables the `.env` file gave
        (names only), and each model whose key is set nowhere (the real run refuses to start)."""
        lines = [f"keys from {self.file}: {', '.join(self.from_file)}"] if self.from_file else []
        warnings = [
            f"warning: model {model!r}: environment variable {variable} is not set (its "
            f"api_key_env): the run will refuse to start until it is exported or put in "
            f"{self.file}"
            for model, variable in self.unset(models)
        ]
        return lines, warnings

    def added(self) -> dict[str, str]:
        """The variables the run adds to its own environment (from the file)."""
        return {name: self.environ[name] for name in self.from_file}


def read_dotenv(path: Path) -> dict[str, str]:
    """The variables of a `.env` file (see the module docstring); {} when there is none.

    Raises `SweepConfigError` naming the file and the line number of a line that is not
    `NAME=VALUE` (the line itself is not shown: it may hold a key)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError) as err:
        reason = getattr(err, "strerror", None) or type(err).__name__
        raise SweepConfigError(str(path), [Problem("", f"cannot read: {reason}")]) from None
    found: dict[str, str] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        match = _LINE.fullmatch(line)
        if match is None:
            raise SweepConfigError(
                str(path), [Problem(f"line {number}", "expected NAME=VALUE (a # starts a comment)")]
            )
        found[match.group(1)] = _value(match.group(2))
    return found


def _value(text: str) -> str:
    if len(text) >= 2 and text[0] in "'\"" and text[-1] == text[0]:
        return text[1:-1]
    return re.split(r"\s+#", text, maxsplit=1)[0].strip()


def key_sources(config_path: Path, environ: Mapping[str, str]) -> KeySources:
    """`environ`, completed by the `.env` file in the config's directory where it has no value."""
    file = config_path.parent / DOTENV
    from_file = {k: v for k, v in read_dotenv(file).items() if v and not environ.get(k)}
    return KeySources({**environ, **from_file}, tuple(sorted(from_file)), file)
