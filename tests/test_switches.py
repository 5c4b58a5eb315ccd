"""The `VABENCH_*` switches: declared once (`vabench.switches`), each a config field or a
message, read through the module only, overriding their field, handed to child processes and
kept in the run directory."""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import typing
from pathlib import Path

import pytest
import yaml

from vabench import switches
from vabench.config import SweepConfig, SweepConfigError, load_config
from vabench.config.choices import choose
from vabench.sim_mjx.backends import resolve
from vabench.switches import SWITCHES, Cache, Folder, SwitchError, Text
from vabench.tuning.engine_env import child_environment

ROOT = Path(__file__).resolve().parents[1]
MODEL = {"name": "m", "api": "openai_chat", "base_url": "http://127.0.0.1:9/v1"}

BAD = {  # a value each parser refuses (folders and names accept any text)
    "OneOf": ["nonsense", ""],
    "Whole": ["many", "0", "1.5"],
    "Seconds": ["soon", "-1", "inf"],
    "Device": ["gpu0", "cuda:x"],
    "Flag": ["yes"],
}


@pytest.fixture
def environ_kept():
    """os.environ as it was, after the test (a sweep run in this process sets switches)."""
    before = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(before)


def write(tmp_path: Path, doc: dict, name: str = "sweep.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


# -- the declarations ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SWITCHES))
def test_each_switch_reads_its_default_and_refuses_a_bad_value_by_name(name):
    switch = SWITCHES[name]
    assert switches.get(name, {}) == switch.default
    assert switches.get(name, {switch.env: ""}) == switch.default  # empty counts as unset
    if switch.default is not None:
        assert switch.read(switches.as_text(switch.default)) == switch.default
    kind = type(switch.parse).__name__
    if isinstance(switch.parse, Folder | Text | Cache):
        assert switch.read("some/where") == "some/where"
        return
    for bad in BAD[kind]:
        if not bad:
            continue
        with pytest.raises(SwitchError) as info:
            switches.get(name, {switch.env: bad})
        message = str(info.value)
        assert message.startswith(f"{switch.env} must be ") and repr(bad) in message
        assert switch.parse.allowed in message


def test_every_behaviour_and_measurement_switch_is_a_field_with_the_same_default():
    config = SweepConfig(name="x", out="x", models=(), tracks=(), tasks=(), seeds={})
    values = config.switch_values()
    fields = {s.name for s in SWITCHES.values() if s.field is not None}
    kinds = {s.name for s in SWITCHES.values() if s.kind != "message"}
    assert fields == kinds == set(values)
    assert values == {n: SWITCHES[n].default for n in fields}
    assert {s.name for s in SWITCHES.values() if s.kind == "message"} == {
        "cores",
        "gpu_share",
        "ray_mps",
        "ray_mps_ranked",
    }


def _literal(path: str, name: str) -> tuple[str, ...]:
    """The tuple of strings module `path` assigns to `name` (read, not imported: Warp)."""
    for node in ast.parse((ROOT / path).read_text()).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == name for t in node.targets
        ):
            return tuple(ast.literal_eval(node.value))
    raise AssertionError(f"{path} assigns no {name}")


def test_the_choices_agree_with_their_fields_and_the_modules_that_use_them():
    from vabench.config import schema

    field_types = {
        "warp_loop": schema.SimulatorOptions,
        "cuda_sync": schema.SimulatorOptions,
        "matmul_precision": schema.SimulatorOptions,
        "warp_jpeg": schema.RenderOptions,
        "warp_precompile": schema.ExecutorOptions,
    }
    for name, section in field_types.items():
        leaf = str(SWITCHES[name].field).split(".")[1]
        annotation = section.model_fields[leaf].annotation
        assert typing.get_args(annotation) == SWITCHES[name].parse.values, name
    assert SWITCHES["warp_loop"].parse.values == _literal("vabench/sim_mjx/warp/graphs.py", "LOOPS")
    assert SWITCHES["cuda_sync"].parse.values == _literal(
        "vabench/sim_mjx/warp/cuda_sync.py", "MODES"
    )
    jpeg = _literal("vabench/render/warp_renderer.py", "JPEG_CHOICES")
    assert set(SWITCHES["warp_jpeg"].parse.values) == set(jpeg)


