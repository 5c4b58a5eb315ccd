"""What a sweep's processes import at their start.

Every process of a sweep imports its entry module before doing anything: the sweep itself,
each engine process, each embedded-server process. `mujoco.mjx` is the MJX backend's alone (it
imports its own copy of MuJoCo Warp and Warp: ~4 s a process on a 2-core machine, paid by
every process when the JAX set-up imported it); matplotlib is the report's figures' alone; the
server's processes (ten on a 16-core GPU host) need neither JAX nor Warp. Each entry is
imported in a fresh interpreter, all of them at once.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

MJX_AND_FIGURES = ("mujoco.mjx", "matplotlib")
ENTRIES: dict[str, tuple[str, ...]] = {
    "vabench.sweep.__main__": MJX_AND_FIGURES,  # the sweep (and `--dry-run`, `--help`)
    "vabench.sweep.process_executor": MJX_AND_FIGURES,  # an engine process
    "vabench.sweep.ray_engine": MJX_AND_FIGURES,  # an engine on a Ray cluster
    "vabench.tuning.precompile": MJX_AND_FIGURES,  # a fresh machine's compiling children
    "vabench.sim_mjx.warp.batch": MJX_AND_FIGURES,  # Warp physics
    "vabench.render.warp_renderer": MJX_AND_FIGURES,  # Warp images
    "vabench.sim_mjx.cpu": MJX_AND_FIGURES,  # C MuJoCo
    "vabench.llm_pool.server": (*MJX_AND_FIGURES, "jax", "warp", "mujoco_warp"),  # server
    # The check itself: the MJX backend does import mjx.
    "vabench.sim_mjx.mjx_batch": (),
}
PROBE = (
    "import importlib, json, sys; importlib.import_module(sys.argv[1]); "
    "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
    "('mujoco', 'matplotlib', 'jax', 'warp', 'mujoco_warp'))))"
)


@pytest.fixture(scope="module")
def imported() -> dict[str, set[str]]:
    """The modules of interest each entry imports, from interpreters run side by side."""
    runs = {
        entry: subprocess.Popen(
            [sys.executable, "-c", PROBE, entry], stdout=subprocess.PIPE, text=True
        )
        for entry in ENTRIES
    }
    found = {}
    for entry, run in runs.items():
        out, _ = run.communicate(timeout=300)
        assert run.returncode == 0, f"importing {entry} failed"
        found[entry] = set(json.loads(out.strip().splitlines()[-1]))
    return found


def _has(modules: set[str], name: str) -> bool:
    return any(m == name or m.startswith(name + ".") for m in modules)


@pytest.mark.parametrize("entry", [e for e, never in ENTRIES.items() if never])
def test_a_process_s_entry_imports_nothing_its_work_never_uses(imported, entry):
    unused = [name for name in ENTRIES[entry] if _has(imported[entry], name)]
    assert not unused, f"{entry} imports {unused} at its start"


def test_the_probe_sees_an_import_where_there_is_one(imported):
    assert _has(imported["vabench.sim_mjx.mjx_batch"], "mujoco.mjx")
    assert _has(imported["vabench.sim_mjx.warp.batch"], "mujoco_warp")
