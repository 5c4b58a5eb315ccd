"""Warp's kernels compiled side by side before a sweep (vabench/tuning/precompile.py): a family
is compiled once per code and machine, a failure is reported and left to the sweep, and the
child process compiles for real (slow: a whole expert episode on Warp's CPU device)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("warp", reason="the Warp backend needs warp-lang (the [test] extra has it)")
pytest.importorskip("mujoco_warp", reason="the Warp backend needs mujoco-warp ([test] extra)")

import warp as wp

from vabench.tuning import precompile


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


def test_every_family_compiles_side_by_side_sharing_one_folder_of_claims(markers, monkeypatch):
    """All families start at once, each child given the same claims folder (so a module shared
    by families is compiled by one of them) and threads beyond the cores; one child's failure
    does not stop the others and leaves its family unmarked."""
    events: list[tuple[str, str, int, object]] = []
    guard = threading.Lock()
    together = threading.Barrier(3, timeout=30)  # fails unless all three run at once

    def child(task, size, device, threads, claims=None, stats=None, nice=0, ready=None):
        assert claims is not None and claims.is_dir() and stats is not None
        with guard:
            events.append(("start", task, threads, claims))
        together.wait()
        with guard:
            events.append(("end", task, threads, claims))
        return "broken" if task == "grasp_single_cube" else None

    monkeypatch.setattr(precompile, "_child", child)
    families = ["grasp_single_cube", "lift_pot", "place_shoe"]
    failed = precompile.ensure_compiled(families, 64, 48, "cpu", images=False, processes=3)
    assert [e[0] for e in events] == ["start"] * 3 + ["end"] * 3
    assert sorted(e[1] for e in events[:3]) == sorted(families)
    assert {e[2] for e in events} == {2} and len({e[3] for e in events}) == 1
    assert not events[0][3].exists()  # the claims are the run's own, removed after it
    assert failed == ["grasp_single_cube"]
    key = precompile.code_key("sm0", 0, 0)
    assert precompile.missing(families, key, markers) == ["grasp_single_cube"]


def test_a_family_alone_compiles_in_threads_beyond_the_cores(markers, monkeypatch):
    calls = []
    monkeypatch.setattr(precompile, "_child", lambda *args, **kw: calls.append(args[1:4]))
    assert precompile.ensure_compiled(["lift_pot"], 64, 48, "cpu", processes=4) == []
    assert calls == [((64, 48), "cpu", 8)]


def test_a_claimed_module_is_loaded_by_its_holder_and_waited_for_by_the_others(tmp_path):
    """Two loaders of the same modules (threads here; the lock is per open file, so processes
    behave alike): a module the first holds is set aside by the second, which loads every
    free one first, then waits for the held one and loads it after its holder is done."""
    from vabench.tuning import warp_ahead

    holding, release = threading.Event(), threading.Event()
    order: list[tuple[str, str]] = []
    released: list[bool] = []  # asserted here: an exception in a load is only logged

    def first_load(job):
        order.append(("first", job))
        holding.set()
        released.append(release.wait(10))

    first = threading.Thread(
        target=warp_ahead.claimed, args=(["shared"], first_load, str, tmp_path, 1)
    )
    first.start()
    assert holding.wait(10)

    def second_load(job):
        order.append(("second", job))
        if job == "own":
            release.set()  # the free module is done before the held one is waited for

    waited = warp_ahead.claimed(["shared", "own"], second_load, str, tmp_path, 1)
    first.join(10)
    assert waited == 1 and released == [True]
    assert order == [("first", "shared"), ("second", "own"), ("second", "shared")]


def test_without_claims_every_module_is_loaded_at_once(tmp_path):
    from vabench.tuning import warp_ahead

    loaded: list[str] = []
    assert warp_ahead.claimed(["a", "b"], loaded.append, str, None, 2) == 0
    assert sorted(loaded) == ["a", "b"]


def test_a_recorded_launch_names_its_module_and_runs_nothing():
    """How a family's modules are found before they are compiled (warp_ahead): while
    recording, a launch records its kernel's module and block size and launches nothing."""
    import warp as wp

    from vabench.tuning import warp_ahead

    out = wp.zeros(4, dtype=int, device="cpu")
    found: warp_ahead.Found = {}
    with warp_ahead.recording(found):
        wp.launch(_fill_seven, dim=4, inputs=[out], device="cpu")
    assert [module for module, _, _ in found.values()] == [_fill_seven.module]
    assert out.numpy().tolist() == [0, 0, 0, 0]  # nothing ran; and launching works again:
    wp.launch(_fill_seven, dim=4, inputs=[out], device="cpu")
    assert out.numpy().tolist() == [7, 7, 7, 7]


