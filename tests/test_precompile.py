"""Warp's kernels compiled side by side before a sweep (vabench/sweep/precompile.py): a family
is compiled once per code and machine, a failure is reported and left to the sweep, and the
child process compiles for real (slow: a whole expert episode on Warp's CPU device)."""

from __future__ import annotations

import pytest

pytest.importorskip("warp", reason="the Warp backend needs warp-lang (the [test] extra has it)")
pytest.importorskip("mujoco_warp", reason="the Warp backend needs mujoco-warp ([test] extra)")

from vabench.sweep import precompile


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
