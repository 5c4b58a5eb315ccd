"""An action that ends at rest (`action_end: at_rest`, `paced`): the rule on C MuJoCo and Warp.

A slot's action ends at the first substep, once its references are final, where every dof is slower
than its rest speed (scene.rest_speeds), ACTION_SECONDS at the latest; its state is that substep's,
whatever the other slots do and however long the batch's loop ran for them. Paced, a move's time
follows its length: a short move ends sooner, at the same place.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from vabench.config.schema import SimulatorOptions
from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.backends import Physics
from vabench.sim_mjx.cpu import CpuBatch
from vabench.sim_mjx.interface import STATE_FIELDS
from vabench.sim_mjx.scene import free_objects, rest_speeds
from vabench.tasks import get_task
from vabench.tasks.manifests import verified_seeds

DOWN = {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 40}
RIGHT = {"action": "gripper.move_world", "axis": "x", "sign": "+", "distance_mm": 30}
CLOSE = {"action": "gripper.close"}
FAR = {"action": "gripper.move_world", "axis": "y", "sign": "+", "distance_mm": 100}
NUDGE = {"action": "gripper.move_world", "axis": "x", "sign": "-", "distance_mm": 8}
TURN = {"action": "gripper.rotate_local", "axis": "rz", "sign": "+", "angle_deg": 15}


@pytest.fixture(scope="module")
def cube():
    task = get_task("grasp_single_cube")
    model = task.build_model()
    q0 = task.initial_qpos(model, task.sample(verified_seeds(task.name)[0]))
    return model, q0


def _reset(batch, q0):
    n = batch.n_slots
    batch.reset(range(n), np.broadcast_to(q0, (n, len(q0))), settle_steps=50)


def test_c_ends_each_action_at_the_substep_it_comes_to_rest(cube):
    """The state after an action ending at rest is the fixed action's state at that substep."""
    model, q0 = cube
    rest, fixed = CpuBatch(model, 1, action_end="at_rest"), CpuBatch(model, 1)
    fixed.capture_every = 1
    for b in (rest, fixed):
        _reset(b, q0)
    ran = []
    for action in (DOWN, CLOSE, RIGHT):
        fixed.captured.clear()
        fixed.set_state([0], rest.get_state([0]), rest.variant()[[0]])
        rest.step([action])
        fixed.step([action])
        k = int(rest.last_substeps[0])
        assert ctl.rest_from(rest.n_substeps) <= k <= rest.n_substeps
        assert fixed.last_substeps[0] == fixed.n_substeps
        np.testing.assert_array_equal(rest.qpos()[0], fixed.captured[0][k - 1])
        ran.append(k)
    assert min(ran) < rest.n_substeps  # some action did end early


def test_c_threads_take_the_same_rule(cube):
    """The rollout threads' path (cold warm start) picks its rest substep by the same rule."""
    model, q0 = cube
    batch = CpuBatch(model, 2, threads=2, action_end="at_rest")
    _reset(batch, q0)
    batch.step([DOWN, FAR])
    k = batch.last_substeps
    assert np.all((k >= ctl.rest_from(batch.n_substeps)) & (k <= batch.n_substeps))


def test_c_paced_short_moves_end_sooner_at_the_same_place(cube):
    """Paced, a short move or turn ends well before the fixed timing's rest substep, the
    gripper within a millimetre of where the at_rest action leaves it; a long move and a grip
    keep their time."""
    model, q0 = cube
    paced, rest = CpuBatch(model, 1, action_end="paced"), CpuBatch(model, 1, action_end="at_rest")
    for b in (paced, rest):
        _reset(b, q0)
    for action, short in ((NUDGE, True), (TURN, True), (DOWN, True), (CLOSE, False)):
        rest.set_state([0], paced.get_state([0]), paced.variant()[[0]])
        paced.step([action])
        rest.step([action])
        k, k_rest = int(paced.last_substeps[0]), int(rest.last_substeps[0])
        if short:
            assert k < ctl.rest_from(paced.n_substeps) <= k_rest, (action, k, k_rest)
        else:
            assert k >= ctl.rest_from(paced.n_substeps) * rc.GRIP_FRACTION / max(
                rc.MOVE_FRACTION, rc.GRIP_FRACTION
            ), (action, k)
        gc_paced, gc_rest = paced.proprio().gc[0], rest.proprio().gc[0]
        assert np.linalg.norm(gc_paced - gc_rest) < 1e-3, (action, gc_paced, gc_rest)