def test_a_recorded_occupancy_query_names_its_module_and_answers():
    """MuJoCo Warp asks CUDA for a kernel's occupancy (`wp.get_suggested_block_size`) before
    some launches; Warp's answer needs the module loaded, so while recording the query is
    answered (and its module recorded) instead of raising and ending the dry step there."""
    import warp as wp

    from vabench.tuning import warp_ahead

    found: warp_ahead.Found = {}
    with warp_ahead.recording(found):
        # a CUDA device, as MuJoCo Warp queries it (this machine may have none: a stand-in
        # with the attributes the query reads)
        block, grid = wp.get_suggested_block_size(_fill_seven, _CudaStandIn())
        assert wp.get_suggested_block_size(_fill_seven, "cpu") == (1, 1)  # as Warp answers
    assert block == 256 and grid == warp_ahead.BLOCKS_PER_SM * 132
    [(module, device, block_dim)] = found.values()  # the CPU query recorded nothing
    assert module is _fill_seven.module and isinstance(device, _CudaStandIn)
    assert block_dim == _fill_seven.module.options["block_dim"]  # the block size it loads


class _CudaStandIn:
    is_cuda, sm_count = True, 132


def test_vabench_s_kernels_in_modules_of_their_own_are_loaded_ahead_with_its_modules():
    """`warp_jpeg._transform` is in a module of its own (`module="unique"`, named after the
    kernel, not after vabench's module) that no dry call launches (the dry render pass encodes
    nothing): left out of what is loaded ahead, each child's check compiled it again, side by
    side, on a fresh host (its renderer loads it). Warp's own modules are not vabench's."""
    from warp._src import context

    from vabench.render import warp_jpeg, warp_scan
    from vabench.tuning import warp_ahead

    own = warp_ahead.own_modules(list(context.user_modules.values()))
    assert warp_jpeg._transform.module.name != warp_jpeg.__name__  # its own module
    for module in (warp_jpeg._transform.module, warp_jpeg._count_bits.module):
        assert any(m is module for m in own), module.name
    assert warp_scan.__name__ in {m.name for m in own}
    assert all(m is not _fill_seven.module for m in own)  # this test's kernel: not vabench's
    assert not any(m.name.startswith("warp.") for m in own)


@pytest.mark.slow
def test_shared_modules_compile_once(markers, tmp_path, monkeypatch):
    """Two families from an empty Warp cache, side by side: no module is compiled twice (the
    claims), and together they compile about one family's modules plus the second's scene's
    own few (measured on Warp's CPU device: 47 and 48 between them, 2026-11-27)."""
    monkeypatch.setenv("WARP_CACHE_PATH", str(tmp_path / "warp"))
    stats = tmp_path / "stats"
    stats.mkdir()
    monkeypatch.setenv(precompile.STATS_ENV, str(stats))
    families = ["grasp_single_cube", "lift_pot"]
    assert precompile.ensure_compiled(families, 64, 48, "cpu", processes=2) == []
    reports = {t: json.loads((stats / f"{t}.json").read_text()) for t in families}
    every = [name for r in reports.values() for name in r["compiled"]]
    assert len(every) == len(set(every))
    assert 30 <= len(every) <= 60


