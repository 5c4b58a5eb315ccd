"""The Warp backend on Warp's CPU device: batch independence, frozen idle slots, buffer overflow
as an infrastructure error, the settled-state cache, fidelity to C MuJoCo, and the message a
machine without a GPU (or without the packages) gets.

Warp's CPU device runs the very kernels the GPU runs (one CUDA graph per action there, plain
launches here), thread after thread, so what is tested here is the backend's logic and
numerics; speed and the GPU-only paths are measured by benchmarks/ on a GPU host
(docs/PERFORMANCE.md, "Simulator throughput"; docs/FIDELITY.md).
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("warp", reason="the Warp backend needs warp-lang (the [test] extra has it)")
pytest.importorskip("mujoco_warp", reason="the Warp backend needs mujoco-warp ([test] extra)")

from vabench.sim_mjx import backends
from vabench.sim_mjx.backends import BackendUnavailable
from vabench.sim_mjx.cpu import CpuBatch
from vabench.sim_mjx.interface import DIVERGED, STATE_FIELDS, BatchBase
from vabench.sim_mjx.reset_cache import SettledCache
from vabench.sim_mjx.warp import device
from vabench.sim_mjx.warp.batch import WarpBatch
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds
from vabench.tasks.task_batch import TaskBatch, run_experts

DOWN = {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 40}
RIGHT = {"action": "gripper.move_world", "axis": "x", "sign": "+", "distance_mm": 30}
TURN = {"action": "gripper.rotate_local", "axis": "rz", "sign": "+", "angle_deg": 20}
CLOSE = {"action": "gripper.close"}
FAR = {"action": "gripper.move_world", "axis": "y", "sign": "+", "distance_mm": 100}

# The finger centre after every action of an expert episode, Warp against C MuJoCo (the target
# of docs/FIDELITY.md). Both integrate the same model in float32 (Warp) and float64 (C) with
# different contact generation code; 2 mm is what a grasp or a placement can tolerate.
GC_TOLERANCE_M = 0.002


@pytest.fixture(scope="module")
def cube():
    task = get_task("grasp_single_cube")
    model = task.build_model()
    q0 = task.initial_qpos(model, task.sample(verified_seeds(task.name)[0]))
    return task, model, q0


def _reset(batch, q0, slots=None):
    slots = list(range(batch.n_slots)) if slots is None else slots
    batch.reset(slots, np.broadcast_to(q0, (len(slots), len(q0))), settle_steps=50)


def _states_equal(a: dict, b: dict) -> bool:
    return all(np.array_equal(a[f], b[f]) for f in STATE_FIELDS)


def test_slot_independent_of_batch_size_index_and_neighbours(cube):
    """The same slot, alone or third of three with busy neighbours, moves bit for bit alike."""
    _, model, q0 = cube
    alone = WarpBatch(model, 1, device="cpu")
    crowd = WarpBatch(model, 3, device="cpu")
    _reset(alone, q0)
    _reset(crowd, q0)
    for ours, theirs in ((DOWN, RIGHT), (TURN, CLOSE), (CLOSE, DOWN)):
        alone.step([ours])
        crowd.step([theirs, FAR, ours])
        assert _states_equal(alone.get_state([0]), crowd.get_state([2]))
    assert not np.array_equal(crowd.qpos()[0], crowd.qpos()[2])  # the neighbours did move


def test_idle_and_failed_slots_stay_frozen(cube):
    _, model, q0 = cube
    batch = WarpBatch(model, 3, device="cpu")
    _reset(batch, q0)
    idle = batch.get_state([1])
    far = {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 100}
    assert batch.step([DOWN, None, far])[2].executed  # 100 mm down: still above the table
    failing = batch.get_state([2])
    res = batch.step([DOWN, None, far])  # another 100 mm would put the fingers in the table
    assert res[1] is None and res[2] is not None and not res[2].planner_success
    assert res[0].executed and not res[2].executed
    assert _states_equal(idle, batch.get_state([1]))
    assert _states_equal(failing, batch.get_state([2]))


def test_contact_overflow_is_a_named_infrastructure_error(cube):
    """One contact per world cannot hold a cube resting on the table (4 corners): the acting
    slot's result says so and names the setting to raise; nothing passes silently."""
    _, model, q0 = cube
    batch = WarpBatch(model, 2, device="cpu", nconmax=1)
    _reset(batch, q0)
    assert batch.failures()[0] is not None and "nconmax" in batch.failures()[0]
    res = batch.step([DOWN, None])
    assert res[0].infrastructure_error is not None
    assert "overflow" in res[0].infrastructure_error and "nconmax" in res[0].infrastructure_error
    assert res[1] is None