def test_the_setting_reaches_c_and_warp_only():
    for end in ("at_rest", "paced"):
        opts = SimulatorOptions(action_end=end)
        assert opts.batch_kwargs(Physics.C)["action_end"] == end
        assert opts.batch_kwargs(Physics.WARP)["action_end"] == end
    opts = SimulatorOptions(action_end="at_rest")
    assert "action_end" not in opts.batch_kwargs(Physics.MJX_JAX)
    assert "action_end" not in SimulatorOptions().batch_kwargs(Physics.WARP)
    with pytest.raises(ValueError, match="action_end must be one of"):
        CpuBatch(get_task("grasp_single_cube").build_model(), 1, action_end="soon")


@pytest.mark.parametrize("end", ["at_rest", "paced"])
def test_warp_slot_ends_at_its_own_rest_whatever_its_neighbours(cube, end):
    """On Warp (its CPU device) a slot's action ends at its own rest substep: alone, or beside
    neighbours whose moves keep the batch's loop running longer, it moves bit for bit alike."""
    pytest.importorskip("mujoco_warp", reason="the Warp backend needs mujoco-warp")
    from vabench.sim_mjx.warp.batch import WarpBatch

    model, q0 = cube
    alone = WarpBatch(model, 1, device="cpu", action_end=end)
    crowd = WarpBatch(model, 3, device="cpu", action_end=end)
    for b in (alone, crowd):
        _reset(b, q0)
    for ours, theirs in ((DOWN, FAR), (CLOSE, RIGHT)):
        alone.step([ours])
        crowd.step([theirs, FAR, ours])
        a, c = alone.get_state([0]), crowd.get_state([2])
        assert all(np.array_equal(a[f], c[f]) for f in STATE_FIELDS)
        assert alone.last_substeps[0] == crowd.last_substeps[2]
        assert alone.last_substeps[0] <= alone.n_substeps
        if end == "at_rest":
            assert ctl.rest_from(alone.n_substeps) <= alone.last_substeps[0]


def test_rest_speeds_hold_free_turns_at_the_rest_radius(cube):
    """A free body's three turning dofs rest below REST_SPIN (REST_SPEED at REST_RADIUS), every
    other dof below REST_SPEED."""
    model, _ = cube
    speeds = rest_speeds(model)
    spin = np.zeros(model.nv, bool)
    for jid in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
        spin[model.jnt_dofadr[jid] + 3 : model.jnt_dofadr[jid] + 6] = True
    assert spin.sum() == 3 * len(free_objects(model)) > 0
    assert np.all(speeds[spin] == pytest.approx(rc.REST_SPEED / rc.REST_RADIUS))
    assert np.all(speeds[~spin] == rc.REST_SPEED)
    assert rc.REST_SPIN > 0.019  # above a standing object's float32 jitter on Warp


def test_warp_rest_rule_is_the_c_rule(cube):
    """Warp's mark_rest ends exactly the slots whose every dof is below its rest speed (the C
    path's rule), once their references are final."""
    wp = pytest.importorskip("warp", reason="the Warp backend needs warp")
    from vabench.sim_mjx.warp import rows as wr

    model, _ = cube
    speeds = rest_speeds(model)
    rng = np.random.default_rng(0)
    n = 64
    qvel = speeds * rng.uniform(-0.99, 0.99, (n, model.nv))
    moving = rng.random(n) < 0.5  # one dof of these rows just above its rest speed
    hot = rng.integers(0, model.nv, n)[moving]
    qvel[moving, hot] = (
        speeds[hot] * rng.choice([-1.0, 1.0], hot.size) * rng.uniform(1.01, 2, hot.size)
    )
    rest_from = rng.integers(0, 3, n)
    k = 1
    go = np.ones(n, int)
    go[::7] = 0

    def arr(x, dtype=int):
        return wp.array(np.asarray(x), dtype=dtype, device="cpu")

    done, newly, steps = arr(np.zeros(n)), arr(np.zeros(n)), arr(np.zeros(n))
    wp.launch(
        wr.mark_rest,
        dim=n,
        inputs=[arr([k]), arr(rest_from), arr(speeds, float), arr(go), arr(qvel, float)],
        outputs=[done, newly, steps],
        device="cpu",
    )
    expect = (go != 0) & (k >= rest_from) & np.all(np.abs(qvel) < speeds, axis=1)
    np.testing.assert_array_equal(done.numpy() != 0, expect)
    assert 0 < expect.sum() < n