def test_the_summary_reads_the_childrens_reports_and_skips_a_broken_one(tmp_path):
    """A stale or foreign report never breaks the precompile (it would skip every marker)."""
    good = {
        "task": "lift_pot",
        "compiled": ["a", "b"],
        "compile_s": 3.0,
        "s": 9.0,
        "waited": 1,
        "compiled_after": ["b"],
        "parts_s": {"ahead": 5.0, "expert": 4.0},
    }
    (tmp_path / "lift_pot.json").write_text(json.dumps(good))
    (tmp_path / "place_shoe.json").write_text(json.dumps({"task": "place_shoe"}))
    (tmp_path / "grasp_single_cube.json").write_text("not json")
    line = precompile._summary(["lift_pot", "place_shoe", "grasp_single_cube", "none"], tmp_path)
    assert "2 modules compiled" in line and "1 waited for" in line
    assert "1 compiled only after the first step" in line and "slowest lift_pot 9 s" in line
    assert precompile._summary(["place_shoe"], tmp_path) == ""


def test_every_family_of_the_shipped_config_compiles_at_once_on_a_gpu_host():
    """On a 16-core H100 one child a core ran configs/all.yaml's 22 families in two waves (the
    second ~40 s longer, 1.7 cores busy): every child starts at once now, up to two a core."""
    from vabench.tuning.precompile import children

    assert children(22, 16) == (22, 2)
    assert children(8, 16) == (8, 4)  # fewer families: more threads each
    assert children(22, 2) == (4, 2)  # a 2-core machine: 4 at a time
    assert children(1, 1) == (1, 2)


def _hold_machine_lock(markers):
    """The machine's compile lock taken as another process would (its own open file)."""
    import fcntl

    markers.mkdir(parents=True, exist_ok=True)
    handle = open(markers / ".lock", "w")  # noqa: SIM115 (closed by the caller)
    fcntl.flock(handle, fcntl.LOCK_EX)
    return handle


def test_a_family_is_ready_as_its_own_child_ends(markers, monkeypatch):
    """Each family's marker is written when its child ends, not after the last: a sweep's
    fast families start while the basket still compiles (101 s on a fresh H100, 2026-11-28,
    the first episode waiting for all of it)."""
    slow_may_end = threading.Event()

    def child(task, size, device, threads, claims=None, stats=None, nice=0, ready=None):
        if task == "put_everything_in_basket":
            assert slow_may_end.wait(30)
        return None

    monkeypatch.setattr(precompile, "_child", child)
    families = ["put_everything_in_basket", "lift_pot"]
    compiling = precompile.Compiling.start(families, 64, 48, "cpu", images=False)
    key = precompile.code_key("sm0", 0, 0)
    assert compiling.key == key
    deadline = time.monotonic() + 30
    while not compiling.ready("lift_pot"):
        assert time.monotonic() < deadline, "lift_pot never became ready"
        time.sleep(0.05)
    assert (markers / f"lift_pot.{key}").exists()
    assert not compiling.ready("put_everything_in_basket")  # still compiling
    assert precompile.compiling(markers)
    slow_may_end.set()
    compiling.join(30)
    assert compiling.ready("put_everything_in_basket") and not precompile.compiling(markers)
    assert compiling.failed == []


def test_a_failed_family_is_ready_once_nothing_compiles(markers, monkeypatch):
    """A family whose child failed has no marker: its episodes go once the compile is over
    (the sweep compiles it on first use, as before)."""
    monkeypatch.setattr(precompile, "_child", lambda task, *a, **k: "broken")
    compiling = precompile.Compiling.start(["lift_pot"], 64, 48, "cpu", images=False)
    compiling.join(30)
    assert compiling.failed == ["lift_pot"]
    assert not (markers / f"lift_pot.{compiling.key}").exists()
    assert compiling.ready("lift_pot")


