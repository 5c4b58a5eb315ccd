"""The packages of vabench form layers, and no import runs upward (issue 24).

A package may import its own modules, the packages of lower layers and, within its layer, none
of the others: a change to a lower layer never needs a higher one, and the dependency graph has
no cycle. Imports inside functions count too (a lazy import is still a dependency); the only
way around a layer is a name resolved at run time (the embedded server's plugged policies,
`llm_pool.policies.PLUGGED_POLICIES`), which this test reads as the data it is.
"""

from __future__ import annotations

import ast
from pathlib import Path

import vabench

ROOT = Path(vabench.__file__).parent

LAYERS: tuple[frozenset[str], ...] = tuple(
    frozenset(layer.split())
    for layer in (
        "field_errors children tables",  # no vabench imports
        "protocol",  # the model-facing decisions
        "sim_mjx",  # physics backends and the executor
        "tasks",  # task families over the simulator
        "render llm_pool reference_agent",  # images, model calls, the non-LLM agent
        "agent seeds demos",  # episodes, learning sessions; seed screening; demonstrations
        "run_records",  # a sweep's results.jsonl read back
        "diagnostics",  # annotations and agreement statistics of recorded episodes
        "report config",  # tables of a run; the sweep's config
        "sweep view episode replay",  # the commands
    )
)
LAYER_OF = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, imported vabench package) of every import in `path`, at any depth."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "vabench":
                found += [(node.lineno, alias.name) for alias in node.names]
            elif node.module.startswith("vabench."):
                found.append((node.lineno, _package(node.module)))
        elif isinstance(node, ast.Import):
            found += [
                (node.lineno, _package(alias.name))
                for alias in node.names
                if alias.name.startswith("vabench.")
            ]
    return found


def test_every_package_has_a_layer():
    packages = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    modules = {p.stem for p in ROOT.glob("*.py") if not p.stem.startswith("_")}
    unplaced = (packages | modules) - set(LAYER_OF)
    assert not unplaced, f"give these a layer: {sorted(unplaced)}"


def test_no_import_runs_upward_or_sideways():
    problems = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        own = rel.parts[0].removesuffix(".py")
        if own == "__init__":
            continue
        for line, imported in imports_of(path):
            if imported == own:
                continue
            if LAYER_OF[imported] >= LAYER_OF[own]:
                problems.append(f"vabench/{rel}:{line}: {own} imports {imported}")
    assert not problems, "\n".join(problems)


def test_the_checker_sees_lazy_imports(tmp_path):
    """A function-level import is found, so the test above can fail on one."""
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from vabench.sweep import runner\n    return runner\n")
    assert imports_of(module) == [(2, "sweep")]
