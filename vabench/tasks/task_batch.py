"""Episodes of one task family over one batch: seeded resets, the jitted predicate after every
action with latched flags and checkpoint progress kept per slot, and expert rollouts.

`TaskBatch` is what the seed screening, the replay CLI and the episode engine drive. The
predicate state (latched flags, checkpoint progress, success) is batch state: arrays over slots,
updated by one jitted, vmapped call of the family's `evaluate` after every `step`, and only for
slots that received an action (idle slots stay exactly as they were).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from vabench.sim_mjx.backends import Physics, as_physics, make_batch
from vabench.sim_mjx.interface import ActionResult, BatchBase, in_lanes
from vabench.sim_mjx.reset_cache import Settled, SettledCache, model_digest, settle_key
from vabench.tasks.base import (
    Evaluation,
    ObjectIndex,
    Sample,
    SlotState,
    Task,
    advance_progress,
    quat_to_mat,
)
from vabench.tasks.expert import ArmView, ExpertContext, ExpertFailed, View

DRIFT_WINDOW = 200  # FACTS: orientation drift measured over the last 200 observed steps
MAX_DRIFT_DEG = 3.0


@dataclass
class SettleReport:
    """The reset gate of one seed: finite poses, orientation drift in the last 200 steps."""

    seed: int
    finite: bool
    max_drift_deg: float
    infrastructure_error: str | None = None  # the simulator failed while settling (re-run)
    cached: bool = False  # the settled state came from the cache (reset_cache)

    @property
    def ok(self) -> bool:
        return (
            self.infrastructure_error is None
            and self.finite
            and self.max_drift_deg <= MAX_DRIFT_DEG
        )

    @property
    def reason(self) -> str | None:
        if self.infrastructure_error is not None:
            return self.infrastructure_error
        if not self.finite:
            return "non-finite pose after settling"
        if self.max_drift_deg > MAX_DRIFT_DEG:
            return f"object turned {self.max_drift_deg:.2f} deg in the last {DRIFT_WINDOW} steps"
        return None


@dataclass
class StepOutcome:
    """One slot's action and the predicate right after it."""

    result: ActionResult
    success: bool
    progress: int  # checkpoints reached so far
    checks: dict[str, bool] = field(default_factory=dict)


def _subtree_geoms(model: mujoco.MjModel, body_name: str) -> np.ndarray:
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body_name)
    if bid < 0:
        raise KeyError(f"contact side {body_name!r} is not a body of the scene")
    inside = np.zeros(model.nbody, bool)
    inside[bid] = True
    for b in range(bid + 1, model.nbody):  # bodies are ordered parents first
        inside[b] |= inside[model.body_parentid[b]]
    return inside[model.geom_bodyid] & (model.geom_contype | model.geom_conaffinity).astype(bool)