def test_a_compile_of_another_process_is_waited_for_family_by_family(markers, monkeypatch):
    """The processes executor's workers: the parent compiles, holding the machine's lock; a
    worker's `Compiling.start` returns at once (it does not wait for the whole compile) and
    each family waits for its marker."""
    import asyncio

    spawned = []
    monkeypatch.setattr(precompile, "_child", lambda task, *a, **k: spawned.append(task))
    handle = _hold_machine_lock(markers)
    try:
        # It returns while the other process still holds the lock (released only below): an
        # order, not a time. Blocked behind the other's compile it would wait for ever, so it
        # runs in a thread whose join is a guard against hanging the suite, not a bound.
        returned: list[precompile.Compiling] = []
        starter = threading.Thread(
            target=lambda: returned.append(
                precompile.Compiling.start(["lift_pot", "place_shoe"], 64, 48, "cpu", False)
            )
        )
        starter.start()
        starter.join(300)
        assert returned, "Compiling.start waited for the other process's compile"
        [compiling] = returned

        async def scenario():
            lift = asyncio.create_task(compiling.wait("lift_pot"))
            shoe = asyncio.create_task(compiling.wait("place_shoe"))
            await asyncio.sleep(2 * precompile.POLL_S)
            assert not lift.done() and not shoe.done()
            (markers / f"lift_pot.{compiling.key}").touch()  # the other's child ended
            await asyncio.wait_for(lift, 10)
            assert not shoe.done()
            (markers / f"place_shoe.{compiling.key}").touch()
            await asyncio.wait_for(shoe, 10)

        asyncio.run(scenario())
    finally:
        handle.close()  # the other process's compile ends
    compiling.join(30)
    assert spawned == []  # both marked by the other: nothing compiled twice


def test_first_makes_every_family_wait_for_the_whole_compile(markers, monkeypatch):
    monkeypatch.setenv(precompile.ENV, "first")
    key = precompile.code_key("sm0", 0, 0)
    markers.mkdir(parents=True)
    (markers / f"lift_pot.{key}").touch()
    handle = _hold_machine_lock(markers)
    try:
        assert not precompile.family_ready("lift_pot", key, markers)
    finally:
        handle.close()
    assert precompile.family_ready("lift_pot", key, markers)
    monkeypatch.delenv(precompile.ENV)
    handle = _hold_machine_lock(markers)
    try:
        assert precompile.family_ready("lift_pot", key, markers)  # marked: ready at once
    finally:
        handle.close()


def test_a_sweep_starts_compiling_in_the_background_on_a_gpu(monkeypatch):
    """`runner.start_compiling` (the local sweep's and each Ray engine's start): Warp on a GPU
    starts compiling every family of the sweep at once and returns the handle (each chunk
    compiling its own family when it came took 372 s for 14 families on a fresh 4 x H100
    host); elsewhere nothing compiles and no family waits."""
    import asyncio
    from types import SimpleNamespace

    from vabench.sweep import runner

    started: list[tuple] = []
    monkeypatch.setattr(
        runner.Compiling, "start", classmethod(lambda cls, *a: started.append(a) or "handle")
    )
    engine = SimpleNamespace(image=SimpleNamespace(width=640, height=480))
    choices = SimpleNamespace(
        physics=SimpleNamespace(is_warp=True), renderer=SimpleNamespace(is_warp=True)
    )
    monkeypatch.setattr(runner, "warp_device", lambda: "cuda:0")
    assert asyncio.run(runner.start_compiling(engine, choices, ["b", "a", "b"])) == "handle"
    assert started == [(["a", "b"], 640, 480, "cuda:0", True, ())]
    started.clear()  # the sweep's critical path goes with them
    assert asyncio.run(runner.start_compiling(engine, choices, ["b", "a"], {"b"})) == "handle"
    assert started == [(["a", "b"], 640, 480, "cuda:0", True, {"b"})]
    monkeypatch.setattr(runner, "warp_device", lambda: "cpu")
    assert asyncio.run(runner.start_compiling(engine, choices, ["c"])) is None


def test_the_critical_path_compiles_first_and_the_others_behind():
    """The basket's chain bounds a fresh machine's suite (its child took 99 s of a 102 s compile
    on an H200, 2026-11-29): its child starts first, the others at a lower CPU priority;
    without a critical family (or with only critical ones) all alike."""
    plan = precompile.child_plan(
        ["lift_pot", "put_everything_in_basket", "place_shoe"], {"put_everything_in_basket"}
    )
    assert list(plan) == ["put_everything_in_basket", "lift_pot", "place_shoe"]
    assert plan["put_everything_in_basket"] == 0
    assert plan["lift_pot"] == plan["place_shoe"] == precompile.BEHIND_NICE
    alike = {"lift_pot": 0, "place_shoe": 0}
    assert precompile.child_plan(["lift_pot", "place_shoe"], {"put_everything_in_basket"}) == alike
    assert precompile.child_plan(["lift_pot", "place_shoe"], {"lift_pot", "place_shoe"}) == alike