def test_a_diverged_world_is_a_named_infrastructure_error(cube):
    """A world whose state is no longer finite (a divergence carries NaN on, as one episode's
    did on an H200, 2026-11-29) fails its action as the simulator's error; its neighbour does
    not."""
    _, model, q0 = cube
    batch = WarpBatch(model, 2, device="cpu")
    _reset(batch, q0)
    state = batch.get_state([0])
    state["qvel"][:] = np.nan
    batch.set_state([0], state, [0])
    res = batch.step([DOWN, DOWN])
    assert res[0] is not None and res[0].infrastructure_error == DIVERGED
    assert res[1] is not None and res[1].executed and res[1].infrastructure_error is None
    assert np.isfinite(batch.qpos()[1]).all()


def test_constraint_overflow_names_njmax(cube):
    _, model, q0 = cube
    batch = WarpBatch(model, 1, device="cpu", njmax=2)
    _reset(batch, q0)
    res = batch.step([DOWN])
    assert res[0].infrastructure_error is not None and "njmax" in res[0].infrastructure_error


def test_overflow_at_reset_is_reported_and_not_cached(cube, tmp_path):
    task, _, _ = cube
    cache = SettledCache(tmp_path)
    tb = TaskBatch(task, 1, backend="mjx", impl="warp", device="cpu", nconmax=1, cache=cache)
    report = tb.reset([0], [verified_seeds(task.name)[0]])[0]
    assert not report.ok and "nconmax" in (report.infrastructure_error or "")
    assert not list(tmp_path.rglob("*.npz"))


@pytest.mark.parametrize("backend", ["c", pytest.param("warp", marks=pytest.mark.slow)])
def test_cached_reset_equals_a_fresh_settle(cube, tmp_path, backend):
    """A reset served by the settled-state cache continues exactly as the settled one did."""
    task, _, _ = cube
    seed = verified_seeds(task.name)[1]
    kwargs = {"impl": "warp", "device": "cpu"} if backend == "warp" else {}
    runs = []
    for _ in range(2):  # the first settles and fills the cache, the second reads it (disk)
        tb = TaskBatch(
            task,
            1,
            backend="mjx" if backend == "warp" else "c",
            cache=SettledCache(tmp_path),
            **kwargs,
        )
        report = tb.reset([0], [seed])[0]
        tb.step([DOWN])
        runs.append((report, tb.batch.get_state([0])))
    (fresh, s1), (cached, s2) = runs
    assert not fresh.cached and cached.cached
    assert (fresh.finite, fresh.max_drift_deg) == (cached.finite, cached.max_drift_deg)
    assert _states_equal(s1, s2)


def test_proprio_equals_the_jax_proprio(cube):
    _, model, q0 = cube
    batch = WarpBatch(model, 2, device="cpu")
    _reset(batch, q0)
    batch.step([TURN, RIGHT])
    warp_p = batch.proprio()
    jax_p = BatchBase.proprio(batch)  # the shared JAX formula on the same qpos
    for field in ("gc", "ee", "rot", "quat", "rpy", "fingers"):
        np.testing.assert_allclose(getattr(warp_p, field), getattr(jax_p, field), atol=2e-5)


def test_world_rotation_turns_about_the_world_axis(cube):
    """A world rotation is encoded from the proprioception's orientation (Warp's, in float32)
    and turns a tilted gripper about the world axis as on C MuJoCo: R(z, t) R within 0.1 deg,
    GC held within 0.5 mm, C MuJoCo's orientation within 0.1 deg."""
    _, model, q0 = cube
    tilts = [{"action": "gripper.rotate_local", "axis": a, "sign": "+", "angle_deg": 20} for a in
             ("ry", "rx")]  # fmt: skip
    turn = {"action": "gripper.rotate_world", "axis": "z", "sign": "+", "angle_deg": 30}
    t = np.radians(30.0)
    rz = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    ends = []
    for batch in (WarpBatch(model, 1, device="cpu"), CpuBatch(model, 1)):
        _reset(batch, q0)
        for tilt in tilts:
            assert batch.step([tilt])[0].planner_success
        start = batch.proprio()
        res = batch.step([turn])[0]
        assert res.valid and res.planner_success and res.label == "rotate_world z+30deg"
        end = batch.proprio()
        r0, r1 = (np.asarray(p.rot[0, 0], float) for p in (start, end))
        assert _angle_deg(rz @ r0, r1) < 0.1
        assert _angle_deg(r0 @ rz, r1) > 5.0  # the same turn about the local z misses it
        assert np.linalg.norm(end.gc[0, 0] - start.gc[0, 0]) < 5e-4
        ends.append(r1)
    assert _angle_deg(*ends) < 0.1