def contact_masks(task: Task, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(P, ngeom) masks of both sides of the task's watched contact pairs. A side is a body
    name (its whole subtree): an object, "table", or "<arm>_gripper" (palm and fingers)."""
    p = max(len(task.contact_pairs), 1)
    a = np.zeros((p, model.ngeom), bool)
    b = np.zeros((p, model.ngeom), bool)
    for i, (x, y) in enumerate(task.contact_pairs):
        a[i], b[i] = _subtree_geoms(model, x), _subtree_geoms(model, y)
    return a, b


def _evaluate_slot(
    task: Task, ix: ObjectIndex, s: SlotState, latched: jax.Array, progress: jax.Array
) -> tuple[Evaluation, jax.Array]:
    ev = task.evaluate(ix, s, latched)
    return ev, advance_progress(progress, ev.subgoals, ev.success)


class TaskBatch:
    """N episodes of one task family on a physics backend (`sim_mjx.backends.as_physics`): a
    `Physics`, or its name: "warp" (MuJoCo Warp), "mjx" (MJX on JAX) or "c" (C MuJoCo); the
    old "mjx" with impl "warp" or "jax" too.

    Resets read and fill the settled-state cache (`sim_mjx.reset_cache`; `cache=None` uses the
    default one, `SettledCache(None)` keeps it in memory only)."""

    def __init__(
        self,
        task: Task,
        n_slots: int,
        backend: str | Physics = "mjx",
        impl: str | None = None,
        cache: SettledCache | None = None,
        **batch_kwargs: Any,
    ):
        self.task = task
        self.physics = as_physics(backend, impl)
        # the two-part name records carry ("mjx", "warp"; "c", "-")
        self.backend, self.impl = self.physics.backend, self.physics.impl
        self.models = task.build_models()
        self.batch: BatchBase = make_batch(self.models, n_slots, self.physics, **batch_kwargs)
        self.cache = cache if cache is not None else SettledCache.default()
        self._digests = [model_digest(m) for m in self.models]
        self._seeds: dict[int, tuple[Sample, np.ndarray, str]] = {}
        self.n_slots = n_slots
        self.ix = ObjectIndex.from_model(self.models[0])
        self.side_a, self.side_b = contact_masks(task, self.models[0])
        n = self.batch.n_slots
        self.latched = np.zeros((n, len(task.latches)), bool)
        self.progress = np.zeros(n, np.int32)
        self.success = np.zeros(n, bool)
        self.steps = np.zeros(n, np.int32)
        self.init_qpos = np.array(self.batch.qpos())
        self._observed: tuple[np.ndarray, Any] | None = None  # (qpos, proprio) until it moves
        self.samples: list[Sample | None] = [None] * n
        self.seeds: list[int | None] = [None] * n
        # The predicate in the batch's lanes (see sim_mjx.interface.in_lanes): a slot's success
        # and checkpoints never depend on how many episodes share the batch.
        self._eval = jax.jit(
            in_lanes(functools.partial(_evaluate_slot, task, self.ix), 3, self.batch.lanes)
        )

    # -- episodes ---------------------------------------------------------------------------
    def sample(self, seed: int) -> Sample:
        """The seed's initial state (samplers are deterministic; some are slow, so memoised)."""
        return self._seed(seed)[0]

    def _seed(self, seed: int) -> tuple[Sample, np.ndarray, str]:
        """(sample, initial qpos, settled-state cache key) of a seed, memoised: a reset of
        many slots repeats few seeds (the seeds of a task times its runs)."""
        entry = self._seeds.get(seed)
        if entry is None:
            task = self.task
            sample = task.sample(seed)
            qpos = np.asarray(task.initial_qpos(self.models[sample.variant], sample), float)
            schedule = (task.settle_steps + task.observe_steps - DRIFT_WINDOW, DRIFT_WINDOW)
            key = settle_key(
                task.name, self.batch.backend_id, self._digests[sample.variant], qpos, schedule
            )
            entry = self._seeds[seed] = (sample, qpos, key)
        return entry

    def reset(self, slots: Sequence[int], seeds: Sequence[int]) -> list[SettleReport]:
        """Start episodes: place each seed's objects, settle, and gate on drift (FACTS). Seeds
        settled before on this backend and scene are copied from the cache instead."""
        slots, seeds = list(slots), list(seeds)
        if len(slots) != len(seeds):
            raise ValueError(f"{len(slots)} slots but {len(seeds)} seeds")
        entries = [self._seed(s) for s in seeds]
        settled: dict[int, Settled | None] = {
            s: self.cache.get(self._seed(s)[2]) for s in dict.fromkeys(seeds)
        }
        hit = [r for r, s in enumerate(seeds) if settled[s] is not None]
        miss = [r for r, s in enumerate(seeds) if settled[s] is None]
        if hit:
            self._load([slots[r] for r in hit], [seeds[r] for r in hit], settled)
        if miss:
            self._settle(
                [slots[r] for r in miss],
                np.stack([entries[r][1] for r in miss]),
                [entries[r][0].variant for r in miss],
            )
            failures = self.batch.failures()
            before, after = self._settle_before, self.batch.qpos()
            states = self.batch.get_state([slots[r] for r in miss])
            # a world the physics reset while settling is no settled scene: a non-finite
            # settle, as a NaN one is (deterministic on C MuJoCo: `reset_failed`, not re-run)
            diverged = self.batch.diverged_since_written([slots[r] for r in miss])
            for i, row in enumerate(miss):
                slot = slots[row]
                drift = max(
                    (
                        _angle_deg(before[i, a + 3 : a + 7], after[slot, a + 3 : a + 7])
                        for a in self.ix.adr.values()
                    ),
                    default=0.0,
                )
                st = Settled(
                    {f: v[i] for f, v in states.items()},
                    bool(np.isfinite(after[slot]).all()) and not diverged[i],
                    float(drift),
                )
                if failures[slot] is None:
                    self.cache.put(entries[row][2], st)
                settled[seeds[row]] = st  # later rows of this seed read the same report
        self._observed = None
        failures = self.batch.failures() if miss else [None] * self.batch.n_slots
        missed = set(miss)
        reports = []
        for row, (slot, seed) in enumerate(zip(slots, seeds, strict=True)):
            got = settled[seed]
            assert got is not None
            error = failures[slot] if row in missed else None
            reports.append(SettleReport(seed, got.finite, got.drift_deg, error, row not in missed))
            self.samples[slot], self.seeds[slot] = entries[row][0], seed
        self.init_qpos[slots] = self.batch.qpos()[slots]
        self.latched[slots] = False
        self.progress[slots] = 0
        self.success[slots] = False
        self.steps[slots] = 0
        return reports

    def _load(self, slots: list[int], seeds: list[int], settled: dict[int, Any]) -> None:
        """Put `slots` in their seeds' cached settled states, stacked per distinct seed."""
        distinct = list(dict.fromkeys(seeds))
        where = {s: i for i, s in enumerate(distinct)}
        pick = np.array([where[s] for s in seeds])
        fields = settled[distinct[0]].state
        state = {f: np.stack([settled[s].state[f] for s in distinct])[pick] for f in fields}
        self.batch.set_state(slots, state, [self._seed(s)[0].variant for s in seeds])

    def _settle(self, slots: list[int], qpos: np.ndarray, variants: list[int]) -> None:
        """Reset `slots` to `qpos` and run the settle schedule; keeps the qpos of these slots
        before the drift window in `_settle_before`."""
        task = self.task
        self.batch.reset(
            slots,
            qpos,
            settle_steps=task.settle_steps + task.observe_steps - DRIFT_WINDOW,
            variants=variants,
        )
        self._settle_before = self.batch.qpos()[slots]
        self.batch.hold(DRIFT_WINDOW, slots)

    def step(self, actions: Sequence[Any]) -> list[StepOutcome | None]:
        """One action per slot (None = idle); evaluates the predicate of every acting slot."""
        actions = list(actions) + [None] * (self.batch.n_slots - len(actions))
        results = self.batch.step(actions)
        self._observed = None
        acted = np.array([r is not None for r in results])
        if not acted.any():
            return [None] * self.n_slots
        ev, progress = self.evaluate(acted)
        self.latched[acted] = ev.latched[acted]
        self.progress[acted] = progress[acted]
        self.success[acted] = ev.success[acted]
        self.steps[acted] += 1
        out: list[StepOutcome | None] = []
        for slot in range(self.n_slots):
            res = results[slot]
            if res is None:
                out.append(None)
                continue
            checks = {k: bool(v[slot]) for k, v in ev.checks.items()}
            out.append(StepOutcome(res, bool(ev.success[slot]), int(self.progress[slot]), checks))
        return out

    def slot_states(self, slots: np.ndarray | None = None) -> SlotState:
        """Predicate inputs of every slot; contacts only for `slots` (bool mask) when given."""
        qpos, p = self.observe()
        return SlotState(
            qpos=jnp.asarray(qpos),
            init_qpos=jnp.asarray(self.init_qpos),
            grip_open=jnp.asarray(self.batch.grip_open()),
            contacts=jnp.asarray(self.batch.contact_flags(self.side_a, self.side_b, slots)),
            gc=jnp.asarray(p.gc),
            rot=jnp.asarray(p.rot),
            fingers=jnp.asarray(p.fingers),
        )

    def evaluate(self, slots: np.ndarray | None = None) -> tuple[Evaluation, np.ndarray]:
        """The predicate of every slot at its current state (host arrays), with the latches
        and progress it would produce; does not commit them. With `slots` (bool mask) only
        those rows are meaningful."""
        ev, progress = self._eval(
            self.slot_states(slots), jnp.asarray(self.latched), jnp.asarray(self.progress)
        )
        return jax.device_get(ev), np.asarray(progress)

    def observe(self) -> tuple[np.ndarray, Any]:
        """qpos and proprioception of every slot, fetched once per state change: the predicate
        and the experts' views read the same state after each step."""
        if self._observed is None:
            self._observed = (self.batch.qpos(), self.batch.proprio())
        return self._observed

    def checkpoint(self, slot: int) -> str | None:
        """Name of the last checkpoint the slot reached (None before the first)."""
        p = int(self.progress[slot])
        return self.task.checkpoints[p - 1] if p > 0 else None

    # -- evaluator-only views ---------------------------------------------------------------
    def views(self, slots: Sequence[int]) -> dict[int, View]:
        """Evaluator-only views of `slots` (for experts and debugging; never for a model)."""
        qpos_all, p = self.observe()
        out = {}
        for slot in slots:
            qpos = qpos_all[slot]
            objects = {
                name: (qpos[a : a + 3].copy(), np.asarray(quat_to_mat(qpos[a + 3 : a + 7])))
                for name, a in self.ix.adr.items()
            }
            arms = {
                arm: ArmView(
                    gc=np.asarray(p.gc[slot, i]),
                    rot=np.asarray(p.rot[slot, i]),
                    is_open=bool(p.is_open[slot, i]),
                    fingers=np.asarray(p.fingers[slot, i]),
                )
                for i, arm in enumerate(self.batch.arms)
            }
            out[slot] = View(
                objects=objects,
                init={n: self.init_qpos[slot, a : a + 3].copy() for n, a in self.ix.adr.items()},
                arms=arms,
                last=None,
                step=int(self.steps[slot]),
            )
        return out


@dataclass
class ExpertEpisode:
    """The record of one expert run: every action with its outcome, and how it ended."""

    seed: int
    settle: SettleReport
    success: bool = False
    steps: int = 0
    end: str = "not run"  # success | budget | expert gave up: ... | rejected at reset: ...
    actions: list[dict[str, Any]] = field(default_factory=list)
    last_checks: dict[str, bool] = field(default_factory=dict)  # the predicate's terms at the end

    def to_json(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "success": self.success,
            "steps": self.steps,
            "end": self.end,
            "max_drift_deg": round(self.settle.max_drift_deg, 4),
            "last_checks": self.last_checks,
            "actions": self.actions,
        }


def run_experts(
    tb: TaskBatch,
    seeds: Sequence[int],
    slots: Sequence[int] | None = None,
    max_steps: int | None = None,
) -> list[ExpertEpisode]:
    """Reset `slots` (default: the first len(seeds)) to `seeds` and run the family's expert in
    every slot in lockstep, one batched step per round, until each succeeds, gives up, or
    exhausts the step budget (or `max_steps`, ending "stopped"). Seeds failing the reset gate
    are not run."""
    slots = list(range(len(seeds))) if slots is None else list(slots)
    if len(seeds) > tb.n_slots or len(slots) != len(seeds):
        raise ValueError(f"{len(seeds)} seeds for {len(slots)} slots of {tb.n_slots}")
    reports = tb.reset(slots, seeds)
    episodes = {
        slot: ExpertEpisode(seed, rep)
        for slot, seed, rep in zip(slots, seeds, reports, strict=True)
    }
    views = tb.views(slots)
    scripts: dict[int, Any] = {}
    contexts: dict[int, ExpertContext] = {}
    pending: dict[int, dict[str, Any]] = {}

    def advance(slot: int) -> None:
        ep = episodes[slot]
        try:
            pending[slot] = next(scripts[slot])
        except StopIteration:
            ep.end = "expert finished without success"
        except ExpertFailed as err:
            ep.end = f"expert gave up: {err}"
        else:
            return
        scripts.pop(slot)

    for slot in slots:
        ep = episodes[slot]
        if not ep.settle.ok:
            ep.end = f"rejected at reset: {ep.settle.reason}"
            continue
        sample = tb.samples[slot]
        assert sample is not None
        contexts[slot] = ExpertContext(tb.task.arms, views[slot])
        scripts[slot] = iter(tb.task.expert(sample, contexts[slot]))
        advance(slot)

    while scripts:
        actions: list[Any] = [None] * tb.n_slots
        for slot in scripts:
            actions[slot] = pending[slot]
        outcomes = tb.step(actions)
        views = tb.views(list(scripts))
        for slot in list(scripts):
            out = outcomes[slot]
            assert out is not None
            ep = episodes[slot]
            ep.steps += 1
            ep.last_checks = out.checks
            ep.actions.append(
                {
                    "action": pending[slot],
                    "valid": out.result.valid,
                    "planner_success": out.result.planner_success,
                    "progress": out.progress,
                    "success": out.success,
                }
            )
            if out.success:
                ep.success, ep.end = True, "success"
                scripts.pop(slot)
                continue
            if ep.steps >= tb.task.step_budget:
                ep.end = "budget"
                scripts.pop(slot)
                continue
            if max_steps is not None and ep.steps >= max_steps:
                ep.end = f"stopped after {max_steps} steps"
                scripts.pop(slot)
                continue
            view = views[slot]
            view.last = out.result
            contexts[slot].view = view
            advance(slot)
    return [episodes[slot] for slot in slots]


def _angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    q1 = q1 / np.linalg.norm(q1)
    q2 = q2 / np.linalg.norm(q2)
    d = min(1.0, abs(float(np.dot(q1, q2))))
    return float(np.degrees(2.0 * np.arccos(d)))
