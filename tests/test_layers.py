"""The packages of vabench form layers, and no import runs upward.

A package may import its own modules, the packages of lower layers and, within its layer, none
of the others: a change to a lower layer never needs a higher one, and the dependency graph has
no cycle. Imports inside functions count too (a lazy import is still a dependency); the only
way around a layer is a name resolved at run time (the embedded server's plugged policies,
`llm_pool.policies.PLUGGED_POLICIES`), which this test reads as the data it is.
"""

from __future__ import annotations

import ast
import itertools
import re
from pathlib import Path

import vabench

ROOT = Path(vabench.__file__).parent

LAYERS: tuple[frozenset[str], ...] = tuple(
    frozenset(layer.split())
    for layer in (
        "switches",  # the VABENCH_* environment variables: no vabench imports
        "field_errors children tables run_layout machine_cache",  # none but switches
        "protocol",  # the model-facing decisions
        "sim_mjx",  # physics backends and the executor
        "tasks",  # task families over the simulator
        "render llm_pool reference_agent",  # images, model calls and their limit board, the
        # non-LLM agent
        "seeds demos tuning",  # seed screening; demonstrations; the GPU and host tuning
        # beneath the sweep
        "agent",  # episodes, learning sessions and the learning stage of a run directory
        "run_records",  # a sweep's results.jsonl read back
        "diagnostics",  # annotations and agreement statistics of recorded episodes
        "report config",  # tables of a run; the sweep's config and its machine choices
        "check",  # each model's endpoint tried once with the sweep's inputs; the dry run's pace
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


# -- the run directory's names, spelled in one module ----------------------------------------

RUN_LAYOUT = "run_layout.py"
NOT_IN_A_RUN_DIR = {
    ("demos/store.py", "frames"): "the demonstration cache's <cache_dir>/<task>/frames/",
}
"""(module, name) pairs that spell a name of another directory, which happens to match."""
PATH_CALLS = frozenset(
    {"Path", "PurePath", "PurePosixPath", "joinpath", "join", "glob", "rglob"}
    | {"with_name", "with_stem", "with_suffix"}
)
PATH_PARTS = frozenset({"parts", "name", "stem", "parent"})


def run_dir_names() -> dict[str, str]:
    """The names the run directory is made of: `vabench.run_layout`'s public str constants."""
    from vabench import run_layout

    return {
        const: value
        for const, value in vars(run_layout).items()
        if const.isupper() and not const.startswith("_") and isinstance(value, str)
    }


def _path_literals(tree: ast.AST) -> set[int]:
    """ids of the str constants used as a path: operands of `/`, arguments of a path call,
    values of an UPPER_CASE constant, compared with a path's parts or name."""
    found: set[int] = set()

    def mentions_path_part(node: ast.AST) -> bool:
        return any(
            (isinstance(n, ast.Attribute) and n.attr in PATH_PARTS)
            or (isinstance(n, ast.Name) and n.id in PATH_PARTS)
            for n in ast.walk(node)
        )

    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            found |= {id(node.left), id(node.right)}
        elif isinstance(node, ast.Call):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if called in PATH_CALLS:
                found |= {id(arg) for arg in node.args}
        elif isinstance(node, ast.Assign | ast.AnnAssign) and node.value is not None:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id.isupper() for t in targets):
                found.add(id(node.value))
        elif isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            if any(mentions_path_part(o) for o in operands):
                for o in operands:
                    found |= {id(n) for n in ast.walk(o) if isinstance(n, ast.Constant)}
    return found


def _spells(text: str, name: str, used_as_path: bool) -> bool:
    """Whether the literal `text` spells the run directory name `name` (rules: the test)."""
    word = re.escape(name)
    if name.endswith("_"):  # a prefix of numbered folders and files: seed_<s>, step_<NNN>
        return text == name or re.search(rf"(?<![\w.-]){word}(?=\{{\}}|\d)", text) is not None
    if "." in name:  # a file name: distinctive wherever it stands
        return re.search(rf"(?<![\w.-]){word}(?![\w-])", text) is not None
    if used_as_path and text == name:
        return True
    if text.startswith("/"):  # an absolute path or a URL route: never inside a run directory
        return False
    after_slash = rf"(?<=/){word}(?![\w.-])"
    before_slash = rf"(?<![\w.-]){word}/(?=\{{\}}|$|[^\w.-])"
    return re.search(f"{after_slash}|{before_slash}", text) is not None


def spelled_run_dir_names(path: Path, names: dict[str, str]) -> list[tuple[int, str, str]]:
    """(line, name, literal) of every string literal of `path` that spells a run directory
    name; an f-string is read whole, each replacement field as `{}`."""
    tree = ast.parse(path.read_text(), str(path))
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            skip.add(id(node.value))  # docstrings: prose about the layout
        elif isinstance(node, ast.JoinedStr):
            skip |= {id(v) for v in node.values}  # read with their f-string
    as_path = _path_literals(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            text = "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
        elif isinstance(node, ast.Constant) and type(node.value) is str and id(node) not in skip:
            text = node.value
        else:
            continue
        found += [
            (node.lineno, name, text)
            for name in names.values()
            if _spells(text, name, id(node) in as_path)
        ]
    return sorted(found)


def test_run_directory_names_are_spelled_only_by_run_layout():
    """Every file and folder name of a sweep's run directory is `vabench.run_layout`'s: no
    other vabench module spells one in a string literal (docstrings aside: they are prose).

    The names are run_layout's public str constants, read from the module. A literal spells
    one (an f-string read whole, each replacement field as `{}`) when it holds
    - a file name (a name with a dot: results.jsonl, result.json) anywhere, as a whole word:
      such a name is unmistakable, even in a message or a help text;
    - a numbered prefix (a name ending in "_": seed_, step_) equal to the literal or followed by
      a number or a field (`seed_{}`), so `step_budget` and `run_ray` are not names;
    - a folder name (episodes, frames, summaries, report, ...) as a segment of a relative
      path: after a "/" (`runs/episodes`) or before a "/" that ends the path or precedes a field
      (`frames/{}`); "5.7 episodes/s" is prose and "/api/annotations" a URL route;
    - a folder name equal to the whole literal where the literal is used as a path: an operand
      of `/`, an argument of a path call (Path, joinpath, glob, rglob, with_name, ...), the
      value of an UPPER_CASE constant (a second definition), or compared with a path's parts
      or name. A dict key, a JSON field or a column header named "episodes" or "summaries" is
      not a path, and is left alone.
    `NOT_IN_A_RUN_DIR` lists the names of other directories that match, with their reason.
    """
    names = run_dir_names()
    assert {"results.jsonl", "events.jsonl", "seed_", "episodes"} <= set(names.values())
    problems = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel == RUN_LAYOUT:
            continue
        for line, name, text in spelled_run_dir_names(path, names):
            if (rel, name) not in NOT_IN_A_RUN_DIR:
                problems.append(f"vabench/{rel}:{line}: {name!r} spelled in {text!r}")
    assert not problems, "use vabench.run_layout:\n" + "\n".join(problems)


def test_the_name_checker_tells_paths_from_prose(tmp_path):
    """The rules of the test above, on the literals they were made for: it can fail."""
    module = tmp_path / "m.py"
    module.write_text(
        '''"""Docstrings may say results.jsonl and episodes/."""
LEDGER = "results.jsonl"
SUMMARIES_DIR = "summaries"
def f(run_dir, d, k, m, n, seed, step, parts, row):
    a = run_dir / "episodes" / f"seed_{seed}"
    b = d / f"step_{step:03d}.jpg"
    c = f"frames/{step}"
    e = f"not in {run_dir}/results.jsonl"
    g = parts[0] in ("episodes", "summaries")
    h = d.name.startswith("partial_")
    ok = {"episodes": n, "report": 1}, row["summaries"], "5.7 episodes/s", "/api/annotations"
    ok2 = "step_budget", "run_ray", "result.jsonl", "report", k.get("summaries")
'''
    )
    found = {(line, name) for line, name, _ in spelled_run_dir_names(module, run_dir_names())}
    assert found == {
        (2, "results.jsonl"),
        (3, "summaries"),
        (5, "episodes"),
        (5, "seed_"),
        (6, "step_"),
        (7, "frames"),
        (8, "results.jsonl"),
        (9, "episodes"),
        (9, "summaries"),
        (10, "partial_"),
    }


# -- the physics choice is a typed value: no backend name is tested as a string ----------
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
    ...): a string test elsewhere is a second copy of a decision, which drifts (the
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


# -- no import cycle between modules, inside a package too ----------------------------------


def module_name(path: Path, root: Path = ROOT) -> str:
    """The dotted name of the module at `path` (a package's `__init__.py` is the package)."""
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports(path: Path, modules: frozenset[str], root: Path = ROOT) -> list[tuple[int, str]]:
    """(line, imported module) of every import of a module of `modules` in `path`, at any
    depth: in functions and under `if TYPE_CHECKING:` too.

    Relative imports are resolved against the module's package. `from p import n` imports the
    submodule `p.n` where there is one, else a name of `p` (the module `p`, or its
    `__init__.py` for a package); `import p.m` imports `p.m`. The packages above an imported
    module are not counted, though Python runs their `__init__.py` first: a package that
    re-exports its modules would otherwise be in a cycle with every module that imports a
    sibling, which is no dependency of the importer on the package's names."""
    own = module_name(path, root)
    package = own if path.name == "__init__.py" else own.rpartition(".")[0]

    def known(name: str) -> str | None:  # the module `name` is, or the one defining it
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [known(alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, *([base] if base else [])])
            targets = [
                f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else known(base)
                for alias in node.names
            ]
        else:
            continue
        found += [(node.lineno, t) for t in targets if t is not None and t != own]
    return sorted(set(found))


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every elementary cycle of `graph` (module -> the modules it imports), each once, as the
    path from its smallest module back to it."""
    importers: dict[str, set[str]] = {m: set() for m in graph}
    for module, imported in graph.items():
        for other in imported:
            importers.setdefault(other, set()).add(module)
    cycles = []
    for start in sorted(graph):
        # the modules after `start` from which `start` can be reached: the only ways back
        back, todo = {start}, [start]
        while todo:
            for m in importers.get(todo.pop(), ()):
                if m > start and m not in back:
                    back.add(m)
                    todo.append(m)
        paths = [[start]]
        while paths:
            path = paths.pop()
            for nxt in sorted(graph.get(path[-1], set()) & back, reverse=True):
                if nxt == start:
                    cycles.append([*path, start])
                elif nxt not in path:
                    paths.append([*path, nxt])
    return sorted(cycles)


def test_no_import_cycle_between_modules():
    """No module imports itself through others, inside a package as across packages (the
    layers above rule out only the latter): a cycle means neither module can be read, tested
    or changed without the other, and a lazy import is how one hides. Imports in functions and
    under `if TYPE_CHECKING:` count: a reader of the lower module must still read the higher
    one, and the cycle is only hidden from the interpreter. The shared piece belongs in a
    module below both."""
    paths = {module_name(p): p for p in sorted(ROOT.rglob("*.py"))}
    modules = frozenset(paths)
    lines = {m: module_imports(p, modules) for m, p in paths.items()}
    graph = {m: {imported for _, imported in found} for m, found in lines.items()}
    cycles = import_cycles(graph)
    edges = sorted(
        {
            (paths[a].relative_to(ROOT).as_posix(), line, b)
            for cycle in cycles
            for a, b in itertools.pairwise(cycle)
            for line, imported in lines[a]
            if imported == b
        }
    )
    problems = [" -> ".join(cycle) for cycle in cycles] + ["where:"]
    problems += [f"  vabench/{rel}:{line}: imports {b}" for rel, line, b in edges]
    assert not cycles, "import cycles:\n" + "\n".join(problems)


def test_the_cycle_checker_resolves_imports_and_finds_every_cycle(tmp_path):
    """Relative and absolute imports, a submodule and a name imported `from` a package, lazy
    and TYPE_CHECKING imports; every cycle of a graph, once each, longer ones too."""
    root = tmp_path / "vabench"
    (root / "pkg" / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "pkg/__init__.py": "from vabench.pkg.a import A\n",
        "pkg/a.py": "from . import b\nfrom .sub import c\n",
        "pkg/b.py": (
            "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n    from vabench.pkg.a import A\n"
            "def f():\n    import vabench.pkg.sub.c\n"
        ),
        "pkg/sub/__init__.py": "",
        "pkg/sub/c.py": (
            "from ..b import f\nfrom vabench.pkg import A, b\nfrom vabench import pkg\n"
        ),
    }
    for name, text in files.items():
        (root / name).write_text(text)
    paths = {module_name(p, root): p for p in root.rglob("*.py")}
    modules = frozenset(paths)
    found = {m: module_imports(p, modules, root) for m, p in paths.items()}
    assert found == {
        "vabench": [],
        "vabench.pkg": [(1, "vabench.pkg.a")],
        "vabench.pkg.a": [(1, "vabench.pkg.b"), (2, "vabench.pkg.sub.c")],
        "vabench.pkg.b": [(3, "vabench.pkg.a"), (5, "vabench.pkg.sub.c")],
        "vabench.pkg.sub": [],
        "vabench.pkg.sub.c": [(1, "vabench.pkg.b"), (2, "vabench.pkg"), (2, "vabench.pkg.b")]
        + [(3, "vabench.pkg")],
    }
    graph = {"a": {"b", "d"}, "b": {"a", "c"}, "c": {"a", "b"}, "d": set(), "e": {"e"}}
    assert import_cycles(graph) == [
        ["a", "b", "a"],
        ["a", "b", "c", "a"],
        ["b", "c", "b"],
        ["e", "e"],
    ]