def _angle_deg(r0, r1):
    """Angle of the relative rotation r0^T r1."""
    return np.degrees(np.arccos(np.clip((np.trace(r0.T @ r1) - 1.0) / 2.0, -1.0, 1.0)))


def test_every_device_operation_holds_the_device_lock(cube, monkeypatch):
    """Construction, actions, holds, host reads and contact flags all run holding the device's
    lock: on a GPU another thread's CUDA graph capture (global mode) turns any allocation or
    synchronous copy made beside it into an error (an H100 showed "illegal memory access" when
    an engine built two task batches while a third captured its graphs)."""
    import warp as wp

    _, model, q0 = cube
    lock = device.device_lock("cpu")
    seen: list[str] = []

    def checked(name, fn):
        def call(*args, **kwargs):
            seen.append(name)
            assert lock._is_owned(), f"{name} outside the device lock"  # type: ignore[attr-defined]
            return fn(*args, **kwargs)

        return call

    for name in ("launch", "zeros", "full", "ones", "empty", "copy"):  # wp.array(data) copies
        monkeypatch.setattr(wp, name, checked(f"wp.{name}", getattr(wp, name)))
    for name in ("numpy", "assign", "zero_", "fill_"):
        monkeypatch.setattr(wp.array, name, checked(f"array.{name}", getattr(wp.array, name)))
    batch = WarpBatch(model, 2, device="cpu")
    _reset(batch, q0)
    batch.step([DOWN, None])
    batch.hold(3, [1])
    batch.get_state([0, 1])
    batch.qpos()
    batch.proprio()
    side_a, side_b = np.zeros((2, model.ngeom), bool), np.zeros((2, model.ngeom), bool)
    side_a[:, 0], side_b[:, 1:] = True, True  # masks over the geoms: pair p joins a[p], b[p]
    batch.contact_flags(side_a, side_b)
    batch.close()
    assert {"wp.launch", "wp.copy", "wp.zeros", "array.numpy", "array.assign"} <= set(seen)


def test_waits_for_the_gpu_with_the_device_lock_released(cube, monkeypatch):
    """An action, a hold, a reset and the first watch of contact pairs queue their work under
    the device lock and wait for it without the lock (`streams.wait`): while one batch's GPU
    work runs, the threads of the other batches queue theirs. Holding the lock across the wait
    ran the GPU one batch at a time (a third busy on an H100)."""
    from vabench.sim_mjx.warp import streams

    _, model, q0 = cube
    batch = WarpBatch(model, 2, device="cpu")
    lock = device.device_lock("cpu")
    waits: list[bool] = []
    real = streams.wait

    def wait(event):
        waits.append(lock._is_owned())  # type: ignore[attr-defined]
        real(event)

    monkeypatch.setattr(streams, "wait", wait)
    _reset(batch, q0)
    batch.step([DOWN, None])
    batch.hold(3, [1])
    side_a, side_b = np.zeros((1, model.ngeom), bool), np.zeros((1, model.ngeom), bool)
    side_a[0, 0], side_b[0, 1:] = True, True
    first = batch.contact_flags(side_a, side_b)
    batch.step([None, DOWN])
    assert len(waits) >= 4 and not any(waits), waits
    n = len(waits)
    again = batch.contact_flags(side_a, side_b)  # watched: read with the step's results
    assert len(waits) == n and again.shape == first.shape
    batch.close()