def test_the_table_in_setup_is_the_modules():
    printed = subprocess.run(
        [sys.executable, "-m", "vabench.switches"],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
    ).stdout.strip()
    assert printed == switches.table()
    setup = (ROOT / "docs" / "SETUP.md").read_text()
    section = setup.split("## Environment variables\n", 1)[1]
    rows = [line for line in section.splitlines() if line.startswith("|")]
    assert "\n".join(rows) == printed, "run `python -m vabench.switches` into docs/SETUP.md"
    assert len(rows) == 2 + len(SWITCHES)


# -- precedence: the environment over the config ------------------------------------------------


def test_the_environment_overrides_a_config_field(tmp_path):
    doc = {
        "models": [MODEL],
        "tracks": ["active"],
        "render": {"warp_jpeg": "nvjpeg"},
        "simulator": {"warp_loop": "per_step"},
    }
    path = write(tmp_path, doc)
    as_written = load_config(path, environ={})
    assert (as_written.render.warp_jpeg, as_written.simulator.warp_loop) == ("nvjpeg", "per_step")
    env = {"VABENCH_WARP_JPEG": "host", "VABENCH_HOSTLOAD_S": "5", "VABENCH_WARP_PRECOMPILE": "0"}
    config = load_config(path, environ=env)
    assert config.render.warp_jpeg == "host"
    assert config.simulator.warp_loop == "per_step"  # not in the environment: the config's
    assert config.profiling.hostload_s == 5.0
    assert config.executor.precompile == "off"  # the old spelling 0
    assert config.document()["render"]["warp_jpeg"] == "host"  # sweep.yaml says so
    effective = switches.resolve(as_written.switch_values(), env)
    assert effective.values["warp_jpeg"] == "host" and effective.values["warp_loop"] == "per_step"
    assert effective.from_environment == ("warp_jpeg", "warp_precompile", "hostload_s")
    machine_env = {**env, "VABENCH_CORES": "2", "CUDA_VISIBLE_DEVICES": ""}
    choices = choose(as_written, None, machine_env)
    (line,) = [x for x in choices.lines() if x.startswith("switches:")]
    assert "render.warp_jpeg=host (VABENCH_WARP_JPEG)" in line
    assert "profiling.hostload_s=5 (VABENCH_HOSTLOAD_S)" in line
    assert "warp_loop" not in line


def test_a_bad_value_in_the_environment_is_a_config_error_naming_field_and_variable(tmp_path):
    path = write(tmp_path, {"models": [MODEL], "tracks": ["active"]})
    env = {"VABENCH_WARP_LOOP": "sideways", "VABENCH_RENDER_CONCURRENCY": "0"}
    with pytest.raises(SweepConfigError) as info:
        load_config(path, environ=env)
    lines = str(info.value).splitlines()
    assert len(lines) == 2
    assert lines[0] == (
        f"error: {path}: simulator.warp_loop: VABENCH_WARP_LOOP must be one of device, "
        "per_step, unrolled, got 'sideways' (the variable overrides this field)"
    )
    assert "render.concurrency: VABENCH_RENDER_CONCURRENCY must be a whole number >= 1" in lines[1]


def test_the_config_values_reach_this_process_and_its_children():
    values = {**{n: s.default for n, s in SWITCHES.items()}, "warp_loop": "unrolled"}
    values["render_concurrency"], values["hostload_s"] = 2, 0.0
    environ = {"VABENCH_HOSTLOAD_S": "0.0"}  # the user's own spelling is left as it is
    assert switches.apply(values, environ) == {
        "VABENCH_WARP_LOOP": "unrolled",
        "VABENCH_RENDER_CONCURRENCY": "2",
    }
    assert environ["VABENCH_HOSTLOAD_S"] == "0.0"
    c = resolve("c")
    child = child_environment(c, environ)
    assert child["VABENCH_WARP_LOOP"] == "unrolled" and child["VABENCH_HOSTLOAD_S"] == "0"
    assert switches.current(child) == switches.current(environ)
    assert not any(k.startswith("VABENCH_") for k in child_environment(c, {}))


