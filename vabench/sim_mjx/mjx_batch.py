"""The MJX-JAX backend: N episodes ("slots") of one MJX model, one agent action at a time.

Inside: pure jitted functions over the batch state (`SimState`). At the edge: `SimBatch`, which
owns the device buffers (validation, encoding and results come from `interface.BatchBase`).
For CPU JAX (tests) and TPUs; on NVIDIA GPUs the Warp backend (`warp.batch`) is far faster.

One call of `SimBatch.step` executes one action per slot, each slot with its own kind, in a
single jitted call: plan (closed-form IK over the waypoints) -> ACTION_SECONDS of physics
substeps tracking the joint reference -> merge. Slots without an action, with an invalid action
or with a failed plan keep their previous state bit for bit: their physics does not advance.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx import jax_setup  # JAX configured before it compiles
from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx.actions import CommandRows
from vabench.sim_mjx.interface import BatchBase, StepInfo, hold_chunks, in_lanes
from vabench.sim_mjx.layout import ArmLayout, plan_from, with_refs
from vabench.sim_mjx.pytree import PyTree, pytree_dataclass
from vabench.sim_mjx.scene import home_qpos
from vabench.sim_mjx.variants import ModelVariants

with jax_setup.quiet_stdout():  # this backend's alone (`jax_setup.quiet_stdout`)
    from mujoco import mjx


@pytree_dataclass
class SimState(PyTree):
    data: mjx.Data  # batched over slots
    grip_open: jax.Array  # (N, A) bool: last aperture command (True = open)
    init_qpos: jax.Array  # (N, nq) qpos at the slot's last reset, for task predicates
    actions: jax.Array  # (N,) int32 actions executed since the reset
    variant: jax.Array  # (N,) int32 model variant (object model id) of the slot


def _where(mask: jax.Array, new: Any, old: Any) -> Any:
    return jax.tree.map(lambda a, b: jnp.where(mask, a, b), new, old)


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
    plan = plan_from(layout, geoms, d0.qpos, d0.ctrl, cmd, n_substeps)

    def substep(d: mjx.Data, k: jax.Array) -> tuple[mjx.Data, None]:
        arm, fingers = ctl.ctrl_at(plan, k)
        return mjx.step(mx, d.replace(ctrl=with_refs(layout, d.ctrl, arm, fingers))), None

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


def load_slot(
    variants: ModelVariants,
    mx: mjx.Model,
    stacked: tuple[jax.Array, ...],
    state: SimState,
    mask: jax.Array,
    loaded: dict[str, jax.Array],
    init_qpos: jax.Array,
    variant: jax.Array,
) -> SimState:
    """Fresh data holding `loaded` (STATE_FIELDS of one slot), derived quantities recomputed;
    a reset is a load with zero velocity and the arm's references at its joints."""
    mx = variants.select(mx, stacked, variant)
    d = mjx.make_data(mx)
    d = d.replace(
        time=loaded["time"],
        qpos=loaded["qpos"],
        qvel=loaded["qvel"],
        act=loaded["act"],
        ctrl=loaded["ctrl"],
        qacc_warmstart=loaded["warmstart"],
    )
    fresh = SimState(
        data=mjx.forward(mx, d),
        grip_open=loaded["grip_open"],
        init_qpos=init_qpos,
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
        self.backend_id = f"mjx-jax-{mujoco.__version__}-{platform}"
        self.variants = ModelVariants(self.models, impl="jax", device=device)
        self.mx = self.variants.base
        layout, variants, lanes = self.layout, self.variants, self.lanes
        step = functools.partial(step_slot, layout, self.n_substeps, variants)
        self._step = jax.jit(in_lanes(step, 2, lanes))
        self._load = jax.jit(in_lanes(functools.partial(load_slot, variants), 5, lanes))
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
        self.state = SimState(
            data=jax.tree.map(lambda x: jnp.broadcast_to(x, (n_slots, *x.shape)), d0),
            grip_open=jnp.ones((n_slots, len(self.arms)), bool),
            init_qpos=jnp.asarray(home, self._dtype),
            actions=zeros,
            variant=zeros,
        )
        self.reset(range(n_slots), home)

    def _fields(self) -> dict[str, jax.Array]:
        """The batch's arrays of STATE_FIELDS, (N, ...) each."""
        d = self.state.data
        return {
            "time": d.time,
            "qpos": d.qpos,
            "qvel": d.qvel,
            "act": d.act,
            "ctrl": d.ctrl,
            "warmstart": d.qacc_warmstart,
            "grip_open": self.state.grip_open,
        }

    def _write_state(
        self, slots: list[int], state: dict[str, np.ndarray], variants: np.ndarray
    ) -> None:
        mask = np.zeros(self.n_slots, bool)
        mask[slots] = True
        full = {}
        for name, arr in self._fields().items():
            host = np.array(arr)
            host[slots] = state[name]
            full[name] = jnp.asarray(host, arr.dtype)
        init = np.array(self.state.init_qpos)
        init[slots] = state["qpos"]
        var = np.array(self.state.variant)
        var[slots] = variants
        self.state = self._load(
            self.mx,
            self.variants.stacked,
            self.state,
            jnp.asarray(mask),
            full,
            jnp.asarray(init, self._dtype),
            jnp.asarray(var),
        )

    def get_state(self, slots: Sequence[int]) -> dict[str, np.ndarray]:
        slots = list(slots)
        return {name: np.asarray(arr)[slots] for name, arr in self._fields().items()}

    def hold(self, n_steps: int, slots: Sequence[int] | None = None) -> None:
        """Advance physics n_steps with the current references held (all slots by default)."""
        mask = (
            np.ones(self.n_slots, bool)
            if slots is None
            else np.isin(np.arange(self.n_slots), slots)
        )
        mask_j = jnp.asarray(mask)
        for n in hold_chunks(n_steps, HOLD_CHUNK):
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