def test_device_uploads_outlive_the_wait_for_the_work_that_reads_them(cube, monkeypatch):
    """Warp frees pool memory on CUDA's legacy stream, which waits for no non-blocking stream
    (each batch's): an upload dropped before its batch's work has run goes back to the pool
    while a queued kernel still reads it, and another stream's allocation may take it (the
    likely illegal address of the H100 runs, 2026-11-27). So every device array the batch
    makes for a call is still alive when the call waits for its work (`streams.wait`). Warp's
    CPU device stands in: the arrays' lifetimes are the same Python objects'. (MuJoCo Warp's
    own scratch arrays are allocated inside captured graphs on a GPU, owned by the graph.)"""
    import weakref

    import warp as wp

    from vabench.sim_mjx.warp import batch as batch_module
    from vabench.sim_mjx.warp import streams

    _, model, q0 = cube
    batch = WarpBatch(model, 2, device="cpu")
    _reset(batch, q0)
    made: list[weakref.ref] = []
    real_array = wp.array

    class Tracked(real_array):  # type: ignore[misc, valid-type]
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(weakref.ref(self))

    dropped: list[int] = []
    real_wait = streams.wait

    def wait(event):
        dropped.append(sum(r() is None for r in made))
        made.clear()
        real_wait(event)

    class Warp:  # the batch module's `wp`, making its own arrays Tracked
        array = Tracked

        def __getattr__(self, name):
            return getattr(wp, name)

    monkeypatch.setattr(batch_module, "wp", Warp())
    monkeypatch.setattr(streams, "wait", wait)
    state = batch.get_state([0, 1])
    # a cached reset: the slots' indices and state rows uploaded
    batch.set_state([0, 1], state, np.zeros(2, np.int32))
    side_a, side_b = np.zeros((1, model.ngeom), bool), np.zeros((1, model.ngeom), bool)
    side_a[0, 0], side_b[0, 1:] = True, True
    batch.contact_flags(side_a, side_b)
    batch.step([DOWN, None])
    assert dropped and not any(dropped), dropped
    batch.close()


def _expert_replay_gc_deviation(task_name: str, n_seeds: int) -> float:
    """Run the expert on C, replay its actions on Warp (CPU) in lockstep; the largest finger
    centre distance between the two after any action."""
    task = get_task(task_name)
    seeds = verified_seeds(task_name)[:n_seeds]
    c = TaskBatch(task, len(seeds), backend="c")
    episodes = run_experts(c, seeds)
    assert all(ep.success for ep in episodes)
    scripts = [[a["action"] for a in ep.actions] for ep in episodes]
    w = TaskBatch(task, len(seeds), backend="mjx", impl="warp", device="cpu")
    c.reset(range(len(seeds)), seeds)
    w.reset(range(len(seeds)), seeds)
    worst = 0.0
    outcomes = []
    for step in range(max(map(len, scripts))):
        actions = [s[step] if step < len(s) else None for s in scripts]
        c.step(actions)
        outcomes = w.step(actions)
        gc_c, gc_w = c.batch.proprio().gc, w.batch.proprio().gc
        for i, a in enumerate(actions):
            if a is not None:
                worst = max(worst, float(np.max(np.linalg.norm(gc_c[i] - gc_w[i], axis=-1))))
    assert all(o is None or o.result.infrastructure_error is None for o in outcomes)
    assert all(w.success)  # C's expert actions solve the seeds on Warp too
    return worst


def test_expert_finger_centre_follows_c_mujoco():
    assert _expert_replay_gc_deviation("grasp_single_cube", 1) <= GC_TOLERANCE_M


@pytest.mark.slow
@pytest.mark.parametrize("task_name", ["grasp_single_cube", "place_single_cube"])
def test_expert_finger_centre_follows_c_mujoco_more_seeds(task_name):
    assert _expert_replay_gc_deviation(task_name, 3) <= GC_TOLERANCE_M