def test_jax_is_set_again_from_switches_that_arrive_after_its_import(tmp_path):
    """The sweep's process imports JAX's set-up before its config is read; `configure_jax`
    sets the cache and precision again (in a process of its own: JAX's config is global)."""
    script = (
        "import os, jax\n"
        "from vabench.sim_mjx import jax_setup\n"
        "from vabench.sim_mjx.backends import resolve\n"
        "from vabench.tuning.engine_env import configure_jax\n"
        "def now():\n"
        "    return jax.config.jax_default_matmul_precision, jax.config.jax_compilation_cache_dir\n"
        "before = now()\n"
        "os.environ['VABENCH_MATMUL_PRECISION'] = 'default'\n"
        "os.environ['VABENCH_JAX_CACHE'] = os.environ['AT']\n"
        "configure_jax(resolve('c'))\n"
        "print((before, now()))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("VABENCH_", "JAX_"))}
    env |= {"PYTHONPATH": str(ROOT), "AT": str(tmp_path), "HOME": str(tmp_path / "home")}
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300
    )
    assert done.returncode == 0, done.stderr
    home_cache = str(tmp_path / "home" / ".cache" / "vabench" / "jax")
    assert done.stdout.strip() == str((("highest", home_cache), (None, str(tmp_path))))


# -- the run directory --------------------------------------------------------------------------

TINY = """\
name: tiny
models:
  - {name: local, api: openai_chat, base_url: embedded}
embedded_server: {policy: random_action}
tracks: [{name: active, protocol: active, summaries: none}]
tasks: [grasp_single_cube]
seeds: {verified: 1}
runs: 1
step_budget: 1
simulator: {backend: c, warp_loop: per_step}
render: {width: 64, height: 48, workers: 1}
"""


def test_plan_json_of_a_tiny_sweep_holds_every_switch(tmp_path, monkeypatch, environ_kept, caplog):
    import logging

    from vabench.sweep.__main__ import main

    caplog.set_level(logging.INFO)
    cfg, out = tmp_path / "tiny.yaml", tmp_path / "out"
    cfg.write_text(TINY)
    monkeypatch.setenv("VABENCH_HOSTLOAD_S", "7")
    monkeypatch.delenv("VABENCH_WARP_LOOP", raising=False)
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    plan = json.loads((out / "plan.json").read_text())
    assert set(plan["switches"]) == set(SWITCHES)
    assert plan["switches"]["warp_loop"] == "per_step"  # the config's
    assert plan["switches"]["hostload_s"] == 7.0  # the environment's
    assert plan["switches"]["cores"] == switches.get("cores")  # a message, as the sweep read it
    assert "earlier_switches" not in plan
    assert os.environ["VABENCH_WARP_LOOP"] == "per_step"  # for the processes it starts
    (overridden,) = [m for m in caplog.messages if m.startswith("switches:")]  # said once
    assert "profiling.hostload_s=7 (VABENCH_HOSTLOAD_S)" in overridden
    assert overridden.endswith(": the environment over the config")
    assert "warp_loop" not in overridden  # the config's own value is no override
    swept = yaml.safe_load((out / "sweep.yaml").read_text())
    assert swept["profiling"]["hostload_s"] == 7.0

    monkeypatch.setenv("VABENCH_HOSTLOAD_S", "9")  # a resume under other switches: recorded
    assert main([str(cfg), "--out", str(out), "--plain", "--no-report"]) == 0
    again = json.loads((out / "plan.json").read_text())
    assert again["switches"]["hostload_s"] == 9.0
    assert again["earlier_switches"] == [plan["switches"]]
    assert again["episodes"] == plan["episodes"] and again["fields"] == plan["fields"]


# -- reads go through the module ----------------------------------------------------------------

ALLOWED: dict[str, str] = {}
"""Files that may read a `VABENCH_*` variable themselves, with which (none)."""
SCANNED = ("vabench", "benchmarks")


def _is_environ(node: ast.expr) -> bool:
    return (isinstance(node, ast.Name) and node.id in ("environ", "env")) or (
        isinstance(node, ast.Attribute) and node.attr == "environ"
    )


