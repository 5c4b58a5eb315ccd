"""The Warp backend: N slots of one scene on MuJoCo Warp, one captured CUDA graph per action.

One agent action for the whole batch is one graph launch: plan every slot (closed-form IK over
the waypoints, `control.plan_kernel`), then ACTION_SECONDS of physics substeps (joint
references of substep k written by `ctrl_kernel`, then `mujoco_warp.step`), then the merge
(slots that were idle, invalid or whose plan failed get their saved state back bit for bit,
`rows.Snapshot`), then the observation (kinematics and collision at the final state for the
predicates' contact flags, and the proprioception). Nothing returns to the host until the graph
ends. Settling (`hold`) is a graph of HOLD_CHUNK steps with the same merge. How the graphs hold
the substeps: `graphs`.

On the CPU device (tests) the same kernels run without a graph: Warp's CPU backend executes
every thread of a launch in order, so a slot's trajectory does not depend on the batch size,
its index or its neighbours. On a GPU, MuJoCo Warp's contact and constraint ordering uses
atomics unless `deterministic` asks for its stable orderings (slower; docs/PERFORMANCE.md,
"Simulator throughput").

Threads and streams (`streams`): every batch has a CUDA stream of its own. A method queues its
device work holding the device's lock with that stream current (Warp's current stream is the
process's, not the thread's), queues the copies of everything the host reads next into pinned
buffers (`streams.Readback`: the step's flags, qpos, proprioception, grip state and the
predicates' contact flags), records an event, and waits for it with the lock released: the GPU
runs the actions of many batches side by side while their threads queue the next ones. Host
reads (`qpos`, `proprio`, `contact_flags` of the watched pairs, ...) then come from those copies,
with no device work. Allocations happen under the lock with the batch's stream current. A
free is not ordered behind that stream: Warp frees pool memory on CUDA's legacy stream, which
waits for no non-blocking stream, so device memory the batch's queued work reads is dropped
only after `_wait` (or kept by the batch for its life).

Buffers (contacts, constraint rows) are sized from the scene (`model.capacity`); a slot
whose world overflows them gets an infrastructure error (`failure_text`), never silent wrong
physics.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from vabench import switches
from vabench.sim_mjx import controller as ctl
from vabench.sim_mjx.actions import CommandRows
from vabench.sim_mjx.interface import BatchBase, StepInfo, hold_chunks
from vabench.sim_mjx.layout import Proprio
from vabench.sim_mjx.scene import home_qpos, rest_speeds
from vabench.sim_mjx.variants import check_same_structure
from vabench.sim_mjx.warp import arm_indices as wl
from vabench.sim_mjx.warp import control as wc
from vabench.sim_mjx.warp import fk_ik as wk
from vabench.sim_mjx.warp import rows as wr
from vabench.sim_mjx.warp import streams
from vabench.sim_mjx.warp.device import device_lock
from vabench.sim_mjx.warp.graphs import Graphs
from vabench.sim_mjx.warp.model import FAILURE_BITS, WarpModel, capacity, failure_texts
from vabench.sim_mjx.warp.modules import keep_loaded

F = TypeVar("F", bound=Callable[..., Any])


def on_device(method: F) -> F:
    """Run a WarpBatch method holding its device's lock, with the device current and the
    batch's stream current (see the module docstring: Threads and streams). The lock is
    re-entrant, so methods may call each other."""

    @functools.wraps(method)
    def locked(self: WarpBatch, *args: Any, **kwargs: Any) -> Any:
        with self._queued():
            return method(self, *args, **kwargs)

    return locked  # type: ignore[return-value]


LOOP_ENV = switches.variable("warp_loop")
"""Environment variable: how graphs hold an action's substeps (`graphs.LOOPS`; default device)."""

HOLD_CHUNK = 100  # physics steps per settle graph (see interface.hold_chunks)
PREDICATE_LANES = 32  # width of the JAX predicate and proprio vmaps (see interface.in_lanes)