def test_no_gpu_gets_one_clear_message(cube, monkeypatch):
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("this machine has a CUDA GPU")
    monkeypatch.delenv("VABENCH_WARP_DEVICE", raising=False)
    task, _, _ = cube
    with pytest.raises(BackendUnavailable, match=r"needs an NVIDIA GPU.*VABENCH_WARP_DEVICE=cpu"):
        TaskBatch(task, 1, backend="mjx", impl="warp")
    proc = subprocess.run(
        [sys.executable, "-m", "vabench.replay", "--task", task.name, "--seed", "1000"]
        + ["--expert", "--backend", "mjx", "--impl", "warp"],
        capture_output=True,
        text=True,
        env={k: v for k, v in __import__("os").environ.items() if k != "VABENCH_WARP_DEVICE"},
    )
    assert proc.returncode == 2, proc.stderr
    assert "--impl warp: the Warp backend needs an NVIDIA GPU" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_missing_package_is_named(monkeypatch):
    real = importlib.util.find_spec

    def find_spec(name, *args, **kwargs):
        return None if name == "mujoco_warp" else real(name, *args, **kwargs)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    monkeypatch.setattr(device, "nvidia_driver_present", lambda: True)
    problem = device.warp_problem("cuda:0")
    assert problem is not None
    assert "mujoco-warp" in problem and "pip install 'vabench[gpu]'" in problem
    with pytest.raises(BackendUnavailable, match="mujoco-warp"):
        backends.resolve("mjx", "warp")
    auto = backends.resolve("auto")
    assert auto.kind is backends.Physics.C and "mujoco-warp" in auto.reason


def test_no_gpu_is_the_reason_without_a_driver(monkeypatch):
    """Without an NVIDIA driver the reason is the missing GPU, not a package: installing
    warp-lang would not help."""
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a, **k: None if name == "warp" else real(name, *a, **k),
    )
    monkeypatch.setattr(device, "nvidia_driver_present", lambda: False)
    problem = device.warp_problem("cuda:0")
    assert problem is not None and "needs an NVIDIA GPU" in problem
    assert "warp-lang" not in problem
    auto = backends.resolve("auto")
    assert auto.kind is backends.Physics.C and "needs an NVIDIA GPU" in auto.reason
    assert "Use backend c" not in auto.reason  # auto already fell back to it


def _cuda() -> bool:
    import warp as wp

    return wp.is_cuda_available()


@pytest.mark.skipif(not _cuda(), reason="device loops are CUDA graphs (run on the GPU host)")
def test_a_device_loop_steps_like_a_graph_per_substep(cube):
    """`loop: device` (one graph per action, its substeps in a CUDA while node, MuJoCo Warp's
    scratch arrays from an arena) moves the slots as a graph per substep does, and does not
    fall back. Deterministic orderings; not bit for bit on a GPU, hence the tolerance (a lost or
    extra substep moves the arm by centimetres)."""
    _, model, q0 = cube
    loops = {
        loop: WarpBatch(model, 4, device="cuda:0", deterministic=True, loop=loop)
        for loop in ("device", "per_step")
    }
    for batch in loops.values():
        _reset(batch, q0)
    start = loops["device"].qpos()
    for commands in ([DOWN] * 4, [TURN, CLOSE, RIGHT, DOWN], [CLOSE, FAR, DOWN, TURN]):
        for batch in loops.values():
            batch.step(commands)
    assert loops["device"]._graphs.loop == "device"  # captured, not fallen back to per_step
    moved = loops["device"].qpos()
    assert np.abs(moved - start).max() > 0.01
    np.testing.assert_allclose(moved, loops["per_step"].qpos(), atol=1e-3)


@pytest.mark.skipif(not _cuda(), reason="stream priorities are CUDA's (run on the GPU host)")
def test_the_critical_path_batch_streams_at_the_highest_priority(cube):
    import ctypes

    from vabench.sim_mjx.warp import streams

    _, model, _ = cube
    cuda = ctypes.CDLL("libcuda.so.1")

    def priority(batch: WarpBatch) -> int:
        value = ctypes.c_int()
        assert (
            cuda.cuStreamGetPriority(ctypes.c_void_p(batch.stream.cuda_stream), ctypes.byref(value))
            == 0
        )
        return value.value

    urgent = WarpBatch(model, 2, device="cuda:0", critical_path=True)
    usual = WarpBatch(model, 2, device="cuda:0")
    least, greatest = ctypes.c_int(), ctypes.c_int()  # Warp's context is current by now
    assert cuda.cuCtxGetStreamPriorityRange(ctypes.byref(least), ctypes.byref(greatest)) == 0
    assert greatest.value < least.value  # the GPU has priorities to give
    assert priority(urgent) == greatest.value
    # ahead of the render passes' ray tracing (least), behind the critical path
    assert priority(usual) == streams.priority_value("middle", least.value, greatest.value)
    assert greatest.value <= priority(usual) < least.value
