"""The one small interface every physics backend implements, and the host-side logic they share.

A batch holds N episodes ("slots") of one scene and executes one agent action per slot per
`step` call. Three implementations:

- `mjx_batch.SimBatch`: MJX on JAX (CPU JAX for tests, TPUs), plan + substeps in one jit;
- `warp.batch.WarpBatch`: MuJoCo Warp on a GPU, plan + substeps + observation in one captured
  CUDA graph;
- `cpu.CpuBatch`: C MuJoCo slot by slot (the oracle, and the fastest path on a laptop).

`backends.make_batch` is the one place that chooses between them. What they share lives in
`BatchBase`: validating and encoding actions (bulk arrays in, `CommandRows`), shaping results,
slot checks, and the state export/import the settled-state cache (`reset_cache`) uses.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from pydantic import BaseModel

from vabench import protocol as P
from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)
from vabench.sim_mjx import kinematics as kin
from vabench.sim_mjx.actions import CommandRows, encode, needs_orientation
from vabench.sim_mjx.layout import ArmLayout, Proprio, proprio_slot
from vabench.sim_mjx.pytree import PyTree, pytree_dataclass
from vabench.sim_mjx.scene import free_objects

STATE_FIELDS = ("time", "qpos", "qvel", "act", "ctrl", "warmstart", "grip_open")
"""What `get_state` returns per slot: everything the next action's physics depends on (with
the slot's model variant, passed separately)."""


class SimulationError(RuntimeError):
    """The simulator could not produce trustworthy physics for some slots (a contact or
    constraint buffer overflowed). Infrastructure, not the model's doing: the episode is
    re-run, never scored."""


class DeviceFailure(RuntimeError):
    """The GPU's CUDA context failed (an illegal memory access, a launch failure: CUDA's
    sticky errors): nothing more can run on that device in this process. Not an episode's
    outcome: the episodes it interrupts get no record, the sweep stops, and the same command
    (a new process, a new context) runs them again."""


_CONTEXT_CHECKS: dict[str, Callable[[], str | None]] = {}


def watch_device(name: str, check: Callable[[], str | None]) -> None:
    """Register how to ask whether device `name`'s context has failed (`check` returns the
    reason, or None while it works). The Warp backends register each CUDA device they queue
    work on (`warp.device.device_lock`)."""
    _CONTEXT_CHECKS.setdefault(name, check)


def watched_devices() -> bool:
    """Whether any device's context check is registered (none on a machine without CUDA)."""
    return bool(_CONTEXT_CHECKS)


def device_failure(err: BaseException) -> DeviceFailure | None:
    """`err` as a `DeviceFailure` when a device this process uses has a failed context, else
    None. The one test an episode's error passes before it is recorded: after a sticky CUDA
    error every later call fails wherever it is made (an allocation, a module load, a JPEG
    encode), and no call site can be trusted to wrap its own (a run of 8 engine processes
    under MPS recorded 136 such errors as harness errors before this). Synchronises
    the devices checked: for error paths only."""
    if isinstance(err, DeviceFailure):
        return err
    for check in list(_CONTEXT_CHECKS.values()):
        reason = check()
        if reason is not None:
            failure = DeviceFailure(f"{reason}; first error here: {type(err).__name__}: {err}")
            failure.__cause__ = err
            return failure
    return None


@pytree_dataclass
class StepInfo(PyTree):
    executed: jax.Array  # (N,) bool: the slot's physics advanced
    planner_success: jax.Array  # (N,) bool
    clipped: jax.Array  # (N, A) bool
    executed_m: jax.Array  # (N, A) planned GC displacement after clipping
    failure: Any = None  # (N,) str | None per slot: why its physics is not to be trusted


DIVERGED = (
    "physics diverged (the world's state left the finite numbers during this action): the "
    "simulator failed, not the model; the episode is re-run"
)


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
    infrastructure_error: str | None = None  # the simulator failed this slot (re-run it)


