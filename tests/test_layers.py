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


# -- the physics choice is a typed value: no backend name is tested as a string (issue 32) ----
BACKEND_NAMES = frozenset({"c", "mjx", "warp", "jax", "mjx/warp", "mjx/jax"})
"""Physics and renderer backend names: the config's and the command lines' spellings, and the
two-part labels records carry."""
TWO_PART_NAMES = frozenset({"mjx/warp", "mjx/jax"})
"""Labels that only a backends module may write at all (anywhere else they are a test of the
choice's label, a copy of the rule that names it)."""
BACKEND_MODULES = frozenset({"sim_mjx/backends.py", "render/backends.py"})
"""Where backend names are read and written: everything else receives a typed choice."""


def _names_in(node: ast.expr) -> list[str]:
    """The string constants a comparison operand holds: itself, or the items of a literal
    tuple, list or set (`x in ("mjx", "c")`)."""
    items = node.elts if isinstance(node, ast.Tuple | ast.List | ast.Set) else [node]
    return [i.value for i in items if isinstance(i, ast.Constant) and isinstance(i.value, str)]


def backend_string_tests(path: Path) -> list[tuple[int, str]]:
    """(line, name) of every comparison with a backend name in `path` (`== "c"`, `!= "mjx"`,
    `in ("mjx", "c")`, `case "warp":`) and of every two-part label written anywhere. A
    declaration that lists names (a `Literal[...]`, argparse `choices=`, a default) is not a
    comparison, so the config schema's `Literal` of accepted spellings is not flagged here;
    `tests/test_config.py` checks that it lists what `sim_mjx.backends` accepts."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Compare):
            for operand in (node.left, *node.comparators):
                found += [(node.lineno, s) for s in _names_in(operand) if s in BACKEND_NAMES]
        elif isinstance(node, ast.MatchValue):
            found += [(node.lineno, s) for s in _names_in(node.value) if s in BACKEND_NAMES]
        elif isinstance(node, ast.Constant) and node.value in TWO_PART_NAMES:
            found.append((node.lineno, node.value))
    return sorted(set(found))  # a two-part label compared is both a comparison and a label


def test_no_backend_name_is_compared_outside_the_backends_modules():
    """The physics and renderer choices are made in `sim_mjx/backends.py` and
    `render/backends.py` and passed on as typed values (`Choice.kind`, `batched`, `is_warp`,
    ...): a string test elsewhere is a second copy of a decision, which drifts (issue 32: the
    auto rule was resolved five times and tested as strings twelve times)."""
    problems = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel in BACKEND_MODULES:
            continue
        found = backend_string_tests(path)
        problems += [f"vabench/{rel}:{line}: {name!r}" for line, name in found]
    assert not problems, "backend names tested outside the backends modules:\n" + "\n".join(
        problems
    )


def test_the_backend_checker_sees_every_spelling_of_a_test(tmp_path):
    module = tmp_path / "m.py"
    module.write_text(
        "a = backend == 'c'\n"
        "b = choice.impl in ('jax', 'warp')\n"
        "c = {'mjx/warp': 1}\n"
        "match x:\n"
        "    case 'mjx':\n"
        "        pass\n"
        "d = Literal['auto', 'warp', 'mjx', 'c']\n"  # a declaration: not a test
        "e = kind == 'cpu'\n"  # not a backend name
    )
    assert backend_string_tests(module) == [
        (1, "c"),
        (2, "jax"),
        (2, "warp"),
        (3, "mjx/warp"),
        (5, "mjx"),
    ]
