"""The Warp backend: N slots of one scene on MuJoCo Warp, one captured CUDA graph per action.

One agent action for the whole batch is one graph launch: plan every slot (closed-form IK over
the waypoints, `warp_control.plan_kernel`), then ACTION_SECONDS of physics substeps (joint
references of substep k written by `ctrl_kernel`, then `mujoco_warp.step`), then the merge
(slots that were idle, invalid or whose plan failed get their saved state back bit for bit),
then the observation (kinematics and collision at the final state for the predicates' contact
flags, and the proprioception). Nothing returns to the host until the graph ends. Settling
(`hold`) is a graph of HOLD_CHUNK steps with the same merge.

On the CPU device (tests) the same kernels run without a graph: Warp's CPU backend executes
every thread of a launch in order, so a slot's trajectory does not depend on the batch size,
its index or its neighbours. On a GPU, MuJoCo Warp's contact and constraint ordering uses
atomics unless `deterministic` asks for its stable orderings (slower; see docs/PERFORMANCE.md).

Buffers (contacts, constraint rows) are sized from the scene (`warp_model.capacity`); a slot
whose world overflows them gets an infrastructure error (`failure_text`), never silent wrong
physics.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from vabench.sim_mjx import warp_control as wc
from vabench.sim_mjx import warp_kinematics as wk
from vabench.sim_mjx import warp_layout as wl
from vabench.sim_mjx.actions import CommandRows
from vabench.sim_mjx.backends import device_lock
from vabench.sim_mjx.interface import BatchBase, StepInfo
from vabench.sim_mjx.layout import Proprio
from vabench.sim_mjx.scene import home_qpos
from vabench.sim_mjx.variants import check_same_structure
from vabench.sim_mjx.warp_model import FAILURE_BITS, WarpModel, capacity, failure_text

HOLD_CHUNK = 100  # physics steps per settle graph (the reset gate holds 2,300 then 200)
LOOPS = ("per_step", "unrolled")
"""How graphs hold an action's substeps. per_step (default): a graph of one substep (references,
mujoco_warp.step, counter), launched n times between a graph before and one after; launches
are asynchronous, so nothing returns to the host between substeps. unrolled: one graph for the
whole action. Measured on an H100 (docs/PERFORMANCE.md) both step equally fast, but unrolled
costs 3.5-5 s of capture per batch shape and each distinct hold length. A device-side while
loop (one small graph) is not possible: MuJoCo Warp allocates scratch arrays inside its step,
and CUDA graphs allow no allocation inside a conditional body."""
PREDICATE_LANES = 32  # width of the JAX predicate and proprio vmaps (see interface.in_lanes)


@wp.kernel
def _save_rows(src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)):
    w, j = wp.tid()
    dst[w, j] = src[w, j]


@wp.kernel
def _restore_rows(
    keep: wp.array(dtype=int), saved: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)
):
    """Rows of worlds whose physics must not advance get their saved values back."""
    w, j = wp.tid()
    if keep[w] == 0:
        dst[w, j] = saved[w, j]


@wp.kernel
def _restore_time(
    keep: wp.array(dtype=int), saved: wp.array(dtype=float), t: wp.array(dtype=float)
):
    w = wp.tid()
    if keep[w] == 0:
        t[w] = saved[w]


@wp.kernel
def _count(k: wp.array(dtype=int)):
    """One more substep done (the references of the next one read k)."""
    k[0] = k[0] + 1


@wp.kernel
def _finish_action(
    go: wp.array(dtype=int),
    cmd_grip: wp.array2d(dtype=int),
    overflow: wp.array(dtype=int),
    failure_bits: int,
    grip_open: wp.array2d(dtype=int),
    failed: wp.array(dtype=int),
):
    """Commit the gripper command of slots that moved; record overflow of those slots."""
    w, a = wp.tid()
    if go[w] == 0:
        return
    g = cmd_grip[w, a]
    if g >= 0:
        grip_open[w, a] = wp.where(g == 1, 1, 0)
    if a == 0:
        failed[w] = overflow[w] & failure_bits


@wp.kernel
def _finish_hold(
    mask: wp.array(dtype=int),
    overflow: wp.array(dtype=int),
    failure_bits: int,
    failed: wp.array(dtype=int),
):
    w = wp.tid()
    if mask[w] != 0:
        failed[w] = overflow[w] & failure_bits


@wp.kernel
def _scatter_rows(
    idx: wp.array(dtype=int), rows: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)
):
    i, j = wp.tid()
    dst[idx[i], j] = rows[i, j]


@wp.kernel
def _gather_rows(
    idx: wp.array(dtype=int), src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)
):
    i, j = wp.tid()
    dst[i, j] = src[idx[i], j]


@wp.kernel
def _scatter_int_rows(
    idx: wp.array(dtype=int), rows: wp.array2d(dtype=int), dst: wp.array2d(dtype=int)
):
    i, j = wp.tid()
    dst[idx[i], j] = rows[i, j]


@wp.kernel
def _scatter(idx: wp.array(dtype=int), values: wp.array(dtype=float), dst: wp.array(dtype=float)):
    i = wp.tid()
    dst[idx[i]] = values[i]


@wp.kernel
def _contact_flags(
    nacon: wp.array(dtype=int),
    geom: wp.array(dtype=wp.vec2i),
    dist: wp.array(dtype=float),
    worldid: wp.array(dtype=int),
    side_a: wp.array2d(dtype=int),
    side_b: wp.array2d(dtype=int),
    flags: wp.array2d(dtype=int),
):
    """flags[w, p] = 1 when a touching contact (dist <= 0) of world w joins a geom of side_a[p]
    and one of side_b[p] (either order). Every writer writes 1: no race matters."""
    c = wp.tid()
    if c >= nacon[0] or dist[c] > 0.0:
        return
    g1, g2 = geom[c][0], geom[c][1]
    if g1 < 0 or g2 < 0:
        return
    w = worldid[c]
    for p in range(side_a.shape[0]):
        hit = (side_a[p, g1] != 0 and side_b[p, g2] != 0) or (
            side_a[p, g2] != 0 and side_b[p, g1] != 0
        )
        if hit:
            flags[w, p] = 1


class WarpBatch(BatchBase):
    """N slots of one scene on MuJoCo Warp; one agent action per slot per `step` call.

    `device`: a Warp device ("cuda:0" by default; "cpu" runs the same kernels on the CPU, for
    tests). `nconmax` / `njmax`: per-world contact and constraint-row capacity (default: sized
    from the scene). `deterministic`: MuJoCo Warp's stable contact and constraint orderings on
    GPUs (bit-reproducible, slower). `graphs`: capture CUDA graphs (GPU only; off = launch
    kernel by kernel, for debugging). `loop`: see LOOPS.
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
        loop: str = "per_step",
    ):
        self._setup(model, n_slots, PREDICATE_LANES)
        check_same_structure(self.models)
        m0 = self.model
        self.device = wp.get_device(device or "cuda:0")
        self.lock = device_lock(str(self.device))
        self.capacity = capacity(m0, nconmax, njmax)
        self.backend_id = f"mjx-warp-{mjw.__version__}-{mujoco.__version__}-{self.device.arch}"
        self._graphs_on = graphs and self.device.is_cuda
        if loop not in LOOPS:
            raise ValueError(f"loop must be one of {LOOPS}, got {loop!r}")
        self.loop = loop
        self._graphs: dict[str, wp.Graph] = {}
        n, arms = n_slots, len(self.arms)
        with wp.ScopedDevice(self.device):
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
            self._grip_open = wp.ones((n, arms), dtype=int)
            self._obs = wl.ProprioBuffers.allocate(n, arms, self.device)
            self._flags: wp.array | None = None
            self._sides: tuple[bytes, wp.array, wp.array] | None = None
            d = self._d
            self._state2d = [d.qpos, d.qvel, d.ctrl, d.qacc_warmstart]
            if m0.na:
                self._state2d.append(d.act)
            self._saved2d = [wp.empty_like(a) for a in self._state2d]
            self._saved_time = wp.empty_like(d.time)
        self._variant = np.zeros(n, np.int32)
        self._init_qpos = np.zeros((n, m0.nq))
        self._host: dict[str, np.ndarray] = {}
        self.reset(range(n), np.broadcast_to(home_qpos(m0), (n, m0.nq)))

    # -- graphs -----------------------------------------------------------------------------
    def _graph(self, name: str, body: Callable[[], None]) -> None:
        """Launch `body` (device work only) as the CUDA graph `name`, captured on first use."""
        graph = self._graphs.get(name)
        if graph is None:
            with wp.ScopedCapture(device=self.device) as capture:
                body()
            graph = self._graphs[name] = capture.graph
        wp.capture_launch(graph)

    def _physics(self, name: str, pre: Callable, substep: Callable, post: Callable, n: int) -> None:
        """pre, n x substep, post: as graphs (see LOOPS) or, on the CPU or with graphs off, as
        plain launches."""
        self._host.clear()
        with self.lock, wp.ScopedDevice(self.device):
            if not self._graphs_on:
                pre()
                for _ in range(n):
                    substep()
                post()
            elif self.loop == "per_step":
                self._graph(f"{name}.pre", pre)
                for _ in range(n):
                    self._graph(f"{name}.step", substep)
                self._graph(f"{name}.post", post)
            else:

                def body() -> None:
                    pre()
                    for _ in range(n):
                        substep()
                    post()

                self._graph(f"{name}.{n}", body)

    def _start_loop(self) -> None:
        self._k.zero_()
        self._d.overflow.zero_()

    def _save(self) -> None:
        for src, dst in zip(self._state2d, self._saved2d, strict=True):
            if src.shape[1]:
                wp.launch(_save_rows, dim=src.shape, inputs=[src, dst])
        wp.copy(self._saved_time, self._d.time)

    def _restore(self, keep: wp.array) -> None:
        for dst, saved in zip(self._state2d, self._saved2d, strict=True):
            if dst.shape[1]:
                wp.launch(_restore_rows, dim=dst.shape, inputs=[keep, saved, dst])
        wp.launch(_restore_time, dim=self.n_slots, inputs=[keep, self._saved_time, self._d.time])

    def _observe(self) -> None:
        """Derived quantities at the final state: body poses and contacts (the predicates'
        contact flags read them) and the proprioception."""
        mjw.kinematics(self._m, self._d)
        mjw.collision(self._m, self._d)
        wl.launch_proprio(self._geoms, self._d.qpos, self._idx, self._obs, self._grip_open)

    def _step_physics(self, with_ctrl: bool) -> Callable[[], None]:
        def substep() -> None:
            if with_ctrl:
                wc.launch_ctrl(self._k, self.n_substeps, self._plan, self._idx, self._d.ctrl)
            mjw.step(self._m, self._d)
            wp.launch(_count, dim=1, inputs=[self._k])

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
        )
        self._save()
        self._start_loop()

    def _action_post(self) -> None:
        self._restore(self._go)
        wp.launch(
            _finish_action,
            dim=(self.n_slots, len(self.arms)),
            inputs=[self._go, self._cmd_grip, self._d.overflow, FAILURE_BITS],
            outputs=[self._grip_open, self._failed],
        )
        self._observe()

    def _hold_pre(self) -> None:
        self._save()
        self._start_loop()

    def _hold_post(self) -> None:
        self._restore(self._mask)
        wp.launch(
            _finish_hold,
            dim=self.n_slots,
            inputs=[self._mask, self._d.overflow, FAILURE_BITS],
            outputs=[self._failed],
        )
        self._observe()

    # -- the interface ----------------------------------------------------------------------
    def _execute(self, rows: CommandRows) -> StepInfo:
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
        )
        failed = self._failed.numpy()
        failure = [failure_text(int(b), self.capacity) if b else None for b in failed]
        return StepInfo(
            executed=self._go.numpy().astype(bool),
            planner_success=self._ok.numpy().astype(bool),
            clipped=self._plan.clipped.numpy().astype(bool),
            executed_m=self._plan.executed_m.numpy(),
            failure=failure if failed.any() else None,
        )

    def hold(self, n_steps: int, slots: Sequence[int] | None = None) -> None:
        mask = np.zeros(self.n_slots, np.int32)
        mask[list(range(self.n_slots)) if slots is None else list(slots)] = 1
        self._mask.assign(mask)
        self._failed.zero_()
        chunks = [HOLD_CHUNK] * (n_steps // HOLD_CHUNK)
        if n_steps % HOLD_CHUNK:
            chunks.append(n_steps % HOLD_CHUNK)
        failed = np.zeros(self.n_slots, np.int32)
        for k in chunks:
            self._physics("hold", self._hold_pre, self._step_physics(False), self._hold_post, k)
            failed |= self._failed.numpy()
        self._hold_failed = failed

    def failures(self) -> list[str | None]:
        """Slots whose last hold (reset settling) overflowed a buffer."""
        failed = getattr(self, "_hold_failed", np.zeros(self.n_slots, np.int32))
        return [failure_text(int(b), self.capacity) if b else None for b in failed]

    def set_state(
        self, slots: Sequence[int], state: dict[str, np.ndarray], variants: Sequence[int]
    ) -> None:
        slots = list(slots)
        self._check_state(slots, state)
        var = self._check_variants(slots, variants)
        if not slots:
            return
        d = self._d
        with self.lock, wp.ScopedDevice(self.device):
            idx = wp.array(np.asarray(slots, np.int32), dtype=int)
            for name, dst in (
                ("qpos", d.qpos),
                ("qvel", d.qvel),
                ("ctrl", d.ctrl),
                ("warmstart", d.qacc_warmstart),
                ("act", d.act),
            ):
                if dst.shape[1]:
                    rows = wp.array(np.asarray(state[name], np.float32), dtype=float)
                    wp.launch(_scatter_rows, dim=rows.shape, inputs=[idx, rows, dst])
            times = wp.array(np.asarray(state["time"], np.float32), dtype=float)
            wp.launch(_scatter, dim=len(slots), inputs=[idx, times, d.time])
            grips = wp.array(np.asarray(state["grip_open"], np.int32), dtype=int)
            wp.launch(_scatter_int_rows, dim=grips.shape, inputs=[idx, grips, self._grip_open])
            self._variant[slots] = var
            self._wm.assign(self._variant)
        self._init_qpos[slots] = state["qpos"]
        self._host.clear()
        with self.lock, wp.ScopedDevice(self.device):
            if self._graphs_on:
                self._graph("observe", self._observe)
            else:
                self._observe()

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
        batch's device), queued behind every action already queued: the renderer reads the
        state where the physics left it, without a trip through the host."""
        with self.lock, wp.ScopedDevice(self.device):
            wp.launch(
                _gather_rows, dim=(slots.shape[0], dst.shape[1]), inputs=[slots, self._d.qpos, dst]
            )

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
        key = side_a.tobytes() + side_b.tobytes()
        with wp.ScopedDevice(self.device):
            if self._sides is None or self._sides[0] != key:
                a = wp.array(side_a.astype(np.int32), dtype=int)
                b = wp.array(side_b.astype(np.int32), dtype=int)
                self._sides = (key, a, b)
                self._flags = wp.zeros((self.n_slots, len(side_a)), dtype=int)
            _, a, b = self._sides
            assert self._flags is not None
            self._flags.zero_()
            c = self._d.contact
            wp.launch(
                _contact_flags,
                dim=self._d.naconmax,
                inputs=[self._d.nacon, c.geom, c.dist, c.worldid, a, b],
                outputs=[self._flags],
            )
            return self._flags.numpy().astype(bool)

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

    def close(self) -> None:
        self._graphs.clear()