def in_lanes(fn: Any, n_batched: int, lanes: int) -> Any:
    """vmap `fn` over `lanes` slots at a time and loop (lax.map) over groups of lanes.

    XLA may sum in a different order when the batch dimension changes size, so a plain vmap over
    N slots is not bit-reproducible across N. Here every slot is computed by the same compiled
    lanes-wide body whatever N is, which makes a slot's result independent of the batch size, of
    its index and of the other slots. The last `n_batched` arguments carry the slot axis; N need
    not be a multiple of lanes (the last group is padded with copies of the last slot).
    """

    def run(*args: Any) -> Any:
        shared, batched = args[: len(args) - n_batched], args[len(args) - n_batched :]
        n = jax.tree.leaves(batched)[0].shape[0]
        pad = -n % lanes

        def group(x: jax.Array) -> jax.Array:
            if pad:
                x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
            return x.reshape(x.shape[0] // lanes, lanes, *x.shape[1:])

        grouped = jax.tree.map(group, batched)
        out = jax.lax.map(lambda xs: jax.vmap(lambda *b: fn(*shared, *b))(*xs), grouped)
        return jax.tree.map(lambda x: x.reshape(x.shape[0] * lanes, *x.shape[2:])[:n], out)

    return run


def hold_chunks(n_steps: int, chunk: int) -> list[int]:
    """n_steps as steps of `chunk` and a remainder: a backend compiles (or captures) one
    program per chunk length, not one per hold length (the reset gate holds 2,300 then 200)."""
    chunks = [chunk] * (n_steps // chunk)
    if n_steps % chunk:
        chunks.append(n_steps % chunk)
    return chunks


def _action_key(raw: Any) -> Any:
    """A hashable key of a raw action (dict or protocol model), or None when it has none."""
    if isinstance(raw, BaseModel):
        return (type(raw), json.dumps(raw.model_dump(exclude_none=True), sort_keys=True))
    if isinstance(raw, dict):
        try:
            return json.dumps(raw, sort_keys=True)
        except (TypeError, ValueError):
            return None
    return None


class BatchBase:
    """Host-side logic shared by every backend: validation, encoding, results and
    observations. Subclasses own the state and implement the methods marked below."""

    model: mujoco.MjModel
    n_slots: int
    layout: ArmLayout
    arms: tuple[str, ...]
    geoms: kin.ArmGeometry
    n_substeps: int
    objects: list[tuple[str, int]]
    backend_id: str = "?"  # names the physics in cache keys and records, e.g. "c-mujoco-4.0.0"
    action_end: str = "fixed"  # controller.ACTION_ENDS (backends c and warp)
    # Physics substeps each slot's last action (or hold) ran (n_substeps for an action with
    # action_end fixed; 0 for a slot that did not act): what ending at rest saves, per slot.
    last_substeps: np.ndarray

    def _setup(
        self, models: mujoco.MjModel | Sequence[mujoco.MjModel], n_slots: int, lanes: int
    ) -> None:
        """`lanes`: see `in_lanes`; every JAX per-slot computation of the batch uses it, so a
        slot's results never depend on the batch size."""
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
        self._parsed: dict[Any, Any] = {}
        self.last_substeps = np.zeros(n_slots, np.int32)

    # -- to implement -----------------------------------------------------------------------
    def _execute(self, rows: CommandRows) -> StepInfo:
        """Run the encoded commands; return host-side StepInfo."""
        raise NotImplementedError

    def reset(
        self,
        slots: Sequence[int],
        qpos: np.ndarray,
        settle_steps: int = 0,
        variants: Sequence[int] | None = None,
    ) -> None:
        """Reset `slots` to the given qpos rows (len(slots), nq): zero velocity, arm references
        at the arm's joints, fingers open, each slot with its model variant (default 0); then
        settle them for `settle_steps` physics steps. The same for every backend: a state
        written with `set_state`, then `hold`."""
        slots = list(slots)
        qpos = self._check_reset(slots, qpos)
        n, m = len(slots), self.model
        state = {
            "time": np.zeros(n),
            "qpos": qpos,
            "qvel": np.zeros((n, m.nv)),
            "act": np.zeros((n, m.na)),
            "ctrl": self.layout.reset_ctrl(np.zeros((n, m.nu)), qpos),
            "warmstart": np.zeros((n, m.nv)),
            "grip_open": np.ones((n, len(self.arms)), bool),
        }
        self.set_state(slots, state, self._check_variants(slots, variants))
        if settle_steps > 0:
            self.hold(settle_steps, slots)

    def hold(self, n_steps: int, slots: Sequence[int] | None = None) -> None:
        """Advance physics n_steps with the current references held (all slots by default)."""
        raise NotImplementedError

    def get_state(self, slots: Sequence[int]) -> dict[str, np.ndarray]:
        """The physics state of `slots`: {field: (len(slots), ...)} for STATE_FIELDS."""
        raise NotImplementedError

    def _write_state(
        self, slots: list[int], state: dict[str, np.ndarray], variants: np.ndarray
    ) -> None:
        """`set_state` once its arguments are checked (`variants`: one valid id per slot)."""
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
        """(N, P) bool: for each watched pair p, some contact touches (dist <= 0) a geom of
        side_a[p] and one of side_b[p] ((P, ngeom) bool masks) at each slot's current state.
        `slots` (bool mask) lets a backend skip slots whose rows the caller ignores."""
        raise NotImplementedError

    def close(self) -> None:
        """Release threads or device memory (the batch is unusable afterwards)."""

    # -- shared -----------------------------------------------------------------------------
    def set_state(
        self,
        slots: Sequence[int],
        state: dict[str, np.ndarray],
        variants: Sequence[int] | np.ndarray,
    ) -> None:
        """Put `slots` in the given state (from `get_state` of the same backend and scene)."""
        slots = list(slots)
        self._check_state(slots, state)
        self._write_state(slots, state, self._check_variants(slots, variants))

    def _check_variants(
        self, slots: Sequence[int], variants: Sequence[int] | np.ndarray | None
    ) -> np.ndarray:
        if variants is None:
            return np.zeros(len(slots), np.int32)
        v = np.asarray(variants, np.int32)
        if v.shape != (len(slots),) or (v < 0).any() or (v >= len(self.models)).any():
            raise ValueError(
                f"variants must be {len(slots)} ints in [0, {len(self.models)}), got {variants}"
            )
        return v

    def encode(self, actions: Sequence[Any]) -> tuple[CommandRows, list[ActionResult | None]]:
        """Validate and encode one action per slot (None = idle): the command arrays and a
        result per slot (invalid actions get theirs now, with a message naming the field).
        Equal actions are parsed once (an episode sweep repeats few distinct actions). A world
        rotation is encoded from the gripper orientations of the current state, the ones the
        controller starts from (`actions` module docstring), read once per call."""
        if len(actions) < self.n_slots and len(actions) == getattr(self, "n_requested", -1):
            actions = [*actions, *([None] * (self.n_slots - len(actions)))]  # lane padding
        if len(actions) != self.n_slots:
            raise ValueError(
                f"expected {self.n_slots} actions (None for idle slots), got {len(actions)}"
            )
        rows = CommandRows.idle(self.n_slots, len(self.arms))
        results: list[ActionResult | None] = [None] * self.n_slots
        rot: np.ndarray | None = None
        for slot, raw in enumerate(actions):
            if raw is None:
                continue
            key = _action_key(raw)
            parsed = self._parsed.get(key) if key is not None else None
            if parsed is None:
                obj = raw.model_dump(exclude_none=True) if isinstance(raw, BaseModel) else raw
                try:
                    parsed = P.parse_robot_action(obj, self.arms)
                except P.ActionError as err:
                    parsed = err
                if key is not None and len(self._parsed) < 4096:
                    self._parsed[key] = parsed
            if isinstance(parsed, P.ActionError):
                results[slot] = ActionResult(valid=False, error=str(parsed))
                continue
            if rot is None and needs_orientation(parsed):
                rot = np.asarray(self.proprio().rot)
            encode(parsed, self.arms, rows, slot, None if rot is None else rot[slot])
            results[slot] = ActionResult(valid=True, label=parsed.label())
        return rows, results

    def step_rows(self, rows: CommandRows) -> StepInfo:
        """Execute already-encoded commands (the bulk path: one array per field for the whole
        batch). Slots with `rows.active` false are idle and stay exactly as they were. The
        rows hold local rotation vectors: a world rotation goes through `encode`."""
        if rows.active.shape != (self.n_slots,):
            raise ValueError(f"rows must cover {self.n_slots} slots, got {rows.active.shape}")
        return self._execute(rows)

    def step(self, actions: Sequence[Any]) -> list[ActionResult | None]:
        """Execute one action per slot: None (idle), a validated action, or a raw dict.

        Invalid actions are rejected with a message naming the field and leave the slot as it
        was; so do actions whose plan fails (planner_success false).
        """
        rows, results = self.encode(actions)
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
            if info.failure is not None and info.failure[slot]:
                res.infrastructure_error = str(info.failure[slot])
        acted = [s for s, r in enumerate(results) if r is not None and r.executed]
        for slot in np.asarray(acted, int)[self._diverged(acted)]:
            res = results[slot]
            assert res is not None
            res.infrastructure_error = res.infrastructure_error or DIVERGED
        return results

    def _diverged(self, slots: Sequence[int]) -> np.ndarray:
        """Per slot of `slots` (bool), whether its physics diverged in the last action: a
        non-finite pose (GPU backends carry NaN on). C MuJoCo resets a diverging world to its
        model's default pose instead, so its backend adds the warnings it counted."""
        if not len(slots):
            return np.zeros(0, bool)
        return ~np.isfinite(self.qpos()[list(slots)]).all(axis=1)

    def proprio(self) -> Proprio:
        """Proprioception of every slot, as host arrays."""
        qpos = jnp.asarray(self.qpos(), self._dtype)
        return jax.device_get(self._proprio(self.geoms, qpos, jnp.asarray(self.grip_open())))

    def failures(self) -> list[str | None]:
        """Per slot, why its current physics cannot be trusted (None: it can). Backends
        without buffers that can overflow never fail."""
        return [None] * self.n_slots

    def diverged_since_written(self, slots: Sequence[int]) -> np.ndarray:
        """Per slot of `slots`, whether its physics diverged since its state was last written
        where the pose cannot show it (C MuJoCo resets a diverging world; GPU backends carry
        NaN on, which the pose shows)."""
        return np.zeros(len(slots), bool)

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
        self._check_slots(slots)
        return qpos

    def _check_state(self, slots: Sequence[int], state: dict[str, np.ndarray]) -> None:
        missing = [f for f in STATE_FIELDS if f not in state]
        if missing:
            raise ValueError(f"state lacks {missing}")
        for f in STATE_FIELDS:
            if len(state[f]) != len(slots):
                raise ValueError(f"state[{f!r}] has {len(state[f])} rows for {len(slots)} slots")
        self._check_slots(slots)

    def _check_slots(self, slots: Sequence[int]) -> None:
        if len(slots):
            index = np.asarray(slots)
            if index.min() < 0 or index.max() >= self.n_slots:
                bad = index[(index < 0) | (index >= self.n_slots)][0]
                raise IndexError(f"slot {bad} out of range [0, {self.n_slots})")
