"""The C MuJoCo path: the same model and the same controller, physics on the CPU.

Used for parity tests (MJX against the reference implementation of MuJoCo) and as the baseline
the MJX batch must beat. The plan and the control sequence come from the same jitted functions
as the MJX batch (`layout.ctrl_sequence_slot`); only the physics differs. Physics runs either in
one thread with `mj_step` (threads=0) or through `mujoco.rollout` on a thread pool.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import rollout

from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx import jax_setup  # noqa: F401  (JAX configured before it compiles)
from vabench.sim_mjx.actions import CommandRows
from vabench.sim_mjx.interface import STATE_FIELDS, BatchBase, StepInfo, in_lanes
from vabench.sim_mjx.layout import ctrl_sequence_slot
from vabench.sim_mjx.scene import home_qpos, rest_speeds
from vabench.sim_mjx.variants import check_same_structure

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
# What C MuJoCo counts when a world diverges (it then resets the world to the model's default
# pose and goes on: finite numbers, wrong physics).
_UNSTABLE = (
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQACC,
)


def _clear_instabilities(d: mujoco.MjData) -> None:
    """Zero the counters: `mj_resetData` (C MuJoCo's answer to a divergence) sets them to 0 and
    counts 1, so a count carried over from another slot of the shared MjData would hide the
    next divergence."""
    for w in _UNSTABLE:
        d.warning[w].number = 0


def _instabilities(d: mujoco.MjData) -> int:
    return sum(int(d.warning[w].number) for w in _UNSTABLE)


class CpuBatch(BatchBase):
    """N slots of one scene simulated by C MuJoCo, with the batch's interface."""

    def __init__(
        self,
        model: mujoco.MjModel | Sequence[mujoco.MjModel],
        n_slots: int,
        threads: int = 0,
        action_end: str = "fixed",
    ):
        self._setup(model, n_slots, lanes=1)
        self.action_end = ctl.check_action_end(action_end)
        check_same_structure(self.models)
        model = self.model
        self.backend_id = f"c-mujoco-{mujoco.__version__}"
        self.threads = threads
        self._datas = [mujoco.MjData(m) for m in self.models]
        self._nstate = mujoco.mj_stateSize(model, _STATE)
        self._state = np.zeros((n_slots, self._nstate))
        # The solver's warm start is per slot too: left in a shared MjData it would carry one
        # slot's last accelerations into the next slot simulated, so results would depend on
        # which episodes share the batch.
        self._warm = np.zeros((n_slots, model.nv))
        self._ctrl = np.zeros((n_slots, model.nu))
        self._rest_speeds = rest_speeds(model)
        self._grip_open = np.ones((n_slots, len(self.arms)), bool)
        self._init_qpos = np.zeros((n_slots, model.nq))
        self._variant = np.zeros(n_slots, np.int32)
        # Slot by slot (in_lanes, 1 lane): a plain vmap's float32 results depend on the batch
        # size on XLA CPU, and an episode must not move differently because others share it.
        self._sequence = jax.jit(
            in_lanes(
                functools.partial(
                    ctrl_sequence_slot, self.layout, self.n_substeps, action_end == "paced"
                ),
                3,
                1,
            )
        )
        self._pool = rollout.Rollout(nthread=threads) if threads > 0 else None
        self._thread_data = [mujoco.MjData(model) for _ in range(threads)]
        # Per slot: C MuJoCo reset the world since its state was last written (a reset, a
        # loaded state) or, for a slot that acted, during its last action (serial path only:
        # the rollout threads' warnings are not read; they serve benchmarks).
        self._unstable = np.zeros(n_slots, bool)
        # Capture (demonstration videos; off by default): with `capture_every` = k > 0, every
        # k-th physics step of an action appends the slot's qpos to `captured[slot]`. Only
        # actions are captured, never reset or hold; it reads state and changes no result.
        self.capture_every = 0
        self.captured: dict[int, list[np.ndarray]] = {}
        self.reset(range(n_slots), np.broadcast_to(home_qpos(model), (n_slots, model.nq)))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def _write_state(self, slots: list[int], state: dict[str, np.ndarray], var: np.ndarray) -> None:
        for row, slot in enumerate(slots):
            m, d = self.models[var[row]], self._datas[var[row]]
            mujoco.mj_resetData(m, d)
            d.time = state["time"][row]
            d.qpos[:] = state["qpos"][row]
            d.qvel[:] = state["qvel"][row]
            d.act[:] = state["act"][row]
            d.ctrl[:] = state["ctrl"][row]
            mujoco.mj_forward(m, d)
            mujoco.mj_getState(m, d, self._state[slot], _STATE)
            self._warm[slot] = state["warmstart"][row]
            self._ctrl[slot] = state["ctrl"][row]
            self._init_qpos[slot] = state["qpos"][row]
            self._grip_open[slot] = state["grip_open"][row]
            self._variant[slot] = var[row]
            self._unstable[slot] = False

    def get_state(self, slots: Sequence[int]) -> dict[str, np.ndarray]:
        slots = list(slots)
        out: dict[str, list[np.ndarray]] = {k: [] for k in STATE_FIELDS}
        for slot in slots:
            m, d = self.models[self._variant[slot]], self._datas[self._variant[slot]]
            mujoco.mj_setState(m, d, self._state[slot], _STATE)
            out["time"].append(np.array(d.time))
            out["qpos"].append(d.qpos.copy())
            out["qvel"].append(d.qvel.copy())
            out["act"].append(d.act.copy())
        out["ctrl"] = list(self._ctrl[slots])
        out["warmstart"] = list(self._warm[slots])
        out["grip_open"] = list(self._grip_open[slots])
        return {k: np.array(v) for k, v in out.items()}

    def hold(self, n_steps: int, slots: Sequence[int] | None = None) -> None:
        slots = list(range(self.n_slots)) if slots is None else list(slots)
        controls = np.repeat(self._ctrl[slots][:, None, :], n_steps, axis=1)
        self._run(slots, controls)

    def _run(
        self,
        slots: list[int],
        controls: np.ndarray,
        capture: int = 0,
        rest_from: np.ndarray | int = 0,
    ) -> None:
        """Advance `slots` through the control sequences (len(slots), n_steps, nu); with
        `capture` = k > 0, append qpos to `captured[slot]` after every k-th step; with
        `rest_from` = r > 0 (an action ending at rest; one a slot), a slot stops after the first
        step k >= r at which every dof is slower than its rest speed (the threads' path computes
        every step and takes the state of that one)."""
        if not slots:
            return
        rests = np.broadcast_to(np.asarray(rest_from, np.int64), (len(slots),))
        if capture > 0 and self._pool is not None:
            raise ValueError("capture_every needs the serial path (threads=0)")
        if self._pool is None:
            for row, slot in enumerate(slots):
                m, d = self.models[self._variant[slot]], self._datas[self._variant[slot]]
                mujoco.mj_setState(m, d, self._state[slot], _STATE)
                d.qacc_warmstart[:] = self._warm[slot]
                _clear_instabilities(d)
                steps = 0
                for steps, u in enumerate(controls[row], 1):
                    d.ctrl[:] = u
                    mujoco.mj_step(m, d)
                    if capture > 0 and steps % capture == 0:
                        self.captured.setdefault(slot, []).append(d.qpos.copy())
                    if 0 < rests[row] <= steps and np.all(np.abs(d.qvel) < self._rest_speeds):
                        break
                self.last_substeps[slot] = steps
                mujoco.mj_getState(m, d, self._state[slot], _STATE)
                self._warm[slot] = d.qacc_warmstart
                self._unstable[slot] |= _instabilities(d) > 0
        else:
            # Threads (benchmarks): rollout does not return the final warm start, so each
            # action starts cold; reproducible across batching, not equal to the serial path.
            models = [self.models[self._variant[s]] for s in slots]
            states, _ = self._pool.rollout(
                models,
                self._thread_data,
                self._state[slots],
                controls,
                initial_warmstart=np.zeros((len(slots), self.model.nv)),
            )
            last = np.full(len(slots), controls.shape[1] - 1)
            if rests.any():  # the same rule as the serial path, on the recorded states
                nq, nv = self.model.nq, self.model.nv
                qvel = np.abs(states[:, :, 1 + nq : 1 + nq + nv])
                still = np.all(qvel < self._rest_speeds, axis=2)
                still &= np.arange(controls.shape[1])[None, :] >= rests[:, None] - 1
                still &= rests[:, None] > 0
                last = np.where(still.any(axis=1), np.argmax(still, axis=1), last)
            self._state[slots] = states[np.arange(len(slots)), last]
            self.last_substeps[slots] = last + 1
        self._ctrl[slots] = controls[:, -1]

    def _execute(self, rows: CommandRows) -> StepInfo:
        cmd = rows.to_device(self._dtype)
        seq, plan = self._sequence(
            self.geoms,
            jnp.asarray(self.qpos(), self._dtype),
            jnp.asarray(self._ctrl, self._dtype),
            cmd,
        )
        seq, plan = jax.device_get((seq, plan))
        go = rows.active & plan.ok
        slots = [int(s) for s in np.flatnonzero(go)]
        self._unstable[slots] = False  # each action judged by its own physics
        self.last_substeps[:] = 0
        rest = np.asarray(plan.rest_from)[slots] if ctl.ends_at_rest(self.action_end) else 0
        self._run(slots, np.asarray(seq[slots], float), self.capture_every, rest)
        opens = rows.grip == 1
        keep = rows.grip < 0
        self._grip_open[go] = np.where(keep[go], self._grip_open[go], opens[go])
        return StepInfo(
            executed=go, planner_success=plan.ok, clipped=plan.clipped, executed_m=plan.executed_m
        )

    def _diverged(self, slots: Sequence[int]) -> np.ndarray:
        return super()._diverged(slots) | self._unstable[list(slots)]

    def diverged_since_written(self, slots: Sequence[int]) -> np.ndarray:
        """C MuJoCo reset these worlds since their states were written (a reset's settling
        included: the world then settles from the model's default pose, finite, and would
        pass the gate with the wrong scene)."""
        return self._unstable[list(slots)].copy()

    def qpos(self) -> np.ndarray:
        # full-physics state layout: time, qpos, qvel, act, ...
        return self._state[:, 1 : 1 + self.model.nq].copy()

    def grip_open(self) -> np.ndarray:
        return self._grip_open.copy()

    def init_qpos(self) -> np.ndarray:
        return self._init_qpos.copy()

    def variant(self) -> np.ndarray:
        return self._variant.copy()

    def contact_flags(
        self, side_a: np.ndarray, side_b: np.ndarray, slots: np.ndarray | None = None
    ) -> np.ndarray:
        """Contacts at each slot's current state (collision detection by mj_forward); only for
        `slots` (bool mask) when given, the other rows stay False."""
        out = np.zeros((self.n_slots, len(side_a)), bool)
        for slot in range(self.n_slots) if slots is None else np.flatnonzero(slots):
            m, d = self.models[self._variant[slot]], self._datas[self._variant[slot]]
            mujoco.mj_setState(m, d, self._state[slot], _STATE)
            mujoco.mj_forward(m, d)
            n = d.ncon
            if n == 0:
                continue
            g1, g2 = d.contact.geom1[:n], d.contact.geom2[:n]
            touching = d.contact.dist[:n] <= 0.0
            hit = (side_a[:, g1] & side_b[:, g2]) | (side_a[:, g2] & side_b[:, g1])
            out[slot] = np.any(hit & touching[None, :], axis=1)
        return out
