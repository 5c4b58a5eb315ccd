"""Warp's kernels compiled side by side before a sweep (vabench/sweep/precompile.py): a family
is compiled once per code and machine, a failure is reported and left to the sweep, and the
child process compiles for real (slow: a whole expert episode on Warp's CPU device)."""

from __future__ import annotations

import json
import threading
import time

import pytest

pytest.importorskip("warp", reason="the Warp backend needs warp-lang (the [test] extra has it)")
pytest.importorskip("mujoco_warp", reason="the Warp backend needs mujoco-warp ([test] extra)")

import warp as wp

from vabench.sweep import precompile


@wp.kernel
def _fill_seven(out: wp.array(dtype=int)):  # type: ignore[valid-type]
    out[wp.tid()] = 7


@pytest.fixture
def markers(tmp_path, monkeypatch):
    monkeypatch.setenv("VABENCH_CACHE", str(tmp_path))
    return tmp_path / "warp_compiled"


def test_a_failing_family_is_reported_and_not_marked(markers):
    failed = precompile.ensure_compiled(["no_such_family"], 64, 48, "cpu", images=False)
    assert failed == ["no_such_family"]
    assert not [p for p in markers.glob("no_such_family.*")]


def test_marked_families_are_not_compiled_again(markers, monkeypatch):
    key = precompile.code_key("sm0", 0, 0)
    markers.mkdir(parents=True)
    (markers / f"grasp_single_cube.{key}").touch()
    assert precompile.missing(["grasp_single_cube", "lift_pot"], key, markers) == ["lift_pot"]
    spawned = []
    monkeypatch.setattr(precompile, "_child", lambda task, size, device: spawned.append(task))
    assert precompile.ensure_compiled(["grasp_single_cube"], 64, 48, "cpu", images=False) == []
    assert spawned == []  # nothing left to compile: no child process


def test_turned_off_by_the_environment(markers, monkeypatch):
    monkeypatch.setenv(precompile.ENV, "0")
    assert precompile.ensure_compiled(["no_such_family"], 64, 48, "cpu") == []
    assert not markers.exists()


@pytest.mark.slow
def test_a_family_compiles_in_a_child_and_is_marked(markers):
    assert precompile.ensure_compiled(["grasp_single_cube"], 64, 48, "cpu") == []
    key = precompile.code_key("sm0", 64, 48)
    assert (markers / f"grasp_single_cube.{key}").exists()


def test_one_family_compiles_alone_first_then_the_rest_side_by_side(markers, monkeypatch):
    """The modules the families share compile once: in the first family's child, in threads,
    before the others start (which then find them in Warp's cache)."""
    events: list[tuple[str, str, int | None]] = []
    guard = threading.Lock()

    def child(task, size, device, threads=None):
        with guard:
            events.append(("start", task, threads))
        time.sleep(0.3)
        with guard:
            events.append(("end", task, threads))
        return "broken" if task == "grasp_single_cube" else None

    monkeypatch.setattr(precompile, "_child", child)
    families = ["grasp_single_cube", "lift_pot", "place_shoe"]
    failed = precompile.ensure_compiled(families, 64, 48, "cpu", images=False, processes=3)
    assert events[:2] == [("start", "grasp_single_cube", 3), ("end", "grasp_single_cube", 3)]
    # the rest side by side, one thread each; the first one's failure does not stop them
    assert [(e[0], e[2]) for e in events[2:]] == [("start", 1)] * 2 + [("end", 1)] * 2
    assert sorted(e[1] for e in events[2:4]) == ["lift_pot", "place_shoe"]
    assert failed == ["grasp_single_cube"]
    key = precompile.code_key("sm0", 0, 0)
    assert precompile.missing(families, key, markers) == ["grasp_single_cube"]


def test_a_family_alone_compiles_in_a_thread_per_core(markers, monkeypatch):
    calls = []
    monkeypatch.setattr(precompile, "_child", lambda *args: calls.append(args[1:]))
    assert precompile.ensure_compiled(["lift_pot"], 64, 48, "cpu", processes=4) == []
    assert calls == [((64, 48), "cpu", 4)]


def test_a_recorded_launch_names_its_module_and_runs_nothing():
    """How a family's modules are found before they are compiled (warp_ahead): while
    recording, a launch records its kernel's module and block size and launches nothing."""
    import warp as wp

    from vabench.sweep import warp_ahead

    out = wp.zeros(4, dtype=int, device="cpu")
    found: warp_ahead.Found = {}
    with warp_ahead.recording(found):
        wp.launch(_fill_seven, dim=4, inputs=[out], device="cpu")
    assert [module for module, _, _ in found.values()] == [_fill_seven.module]
    assert out.numpy().tolist() == [0, 0, 0, 0]  # nothing ran; and launching works again:
    wp.launch(_fill_seven, dim=4, inputs=[out], device="cpu")
    assert out.numpy().tolist() == [7, 7, 7, 7]


@pytest.mark.slow
def test_shared_modules_compile_once(markers, tmp_path, monkeypatch):
    """Two families from an empty Warp cache: no module is compiled twice, and the second
    family compiles only its scene's own few (measured: 3 of 43, 2026-11-26)."""
    monkeypatch.setenv("WARP_CACHE_PATH", str(tmp_path / "warp"))
    stats = tmp_path / "stats"
    stats.mkdir()
    monkeypatch.setenv(precompile.STATS_ENV, str(stats))
    families = ["grasp_single_cube", "lift_pot"]
    assert precompile.ensure_compiled(families, 64, 48, "cpu", processes=2) == []
    compiled = {t: json.loads((stats / f"{t}.json").read_text())["compiled"] for t in families}
    assert len(compiled["grasp_single_cube"]) >= 30
    every = [name for names in compiled.values() for name in names]
    assert len(every) == len(set(every))
    assert len(compiled["lift_pot"]) <= 8