def variable_constants(paths: list[Path]) -> set[str]:
    """Names bound at module level to a VABENCH_ variable (`X = "VABENCH_..."` or
    `X = switches.variable(...)`), in any of `paths`."""
    names = set()
    for path in paths:
        for node in ast.parse(path.read_text()).body:
            if not isinstance(node, ast.Assign):
                continue
            value = node.value
            literal = isinstance(value, ast.Constant) and str(value.value).startswith("VABENCH_")
            call = (
                isinstance(value, ast.Call)
                and isinstance(value.func, ast.Attribute)
                and value.func.attr == "variable"
            )
            if literal or call:
                names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    return names


def environment_reads(path: Path, constants: set[str]) -> list[tuple[int, str]]:
    """(line, key) of every read of a VABENCH_ variable from an environment mapping in `path`:
    `environ.get(K)`, `os.getenv(K)`, `environ[K]` (not assigned), `K in environ`, where K is
    a "VABENCH_..." literal or a constant of `constants`."""

    def key(node: ast.expr) -> str | None:
        if isinstance(node, ast.Constant) and str(node.value).startswith("VABENCH_"):
            return str(node.value)
        name = node.id if isinstance(node, ast.Name) else getattr(node, "attr", None)
        return name if name in constants else None

    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.args:
            f = node.func
            environ_get = f.attr in ("get", "pop", "setdefault") and _is_environ(f.value)
            getenv = f.attr == "getenv"
            setting = f.attr == "setdefault" and len(node.args) > 1  # a default set: no read
            if (environ_get or getenv) and not setting and (k := key(node.args[0])):
                found.append((node.lineno, k))
        elif isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load):
            if _is_environ(node.value) and (k := key(node.slice)):
                found.append((node.lineno, k))
        elif (
            isinstance(node, ast.Compare)
            and any(isinstance(o, ast.In) for o in node.ops)
            and any(_is_environ(c) for c in node.comparators)
            and (k := key(node.left))
        ):
            found.append((node.lineno, k))
    return found


def _scanned() -> list[Path]:
    return sorted(p for d in SCANNED for p in (ROOT / d).rglob("*.py"))


def test_no_vabench_variable_is_read_outside_the_switches_module():
    paths = _scanned()
    constants = variable_constants(paths)
    offenders: dict[str, list[str]] = {}
    for path in paths:
        rel = path.relative_to(ROOT).as_posix()
        if rel == "vabench/switches.py":
            continue
        for line, k in environment_reads(path, constants):
            offenders.setdefault(rel, []).append(f"{rel}:{line}: {k}")
    unexpected = [o for rel, lines in offenders.items() if rel not in ALLOWED for o in lines]
    assert not unexpected, "read these through vabench.switches.get:\n" + "\n".join(unexpected)
    stale = sorted(set(ALLOWED) - set(offenders))
    assert not stale, f"these read through vabench.switches now: remove from ALLOWED: {stale}"


def test_the_read_checker_finds_every_spelling(tmp_path):
    module = tmp_path / "m.py"
    module.write_text(
        "import os\n"
        "VAR = 'VABENCH_X'\n"
        "a = os.environ.get('VABENCH_A')\n"
        "b = os.environ['VABENCH_B']\n"
        "c = os.getenv(VAR)\n"
        "d = 'VABENCH_D' in environ\n"
        "e = env.get(VAR, '1')\n"
        "os.environ['VABENCH_W'] = '1'\n"  # a write: the sweep telling its children
        "f = os.environ.get('HOME')\n"
        "os.environ.setdefault('VABENCH_S', '1')\n"  # a default set, not a read
    )
    constants = variable_constants([module])
    assert constants == {"VAR"}
    assert environment_reads(module, constants) == [
        (3, "VABENCH_A"),
        (4, "VABENCH_B"),
        (5, "VAR"),
        (6, "VABENCH_D"),
        (7, "VAR"),
    ]


def test_every_variable_the_code_names_is_declared():
    """A VABENCH_ name in any string of vabench's code or the benchmarks (docstrings too) is
    a declared switch: an undeclared one would be read without the module."""
    declared = {s.env for s in SWITCHES.values()}
    named = set()
    for path in _scanned():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                named |= {m.rstrip("_") for m in re.findall(r"VABENCH_[A-Z_]*[A-Z]", node.value)}
    assert named - declared == set()
