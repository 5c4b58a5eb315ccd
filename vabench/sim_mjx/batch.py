"""A batch of N episodes ("slots") of one MJX model, stepped one agent action at a time.

Inside: pure jitted functions over the batch state (`SimState`). At the edge: `SimBatch`, which
owns the device buffers, validates and encodes actions, and formats results.

One call of `SimBatch.step` executes one action per slot, each slot with its own kind, in a
single jitted call: plan (closed-form IK over the waypoints) -> ACTION_SECONDS of physics
substeps tracking the joint reference -> merge. Slots without an action, with an invalid action
or with a failed plan keep their previous state bit for bit: their physics does not advance.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from pydantic import BaseModel

from vabench import protocol as P
from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.actions import CommandRows, encode
from vabench.sim_mjx.pytree import pytree_dataclass
from vabench.sim_mjx.scene import free_objects, home_qpos
from vabench.sim_mjx.variants import ModelVariants


@dataclass(frozen=True)
class ArmLayout:
    """Where each present arm lives in qpos and ctrl; resolved once from names."""

    arms: tuple[str, ...]
    qpos: np.ndarray  # (A, 6) arm joint qpos addresses
    fingers: np.ndarray  # (A, 2) finger joint qpos addresses
    arm_act: np.ndarray  # (A, 6) actuator ids
    finger_act: np.ndarray  # (A, 2)

    @staticmethod
    def from_model(m: mujoco.MjModel) -> ArmLayout:
        def jadr(name: str) -> int:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            return int(m.jnt_qposadr[jid]) if jid >= 0 else -1

        def aid(name: str) -> int:
            return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, name)

        arms = tuple(a for a in rc.ARMS if jadr(f"{a}_waist") >= 0)
        if not arms:
            raise ValueError("the model has no vabench arm (joints named '<arm>_waist')")
        return ArmLayout(
            arms=arms,
            qpos=np.array([[jadr(f"{a}_{j}") for j in rc.ARM_JOINTS] for a in arms]),
            fingers=np.array([[jadr(f"{a}_{j}") for j in rc.FINGER_JOINTS] for a in arms]),
            arm_act=np.array([[aid(f"{a}_{j}") for j in rc.ARM_JOINTS] for a in arms]),
            finger_act=np.array([[aid(f"{a}_{j}") for j in rc.FINGER_JOINTS] for a in arms]),
        )

    def geometry(self, m: mujoco.MjModel) -> kin.ArmGeometry:
        per_arm = [kin.ArmGeometry.from_model(m, f"{a}_") for a in self.arms]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *per_arm)


@pytree_dataclass
class SimState:
    data: mjx.Data  # batched over slots
    grip_open: jax.Array  # (N, A) bool: last aperture command (True = open)
    init_qpos: jax.Array  # (N, nq) qpos at the slot's last reset, for task predicates
    actions: jax.Array  # (N,) int32 actions executed since the reset
    variant: jax.Array  # (N,) int32 model variant (object model id) of the slot


@pytree_dataclass
class StepInfo:
    executed: jax.Array  # (N,) bool: the slot's physics advanced
    planner_success: jax.Array  # (N,) bool
    clipped: jax.Array  # (N, A) bool
    executed_m: jax.Array  # (N, A) planned GC displacement after clipping


@pytree_dataclass
class Proprio:
    gc: jax.Array  # (..., A, 3) finger midpoint
    ee: jax.Array  # (..., A, 3) control end effector
    rot: jax.Array  # (..., A, 3, 3) columns: rx, ry, rz in the world frame
    quat: jax.Array  # (..., A, 4) wxyz
    rpy: jax.Array  # (..., A, 3) rad
    fingers: jax.Array  # (..., A, 2) finger openings
    is_open: jax.Array  # (..., A) bool


def _where(mask: jax.Array, new: Any, old: Any) -> Any:
    return jax.tree.map(lambda a, b: jnp.where(mask, a, b), new, old)


def proprio_slot(
    layout: ArmLayout, geoms: kin.ArmGeometry, qpos: jax.Array, grip_open: jax.Array
) -> Proprio:
    q = qpos[layout.qpos]
    fingers = qpos[layout.fingers]
    ee, rot, gc = jax.vmap(kin.gripper_points)(geoms, q, fingers)
    return Proprio(
        gc=gc,
        ee=ee,
        rot=rot,
        quat=jax.vmap(kin.mat_to_quat)(rot),
        rpy=jax.vmap(kin.mat_to_rpy)(rot),
        fingers=fingers,
        is_open=grip_open,
    )


def plan_for(
    layout: ArmLayout, geoms: kin.ArmGeometry, d: mjx.Data, cmd: ctl.ArmCommand
) -> ctl.Plan:
    """The plan of one slot from its current data."""
    return ctl.plan_slot(
        geoms,
        d.qpos[layout.qpos],
        d.qpos[layout.fingers],
        d.ctrl[layout.arm_act],
        d.ctrl[layout.finger_act],
        cmd,
    )


def _with_refs(layout: ArmLayout, ctrl: jax.Array, arm: jax.Array, fingers: jax.Array) -> jax.Array:
    return ctrl.at[layout.arm_act].set(arm).at[layout.finger_act].set(fingers)


def ctrl_sequence_slot(
    layout: ArmLayout,
    n_substeps: int,
    geoms: kin.ArmGeometry,
    qpos: jax.Array,
    ctrl: jax.Array,
    cmd: ctl.ArmCommand,
) -> tuple[jax.Array, ctl.Plan]:
    """The whole control sequence (n_substeps, nu) of one slot's action, for simulators that
    take open-loop controls (C MuJoCo, mujoco.rollout). Same plan and references as step_slot."""
    plan = ctl.plan_slot(
        geoms,
        qpos[layout.qpos],
        qpos[layout.fingers],
        ctrl[layout.arm_act],
        ctrl[layout.finger_act],
        cmd,
    )

    def at(k: jax.Array) -> jax.Array:
        arm, fingers = ctl.ctrl_at(plan, k, n_substeps)
        return _with_refs(layout, ctrl, arm, fingers)

    return jax.vmap(at)(jnp.arange(n_substeps)), plan


def step_slot(
    layout: ArmLayout,
    n_substeps: int,
    variants: ModelVariants,
    mx: mjx.Model,
    stacked: tuple[jax.Array, ...],
    geoms: kin.ArmGeometry,
    state: SimState,
    cmd: ctl.ArmCommand,
) -> tuple[SimState, StepInfo]:
    """One action for one slot (the batch vmaps this)."""
    mx = variants.select(mx, stacked, state.variant)
    d0 = state.data
    plan = plan_for(layout, geoms, d0, cmd)

    def substep(d: mjx.Data, k: jax.Array) -> tuple[mjx.Data, None]:
        arm, fingers = ctl.ctrl_at(plan, k, n_substeps)
        return mjx.step(mx, d.replace(ctrl=_with_refs(layout, d.ctrl, arm, fingers))), None

    d1, _ = jax.lax.scan(substep, d0, jnp.arange(n_substeps))
    go = cmd.active & plan.ok
    grip_open = jnp.where(cmd.grip >= 0, cmd.grip == ctl.GRIP_OPEN, state.grip_open)
    new = state.replace(data=d1, grip_open=grip_open, actions=state.actions + 1)
    info = StepInfo(
        executed=go,
        planner_success=plan.ok,
        clipped=plan.clipped,
        executed_m=plan.executed_m,
    )
    return _where(go, new, state), info


def settle_slot(
    variants: ModelVariants,
    mx: mjx.Model,
    stacked: tuple[jax.Array, ...],
    n_steps: int,
    state: SimState,
    mask: jax.Array,
) -> SimState:
    """Advance physics n_steps holding the current references (masked slots only)."""
    mx = variants.select(mx, stacked, state.variant)

    def substep(d: mjx.Data, _: Any) -> tuple[mjx.Data, None]:
        return mjx.step(mx, d), None

    d1, _ = jax.lax.scan(substep, state.data, None, length=n_steps)
    return _where(mask, state.replace(data=d1), state)


def reset_slot(
    layout: ArmLayout,
    variants: ModelVariants,
    mx: mjx.Model,
    stacked: tuple[jax.Array, ...],
    state: SimState,
    mask: jax.Array,
    qpos: jax.Array,
    variant: jax.Array,
) -> SimState:
    """Fresh data at qpos (zero velocity, references at the arm's joints, fingers open)."""
    mx = variants.select(mx, stacked, variant)
    d = mjx.make_data(mx)
    ctrl = _with_refs(
        layout,
        d.ctrl,
        qpos[layout.qpos],
        jnp.full(layout.fingers.shape, rc.FINGER_OPEN, qpos.dtype),
    )
    d = mjx.forward(mx, d.replace(qpos=qpos, ctrl=ctrl))
    fresh = SimState(
        data=d,
        grip_open=jnp.ones(len(layout.arms), bool),
        init_qpos=qpos,
        actions=jnp.zeros((), jnp.int32),
        variant=variant,
    )
    return _where(mask, fresh, state)


def pair_contacts(
    geom: jax.Array, dist: jax.Array, side_a: jax.Array, side_b: jax.Array
) -> jax.Array:
    """(P,) bool: for each watched pair p, some contact touches (dist <= 0) a geom of side_a[p]
    and a geom of side_b[p]. geom (C, 2) and dist (C,) are one slot's contacts; side_a and
    side_b are (P, ngeom) bool masks."""
    touching = dist <= 0.0
    g1, g2 = geom[:, 0], geom[:, 1]
    hit = (side_a[:, g1] & side_b[:, g2]) | (side_a[:, g2] & side_b[:, g1])  # (P, C)
    return jnp.any(hit & touching[None, :], axis=1)


@dataclass
class ActionResult:
    """What one slot's action did (host side)."""

    valid: bool
    error: str | None = None
    planner_success: bool = False
    executed: bool = False
    clipped: dict[str, bool] | None = None
    executed_mm: dict[str, float] | None = None
    label: str | None = None


class BatchBase:
    """Host-side logic shared by the MJX batch and the C MuJoCo baseline: validation, encoding,
    results and observations. Subclasses own the state and implement `_execute`."""

    model: mujoco.MjModel
    n_slots: int
    layout: ArmLayout
    arms: tuple[str, ...]
    geoms: kin.ArmGeometry
    n_substeps: int
    objects: list[tuple[str, int]]

    def _setup(
        self, models: mujoco.MjModel | Sequence[mujoco.MjModel], n_slots: int, lanes: int
    ) -> None:
        """`lanes`: see `in_lanes`; every per-slot computation of the batch uses it, so a slot's
        results never depend on the batch size (n_slots must be a multiple of lanes)."""
        if n_slots < 1:
            raise ValueError(f"n_slots must be >= 1, got {n_slots}")
        self.models = [models] if isinstance(models, mujoco.MjModel) else list(models)
        model = self.models[0]
        self.model = model
        self.n_slots = n_slots
        self.layout = ArmLayout.from_model(model)
        self.arms = self.layout.arms
        self.geoms = self.layout.geometry(model)
        self.n_substeps = ctl.substeps(model.opt.timestep)
        self.objects = free_objects(model)
        self._dtype = np.dtype(jnp.zeros(()).dtype)
        self.lanes = lanes
        self._proprio = jax.jit(in_lanes(functools.partial(proprio_slot, self.layout), 2, lanes))

    # -- to implement -----------------------------------------------------------------------
    def _execute(self, rows: CommandRows) -> StepInfo:
        """Run the encoded commands; return host-side StepInfo."""
        raise NotImplementedError

    def qpos(self) -> np.ndarray:
        raise NotImplementedError

    def grip_open(self) -> np.ndarray:
        raise NotImplementedError

    def init_qpos(self) -> np.ndarray:
        """qpos of every slot at its last reset (evaluator-only, for predicates)."""
        raise NotImplementedError

    def variant(self) -> np.ndarray:
        """(N,) model variant of every slot."""
        raise NotImplementedError

    def contact_flags(
        self, side_a: np.ndarray, side_b: np.ndarray, slots: np.ndarray | None = None
    ) -> np.ndarray:
        """(N, P) bool: whether watched pair p touches in each slot (see `pair_contacts`).
        `slots` (bool mask) lets a backend skip slots whose rows the caller ignores."""
        raise NotImplementedError

    def _check_variants(self, slots: Sequence[int], variants: Sequence[int] | None) -> np.ndarray:
        if variants is None:
            return np.zeros(len(slots), np.int32)
        v = np.asarray(variants, np.int32)
        if v.shape != (len(slots),) or (v < 0).any() or (v >= len(self.models)).any():
            raise ValueError(
                f"variants must be {len(slots)} ints in [0, {len(self.models)}), got {variants}"
            )
        return v

    # -- shared -----------------------------------------------------------------------------
    def step(self, actions: Sequence[Any]) -> list[ActionResult | None]:
        """Execute one action per slot: None (idle), a validated action, or a raw dict.

        Invalid actions are rejected with a message naming the field and leave the slot as it
        was; so do actions whose plan fails (planner_success false).
        """
        if len(actions) < self.n_slots and len(actions) == getattr(self, "n_requested", -1):
            actions = [*actions, *([None] * (self.n_slots - len(actions)))]  # lane padding
        if len(actions) != self.n_slots:
            raise ValueError(
                f"expected {self.n_slots} actions (None for idle slots), got {len(actions)}"
            )
        rows = CommandRows.idle(self.n_slots, len(self.arms))
        results: list[ActionResult | None] = [None] * self.n_slots
        for slot, raw in enumerate(actions):
            if raw is None:
                continue
            obj = raw.model_dump(exclude_none=True) if isinstance(raw, BaseModel) else raw
            try:
                action = P.parse_robot_action(obj, self.arms)
            except P.ActionError as err:
                results[slot] = ActionResult(valid=False, error=str(err))
                continue
            encode(action, self.arms, rows, slot)
            results[slot] = ActionResult(valid=True, label=action.label())
        if not rows.active.any():
            return results
        info = self._execute(rows)
        for slot, res in enumerate(results):
            if res is None or not res.valid:
                continue
            res.planner_success = bool(info.planner_success[slot])
            res.executed = bool(info.executed[slot])
            res.clipped = {a: bool(info.clipped[slot, i]) for i, a in enumerate(self.arms)}
            res.executed_mm = {
                a: round(float(info.executed_m[slot, i]) * 1000.0, 3)
                for i, a in enumerate(self.arms)
            }
        return results

    def proprio(self) -> Proprio:
        """Proprioception of every slot, as host arrays."""
        qpos = jnp.asarray(self.qpos(), self._dtype)
        return jax.device_get(self._proprio(self.geoms, qpos, jnp.asarray(self.grip_open())))

    def object_poses(self, slot: int) -> dict[str, dict[str, list[float]]]:
        """Evaluator-only object poses of one slot: {name: {pos, quat (wxyz)}}."""
        self._check_slot(slot)
        qpos = self.qpos()[slot]
        return {
            name: {"pos": qpos[a : a + 3].tolist(), "quat": qpos[a + 3 : a + 7].tolist()}
            for name, a in self.objects
        }

    def _check_slot(self, slot: int) -> None:
        if not 0 <= slot < self.n_slots:
            raise IndexError(f"slot {slot} out of range [0, {self.n_slots})")

    def _check_reset(self, slots: Sequence[int], qpos: np.ndarray) -> np.ndarray:
        qpos = np.asarray(qpos, float)
        if qpos.shape != (len(slots), self.model.nq):
            raise ValueError(
                f"qpos must have shape ({len(slots)}, {self.model.nq}), got {qpos.shape}"
            )
        for slot in slots:
            self._check_slot(slot)
        return qpos


def in_lanes(fn: Any, n_batched: int, lanes: int) -> Any:
    """vmap `fn` over `lanes` slots at a time and loop (lax.map) over groups of lanes.

    XLA may sum in a different order when the batch dimension changes size, so a plain vmap over
    N slots is not bit-reproducible across N. Here every slot is computed by the same compiled
    lanes-wide body whatever N is, which makes a slot's result independent of the batch size, of
    its index and of the other slots. The last `n_batched` arguments carry the slot axis.
    """

    def run(*args: Any) -> Any:
        shared, batched = args[: len(args) - n_batched], args[len(args) - n_batched :]
        grouped = jax.tree.map(
            lambda x: x.reshape(x.shape[0] // lanes, lanes, *x.shape[1:]), batched
        )
        out = jax.lax.map(lambda xs: jax.vmap(lambda *b: fn(*shared, *b))(*xs), grouped)
        return jax.tree.map(lambda x: x.reshape(x.shape[0] * lanes, *x.shape[2:]), out)

    return run


DEFAULT_LANES = {"cpu": 1, "gpu": 256, "cuda": 256, "tpu": 256}
HOLD_CHUNK = 100  # physics steps per compiled settle call


class SimBatch(BatchBase):
    """N slots of one scene in one MJX batch; one agent action per slot per `step` call.

    `lanes` is the width of the vectorised physics (see `in_lanes`): results are bit-identical
    for any batch size, slot and neighbours at a given lanes value. The batch holds n_slots
    rounded up to a multiple of lanes; the extra slots stay idle. Default: 1 on CPU (XLA gains
    little from vectorising tiny matrices there), 256 on accelerators.
    """

    def __init__(
        self,
        model: mujoco.MjModel | Sequence[mujoco.MjModel],
        n_slots: int,
        impl: str = "jax",
        device: jax.Device | None = None,
        lanes: int | None = None,
    ):
        platform = (device or jax.devices()[0]).platform
        self.lanes = lanes or min(DEFAULT_LANES.get(platform, 1), n_slots)
        if lanes is None and platform != "cpu":
            # Accelerators: round small batches up to a power of two so lanes stay few shapes.
            self.lanes = min(DEFAULT_LANES.get(platform, 256), 1 << (n_slots - 1).bit_length())
        padded = -(-n_slots // self.lanes) * self.lanes
        self._setup(model, padded, self.lanes)
        model = self.model
        self.n_requested = n_slots
        self.variants = ModelVariants(self.models, impl=impl, device=device)
        self.mx = self.variants.base
        layout, variants, lanes = self.layout, self.variants, self.lanes
        step = functools.partial(step_slot, layout, self.n_substeps, variants)
        self._step = jax.jit(in_lanes(step, 2, lanes))
        self._reset = jax.jit(in_lanes(functools.partial(reset_slot, layout, variants), 4, lanes))
        self._settle = jax.jit(
            lambda mx, stacked, n, state, mask: in_lanes(
                lambda s, m: settle_slot(variants, mx, stacked, n, s, m), 2, lanes
            )(state, mask),
            static_argnums=(2,),
        )
        self._contacts = jax.jit(
            lambda geom, dist, a, b: jax.vmap(pair_contacts, in_axes=(0, 0, None, None))(
                geom, dist, a, b
            )
        )
        n_slots = padded
        home = np.broadcast_to(home_qpos(model), (n_slots, model.nq))
        d0 = mjx.make_data(self.mx)
        zeros = jnp.zeros(n_slots, jnp.int32)
        empty = SimState(
            data=jax.tree.map(lambda x: jnp.broadcast_to(x, (n_slots, *x.shape)), d0),
            grip_open=jnp.ones((n_slots, len(self.arms)), bool),
            init_qpos=jnp.asarray(home, self._dtype),
            actions=zeros,
            variant=zeros,
        )
        self.state = self._reset(
            self.mx,
            self.variants.stacked,
            empty,
            jnp.ones(n_slots, bool),
            jnp.asarray(home, self._dtype),
            zeros,
        )

    def reset(
        self,
        slots: Sequence[int],
        qpos: np.ndarray,
        settle_steps: int = 0,
        variants: Sequence[int] | None = None,
    ) -> None:
        """Reset `slots` to the given qpos rows (len(slots), nq), each with its model variant
        (default 0), and settle them for `settle_steps` physics steps."""
        qpos = self._check_reset(slots, qpos)
        v = self._check_variants(slots, variants)
        mask = np.zeros(self.n_slots, bool)
        full = np.array(self.state.init_qpos)
        var = np.array(self.state.variant)
        mask[list(slots)] = True
        full[list(slots)] = qpos
        var[list(slots)] = v
        mask_j = jnp.asarray(mask)
        self.state = self._reset(
            self.mx,
            self.variants.stacked,
            self.state,
            mask_j,
            jnp.asarray(full, self._dtype),
            jnp.asarray(var),
        )
        if settle_steps > 0:
            self.hold(settle_steps, slots)

    def hold(self, n_steps: int, slots: Sequence[int] | None = None) -> None:
        """Advance physics n_steps with the current references held (all slots by default)."""
        mask = (
            np.ones(self.n_slots, bool)
            if slots is None
            else np.isin(np.arange(self.n_slots), slots)
        )
        # Fixed-size chunks: one compiled program serves every settle length (the reset gate
        # holds 2,300 then 200 steps) instead of one compile per length.
        mask_j = jnp.asarray(mask)
        chunks = [HOLD_CHUNK] * (n_steps // HOLD_CHUNK)
        if n_steps % HOLD_CHUNK:
            chunks.append(n_steps % HOLD_CHUNK)
        for n in chunks:
            self.state = self._settle(self.mx, self.variants.stacked, n, self.state, mask_j)

    def _execute(self, rows: CommandRows) -> StepInfo:
        self.state, info = self._step(
            self.mx, self.variants.stacked, self.geoms, self.state, rows.to_device(self._dtype)
        )
        return jax.device_get(info)

    def variant(self) -> np.ndarray:
        return np.asarray(self.state.variant)

    def contact_flags(
        self, side_a: np.ndarray, side_b: np.ndarray, slots: np.ndarray | None = None
    ) -> np.ndarray:
        contact = self.state.data._impl.contact
        return np.asarray(
            self._contacts(contact.geom, contact.dist, jnp.asarray(side_a), jnp.asarray(side_b))
        )

    def qpos(self) -> np.ndarray:
        return np.asarray(self.state.data.qpos)

    def grip_open(self) -> np.ndarray:
        return np.asarray(self.state.grip_open)

    def init_qpos(self) -> np.ndarray:
        return np.asarray(self.state.init_qpos)


def proprio_fields(p: Proprio, slot: int, arms: Sequence[str]) -> dict[str, dict[str, Any]]:
    """The model-visible proprioception of one slot, per arm, in the fields of FACTS.md."""

    def r(v: Any, nd: int) -> list[float]:
        return [round(float(x), nd) for x in v]

    out = {}
    for i, arm in enumerate(arms):
        rot = p.rot[slot, i]
        out[arm] = {
            "is_open": bool(p.is_open[slot, i]),
            "finger_center_xyz": r(p.gc[slot, i], 4),
            "control_eepose_xyz": r(p.ee[slot, i], 4),
            "control_eepose_rpy_deg": r(np.degrees(p.rpy[slot, i]), 2),
            "control_eepose_quat": r(p.quat[slot, i], 4),
            "local_axes_world": {k: r(rot[:, j], 4) for j, k in enumerate(("rx", "ry", "rz"))},
        }
    return out