class WarpBatch(BatchBase):
    """N slots of one scene on MuJoCo Warp; one agent action per slot per `step` call.

    `device`: a Warp device ("cuda:0" by default; "cpu" runs the same kernels on the CPU, for
    tests). `nconmax` / `njmax`: per-world contact and constraint-row capacity (default: sized
    from the scene). `deterministic`: MuJoCo Warp's stable contact and constraint orderings on
    GPUs (slower; closer run to run, but measured not bit-identical on a GPU). `graphs`:
    capture CUDA graphs (GPU only; off = launch kernel by kernel, for debugging). `loop`: see
    `graphs.LOOPS`. `critical_path`: this batch's episodes bound the sweep's wall time (the
    longest task's): its stream, and those of the render passes that read it, get the GPU's
    highest priority; other batches' streams the middle one, ahead of the render passes' ray
    tracing (`streams.PRIORITIES`). `action_end`: `controller.ACTION_ENDS` (at_rest and paced:
    each slot's action ends at its own rest substep; the device loop ends when every acting
    slot has).
    """

    def __init__(
        self,
        model: mujoco.MjModel | Sequence[mujoco.MjModel],
        n_slots: int,
        device: str | None = None,
        nconmax: int | None = None,
        njmax: int | None = None,
        deterministic: bool = False,
        graphs: bool = True,
        loop: str | None = None,
        critical_path: bool = False,
        action_end: str = "fixed",
    ):
        keep_loaded()  # see modules: no module's code unloaded under a running kernel
        self._setup(model, n_slots, PREDICATE_LANES)
        check_same_structure(self.models)
        m0 = self.model
        self.device = wp.get_device(device or "cuda:0")
        self.lock = device_lock(str(self.device))
        self.capacity = capacity(m0, nconmax, njmax)
        self.backend_id = f"mjx-warp-{mjw.__version__}-{mujoco.__version__}-{self.device.arch}"
        loop = loop or switches.get("warp_loop")
        self._graphs = Graphs(self.device, graphs and self.device.is_cuda, loop)
        n, arms = n_slots, len(self.arms)
        self._event: wp.Event | None = None
        self.critical_path = critical_path
        self.action_end = ctl.check_action_end(action_end)
        with self.lock, wp.ScopedDevice(self.device):
            self.stream = streams.new_stream(self.device, "greatest" if critical_path else "middle")
        with self._queued():
            self._build(n, arms, deterministic)

    def _queued(self) -> contextlib.AbstractContextManager[None]:
        """The device's lock, with the device and this batch's stream current."""
        return streams.queueing(self.lock, self.device, self.stream)

    def _build(self, n: int, arms: int, deterministic: bool) -> None:
        """The device arrays and the first reset (the caller holds the lock)."""
        m0 = self.model
        self._wm = WarpModel(self.models, n)
        if deterministic:
            self._wm.model.opt.deterministic = int(mjw.DeterminismType.ALL)
        self._m = self._wm.model
        d0 = mujoco.MjData(m0)  # no contacts yet: every slot is reset (and observed) below
        d0.qpos[:] = home_qpos(m0)
        self._d = mjw.put_data(
            m0, d0, nworld=n, nconmax=self.capacity.nconmax, njmax=self.capacity.njmax
        )
        self._idx = wl.layout_arrays(self.layout, self.device)
        self._geoms = wk.arm_geometries(self.geoms, self.device)
        self._cmd_active = wp.zeros(n, dtype=int)
        self._cmd_delta = wp.zeros((n, arms), dtype=wp.vec3)
        self._cmd_rotvec = wp.zeros((n, arms), dtype=wp.vec3)
        self._cmd_grip = wp.full((n, arms), -1, dtype=int)
        self._plan = wc.PlanBuffers.allocate(n, arms, self.device)
        self._go = wp.zeros(n, dtype=int)
        self._ok = wp.zeros(n, dtype=int)
        self._mask = wp.zeros(n, dtype=int)
        self._failed = wp.zeros(n, dtype=int)
        self._k = wp.zeros(1, dtype=int)  # substeps done in the current loop
        self._rest_speeds = wp.array(rest_speeds(m0), dtype=float, device=self.device)
        self._grip_open = wp.ones((n, arms), dtype=int)
        self._obs = wl.ProprioBuffers.allocate(n, arms, self.device)
        self._flags: wp.array | None = None
        self._sides: tuple[bytes, wp.array, wp.array] | None = None
        d = self._d
        self._readback = streams.Readback(self.device)
        o = self._obs
        for name, array in (
            ("go", self._go),
            ("ok", self._ok),
            ("clipped", self._plan.clipped),
            ("executed_m", self._plan.executed_m),
            ("failed", self._failed),
            ("qpos", d.qpos),
            ("grip_open", self._grip_open),
            ("gc", o.gc),
            ("ee", o.ee),
            ("rot", o.rot),
            ("quat", o.quat),
            ("rpy", o.rpy),
            ("fingers", o.fingers),
        ):
            self._readback.add(name, array)
        # The (N, k) device arrays of STATE_FIELDS, in the order set_state writes them;
        # the merge saves and restores the same rows.
        self._rows = {
            "qpos": d.qpos,
            "qvel": d.qvel,
            "ctrl": d.ctrl,
            "warmstart": d.qacc_warmstart,
            "act": d.act,
        }
        self._snapshot = wr.Snapshot(list(self._rows.values()), d.time)
        self._rest = wr.RestRows(self._snapshot)
        self._done = wp.zeros(n, dtype=int)
        self._newly = wp.zeros(n, dtype=int)
        self._substeps = wp.zeros(n, dtype=int)
        self._readback.add("substeps", self._substeps)
        self._variant = np.zeros(n, np.int32)
        self._init_qpos = np.zeros((n, m0.nq))
        self._host: dict[str, np.ndarray] = {}
        self.reset(range(n), np.broadcast_to(home_qpos(m0), (n, m0.nq)))

    # -- device work, queued only (see graphs) -----------------------------------------
    def _physics(
        self,
        name: str,
        pre: Callable,
        substep: Callable,
        post: Callable,
        n: int,
        condition: Callable | None = None,
    ) -> None:
        """pre, n x substep, post (see `Graphs.run_loop`); the caller is `_queued`."""
        self._host.clear()
        self._graphs.run_loop(name, pre, substep, post, n, counter=self._k, condition=condition)

    def _at_rest(self) -> bool:
        return ctl.ends_at_rest(self.action_end)

    def _rest_condition(self, go_on: wp.array) -> None:
        wp.launch(
            wr.rest_condition,
            dim=1,
            inputs=[self._k, self.n_substeps, self._go, self._done, go_on],
        )

    def _finish_queue(self) -> None:
        """After the work of a call (the caller is `_queued`): the watched contact flags at the
        new state, the copies of what the host reads, and the event that says they are done."""
        if self._sides is not None:
            self._launch_contact_flags()
        self._readback.queue()
        self._event = streams.record(self.stream)

    def _wait(self) -> None:
        """Wait (the lock released) for the last call's work, then take the host copies."""
        streams.wait(self._event)
        self._event = None
        self._host = self._readback.values()

    def _start_loop(self) -> None:
        self._k.zero_()
        self._d.overflow.zero_()

    def _observe(self) -> None:
        """Derived quantities at the final state: body poses and contacts (the predicates'
        contact flags read them) and the proprioception."""
        mjw.kinematics(self._m, self._d)
        mjw.collision(self._m, self._d)
        wl.launch_proprio(self._geoms, self._d.qpos, self._idx, self._obs, self._grip_open)

    def _step_physics(self, with_ctrl: bool) -> Callable[[], None]:
        def substep() -> None:
            if with_ctrl:
                wc.launch_ctrl(self._k, self._plan, self._idx, self._d.ctrl)
            mjw.step(self._m, self._d)
            wp.launch(wr.count_substep, dim=1, inputs=[self._k])
            if with_ctrl and self._at_rest():
                wp.launch(
                    wr.mark_rest,
                    dim=self.n_slots,
                    inputs=[
                        self._k,
                        self._plan.rest_from,
                        self._rest_speeds,
                        self._go,
                        self._d.qvel,
                        self._done,
                        self._newly,
                        self._substeps,
                    ],
                )
                self._rest.save(self._newly)

        return substep

    def _action_pre(self) -> None:
        d = self._d
        wc.launch_plan(
            self._geoms,
            d.qpos,
            d.ctrl,
            self._idx,
            self._cmd_active,
            self._cmd_delta,
            self._cmd_rotvec,
            self._cmd_grip,
            self._plan,
            self._ok,
            self._go,
            self.n_substeps,
            ctl.rest_from(self.n_substeps),
            self.action_end == "paced",
        )
        self._snapshot.save()
        self._start_loop()
        self._done.zero_()
        self._substeps.zero_()

    def _action_post(self) -> None:
        self._snapshot.restore(self._go)
        if self._at_rest():
            self._rest.restore(self._done)
        else:
            wp.launch(
                wr.fixed_substeps, dim=self.n_slots, inputs=[self._go, self._k, self._substeps]
            )
        wp.launch(
            wr.finish_action,
            dim=(self.n_slots, len(self.arms)),
            inputs=[self._go, self._cmd_grip, self._d.overflow, FAILURE_BITS],
            outputs=[self._grip_open, self._failed],
        )
        self._observe()

    def _hold_pre(self) -> None:
        self._snapshot.save()
        self._start_loop()

    def _hold_post(self) -> None:
        self._snapshot.restore(self._mask)
        wp.launch(
            wr.finish_hold,
            dim=self.n_slots,
            inputs=[self._mask, self._d.overflow, FAILURE_BITS],
            outputs=[self._failed],
        )
        self._observe()

    # -- the interface ----------------------------------------------------------------------
    def _execute(self, rows: CommandRows) -> StepInfo:
        with self._queued():
            self._cmd_active.assign(rows.active.astype(np.int32))
            self._cmd_delta.assign(rows.delta.astype(np.float32))
            self._cmd_rotvec.assign(rows.rotvec.astype(np.float32))
            self._cmd_grip.assign(rows.grip.astype(np.int32))
            self._failed.zero_()
            self._physics(
                "action",
                self._action_pre,
                self._step_physics(True),
                self._action_post,
                self.n_substeps,
                self._rest_condition if self._at_rest() else None,
            )
            self._finish_queue()
        self._wait()
        h: dict[str, Any] = self._host
        self.last_substeps = h["substeps"].astype(np.int32)
        failed = h["failed"]
        failure = failure_texts(failed, self.capacity)
        return StepInfo(
            executed=h["go"].astype(bool),
            planner_success=h["ok"].astype(bool),
            clipped=h["clipped"].astype(bool),
            executed_m=h["executed_m"],
            failure=failure if failed.any() else None,
        )

    def hold(self, n_steps: int, slots: Sequence[int] | None = None) -> None:
        mask = np.zeros(self.n_slots, np.int32)
        mask[list(range(self.n_slots)) if slots is None else list(slots)] = 1
        with self._queued():
            self._mask.assign(mask)
            self._failed.zero_()  # finish_hold ORs each chunk's overflow bits into it
            for k in hold_chunks(n_steps, HOLD_CHUNK):
                self._physics("hold", self._hold_pre, self._step_physics(False), self._hold_post, k)
            self._finish_queue()
        self._wait()
        self._hold_failed = self._host["failed"].copy()

    def failures(self) -> list[str | None]:
        """Slots whose last hold (reset settling) overflowed a buffer."""
        failed = getattr(self, "_hold_failed", np.zeros(self.n_slots, np.int32))
        return failure_texts(failed, self.capacity)

    def _write_state(
        self, slots: list[int], state: dict[str, np.ndarray], variants: np.ndarray
    ) -> None:
        if not slots:
            return
        with self._queued():
            # Every upload stays referenced until the scatters that read it have run (`_wait`
            # below). Warp frees a pool allocation on CUDA's legacy stream, which waits for
            # no non-blocking stream (this batch's): freed at the end of this block, an upload
            # went back to the pool while its scatter was still queued, and another stream's
            # next allocation could take it, so that `idx` held another array's bytes when
            # the scatter wrote `dst[idx[i]]`: an illegal address (CUDA error 700) under MPS.
            uploads = [idx := wp.array(np.asarray(slots, np.int32), dtype=int)]
            for name, dst in self._rows.items():
                if dst.shape[1]:
                    uploads.append(wp.array(np.asarray(state[name], np.float32), dtype=float))
                    wp.launch(
                        wr.scatter_rows, dim=uploads[-1].shape, inputs=[idx, uploads[-1], dst]
                    )
            uploads.append(wp.array(np.asarray(state["time"], np.float32), dtype=float))
            wp.launch(wr.scatter, dim=len(slots), inputs=[idx, uploads[-1], self._d.time])
            uploads.append(wp.array(np.asarray(state["grip_open"], np.int32), dtype=int))
            wp.launch(
                wr.scatter_rows, dim=uploads[-1].shape, inputs=[idx, uploads[-1], self._grip_open]
            )
            self._variant[slots] = variants
            self._wm.assign(self._variant)
            self._host.clear()
            self._graphs.run("observe", self._observe)
            self._finish_queue()
        self._init_qpos[slots] = state["qpos"]
        self._wait()
        del idx
        uploads.clear()  # only now: see above

    @on_device
    def get_state(self, slots: Sequence[int]) -> dict[str, np.ndarray]:
        slots = list(slots)
        d = self._d
        return {
            "time": d.time.numpy()[slots].astype(float),
            "qpos": d.qpos.numpy()[slots],
            "qvel": d.qvel.numpy()[slots],
            "act": d.act.numpy()[slots] if self.model.na else np.zeros((len(slots), 0)),
            "ctrl": d.ctrl.numpy()[slots],
            "warmstart": d.qacc_warmstart.numpy()[slots],
            "grip_open": self._grip_open.numpy()[slots].astype(bool),
        }

    def copy_qpos(self, slots: wp.array, dst: wp.array) -> None:
        """Rows `slots` of the device qpos into rows 0.. of `dst` (a device array on this
        batch's device), for the caller's current stream: the gather runs on this batch's
        stream after the caller's queued work (which wrote `slots`) and after every action
        already queued here, never during one (an action moves idle slots and restores them at
        its end); the caller's stream then waits for it. The renderer reads the state where the
        physics left it, without a trip through the host."""
        caller = wp.get_stream(self.device) if self.device.is_cuda else None
        with self._queued():
            if caller is not None and self.stream is not None:
                self.stream.wait_stream(caller)
            wp.launch(
                wr.gather_rows,
                dim=(slots.shape[0], dst.shape[1]),
                inputs=[slots, self._d.qpos, dst],
            )
            gathered = streams.record(self.stream)
        if caller is not None and gathered is not None:
            caller.wait_event(gathered)

    @on_device
    def _fetch(self, name: str, array: wp.array) -> np.ndarray:
        if name not in self._host:
            self._host[name] = array.numpy()
        return self._host[name]

    def qpos(self) -> np.ndarray:
        return self._fetch("qpos", self._d.qpos).copy()

    def grip_open(self) -> np.ndarray:
        return self._fetch("grip_open", self._grip_open).astype(bool)

    def init_qpos(self) -> np.ndarray:
        return self._init_qpos.copy()

    def variant(self) -> np.ndarray:
        return self._variant.copy()

    def proprio(self) -> Proprio:
        o = self._obs
        return Proprio(
            gc=self._fetch("gc", o.gc),
            ee=self._fetch("ee", o.ee),
            rot=self._fetch("rot", o.rot),
            quat=self._fetch("quat", o.quat),
            rpy=self._fetch("rpy", o.rpy),
            fingers=self._fetch("fingers", o.fingers),
            is_open=self.grip_open(),
        )

    def contact_flags(
        self, side_a: np.ndarray, side_b: np.ndarray, slots: np.ndarray | None = None
    ) -> np.ndarray:
        """See `BatchBase.contact_flags`. The first call watches these pairs: from then on
        every call that moves the batch computes their flags on the device and copies them
        back with the rest (a task's predicate watches the same pairs after every action)."""
        key = side_a.tobytes() + side_b.tobytes()
        if self._sides is not None and self._sides[0] == key and "flags" in self._host:
            return self._host["flags"].astype(bool)
        with self._queued():
            a = wp.array(side_a.astype(np.int32), dtype=int)
            b = wp.array(side_b.astype(np.int32), dtype=int)
            self._sides = (key, a, b)
            self._flags = wp.zeros((self.n_slots, len(side_a)), dtype=int)
            self._readback.add("flags", self._flags)
            self._finish_queue()
        self._wait()
        return self._host["flags"].astype(bool)

    def _launch_contact_flags(self) -> None:
        assert self._sides is not None and self._flags is not None
        _, a, b = self._sides
        self._flags.zero_()
        c = self._d.contact
        wp.launch(
            wr.contact_flags,
            dim=self._d.naconmax,
            inputs=[self._d.nacon, c.geom, c.dist, c.worldid, a, b],
            outputs=[self._flags],
        )

    def memory_bytes(self) -> int:
        """Device memory held by the batch's model and data arrays."""
        seen: set[int] = set()
        total = 0

        def add(obj: object) -> None:
            nonlocal total
            for value in vars(obj).values():
                if isinstance(value, wp.array) and value.ptr not in seen and value.ptr:
                    seen.add(value.ptr)
                    total += value.capacity
                elif hasattr(value, "__dataclass_fields__") and not isinstance(value, type):
                    add(value)

        add(self._m)
        add(self._d)
        return total

    @on_device
    def close(self) -> None:
        # Everything queued on this stream has run before the graphs and their arenas go back
        # to the pool (frees wait for no non-blocking stream: see the module docstring).
        try:
            streams.wait(streams.record(self.stream))
        finally:
            self._graphs.clear()