def test_the_critical_familys_child_is_started_first_and_given_its_plan(markers, monkeypatch):
    started: list[tuple[str, int, int]] = []
    guard = threading.Lock()

    def child(task, size, device, threads, claims=None, stats=None, nice=0, ready=None):
        with guard:
            started.append((task, threads, nice))

    monkeypatch.setattr(precompile, "_child", child)
    families = ["lift_pot", "place_shoe", "put_everything_in_basket"]
    precompile.ensure_compiled(
        families, 64, 48, "cpu", images=False, processes=1, first={"put_everything_in_basket"}
    )
    # one core: children(3, 1) = 2 at a time, 2 threads each; the basket's in the first wave
    assert ("put_everything_in_basket", 2, 0) in started[:2]
    assert sorted(started) == sorted(
        [("put_everything_in_basket", 2, 0), ("lift_pot", 2, 5), ("place_shoe", 2, 5)]
    )


def test_a_child_behind_runs_at_the_lower_cpu_priority():
    """`--nice` is applied by the child itself, before its threads start (in a process of its
    own: a process cannot take its priority back)."""
    probe = (
        "import os\n"
        "from vabench.tuning import precompile, warp_ahead\n"
        "def family(*a, **k):\n"
        "    print('nice', os.nice(0))\n"
        "    return warp_ahead.Ahead(), {}\n"
        "precompile.compile_family = family\n"
        "precompile.main(['lift_pot', '--nice', '3'])\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert f"nice {os.nice(0) + 3}" in out.stdout


def test_a_child_marks_its_family_ready_once_its_modules_are_loaded_ahead(tmp_path, monkeypatch):
    """The marker comes before the expert's check (`compile_family`'s `loaded`), so that the
    family's episodes do not wait for it; not where a dry call failed (the expert's run then
    compiles what it missed) nor where nothing was loaded ahead."""
    from vabench.tasks import task_batch
    from vabench.tuning import warp_ahead

    class Checked(RuntimeError):
        pass

    def no_batch(*args, **kwargs):  # the expert's check: past the point that matters here
        raise Checked

    monkeypatch.setattr(task_batch, "TaskBatch", no_batch)
    cases = (
        (5, (), "2", True),
        (5, ("physics: x",), "2", False),
        (0, (), "2", False),  # e.g. a GPU Warp cannot use: nothing loaded
        (5, (), "1", False),  # one thread and no claims: nothing loaded ahead
    )
    for modules, failed, threads, marked in cases:
        monkeypatch.setattr(
            precompile,
            "load_ahead",
            lambda *a, m=modules, f=failed: warp_ahead.Ahead(modules=m, failed=f),
        )
        ready = tmp_path / f"lift_pot.{modules}.{len(failed)}.{threads}"
        with pytest.raises(Checked):
            precompile.main(["lift_pot", "--threads", threads, "--ready", str(ready)])
        assert ready.exists() == marked, (modules, failed, threads)


def test_a_family_whose_child_failed_after_marking_it_is_unmarked(markers, monkeypatch):
    """A child that wrote its marker (its modules loaded ahead) and then failed its expert's
    check leaves the family to the sweep's own compile, now and in the next sweep."""

    def child(task, size, device, threads, claims=None, stats=None, nice=0, ready=None):
        assert ready is not None and ready.parent == markers
        ready.touch()
        return "the expert's check failed"

    monkeypatch.setattr(precompile, "_child", child)
    assert precompile.ensure_compiled(["lift_pot"], 64, 48, "cpu", images=False) == ["lift_pot"]
    assert precompile.missing(["lift_pot"], precompile.code_key("sm0", 0, 0), markers) == [
        "lift_pot"
    ]
