"""The episode engine: the observe-decide-act loop of one episode, many at once.

Spec: FACTS.md ("Model-facing protocol", "Observation sent each decision") and the paper's
harness appendix. One episode:

1. takes a slot of the task's `SimService`, resets its seed there (batched with other resets),
   and puts the camera at the head view "center_high" (active) or renders the five fixed
   views (passive);
2. per environment step: sends the observation (text + the clean image(s), rendered through
   the `RenderService`) and asks the model for one decision, then
   - a reply that is no valid decision (`vabench.agent.replies`: malformed or invalid JSON, a
     refusal, a reply cut at the output limit, an empty or reasoning-only reply, a function
     call that converts into no decision) gets a repair turn that says what happened, plus
     the current observation; it costs no step. At most `MAX_REPAIRS_PER_DECISION` (2)
     repairs a decision: the next rejection ends the episode as a scored failure whose stop
     reason names it (`refused`, `truncated`, else `invalid_output`), as in the benchmark's
     reference harness (PROTOCOL_FACTS 3.5);
   - a tool call (`geometry.verify`, `camera.history`) is answered in the thread and the
     model is asked again; at most `MAX_TOOL_ROUND_TRIPS` model calls per decision;
   - a camera action moves only the camera (new image, one step of the budget);
   - a robot action goes to the simulator (batched with the other episodes' actions, one
     step of the budget); the success predicate and checkpoints come back with it;
   - stop ends the episode;
3. ends on success, stop, budget exhausted, too many invalid replies or round trips, a
   context the model cannot hold, or an infrastructure error (recorded as such: never a
   success or a failure).

A request the endpoint rejects because it exceeds the model's context window
(`RequestRejected.context_exceeded`) compacts the conversation at once and is sent again,
once; rejected again (or with nothing left to compact) the episode ends as a scored failure,
`context_exceeded`: an episode that the model's own context cannot hold is that model's
failure (the paper's success rate averages over every seed). The window the compaction
follows is the model's `context_window` (`models[i].context_window`), or the engine's
`ContextLimits.window_tokens` where that is smaller.

Only what `vabench.agent.visibility` lists reaches the model: the robot state goes through
`filter_proprio`; object poses, seeds, contacts, checker state and camera numbers stay on this
side (the snapshot's evaluator fields feed only the renderer and the camera model).
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from vabench import protocol as P
from vabench.agent.conversation import CompactionEvent, ContextLimits, Conversation
from vabench.agent.generation import request_options
from vabench.agent.observation import (
    PASSIVE_VIEW_NAME,
    PASSIVE_VIEWS,
    ActionFeedback,
    observation_text,
)
from vabench.agent.prompts import system_prompt
from vabench.agent.records import EpisodeRecorder, EpisodeResult
from vabench.agent.replies import ReplyRejected, history_text, read_decision, stop_reason_of
from vabench.agent.services import TaskServices
from vabench.agent.session import SessionEnd, Spend, reply_fields
from vabench.agent.simulation import SlotSnapshot
from vabench.agent.spec import EpisodeSpec
from vabench.agent.tools import camera_history, geometry_result
from vabench.llm_pool.errors import InfrastructureError, RequestRejected
from vabench.llm_pool.messages import ChatRequest, CompletionResult, Image
from vabench.protocol.version import PROTOCOL_VERSION
from vabench.render import camera as cam
from vabench.render.images import RenderError, RenderItem
from vabench.sim_mjx.interface import (
    DeviceFailure,
    SimulationError,
    device_failure,
    watched_devices,
)


@dataclass
class _Counts:
    """What the episode did, under the names of `EpisodeResult`'s fields."""

    steps_used: int = 0
    robot_actions: int = 0
    camera_actions: int = 0
    invalid_outputs: int = 0
    refusals: int = 0
    truncations: int = 0
    empty_replies: int = 0
    invalid_actions: int = 0
    tool_calls: int = 0


class Episode:
    """One episode's state and loop; `await Episode(spec, services).run()`."""

    def __init__(self, spec: EpisodeSpec, services: TaskServices):
        if spec.protocol not in ("active", "passive"):
            raise ValueError(f"protocol must be 'active' or 'passive', got {spec.protocol!r}")
        self.spec = spec
        self.svc = services
        self.task = services.sim.task
        if spec.task != self.task.name:
            raise ValueError(f"episode of {spec.task!r} on the services of {self.task.name!r}")
        self.arms = tuple(self.task.arms)
        self.budget = self.task.step_budget if spec.step_budget is None else spec.step_budget
        if self.budget < 1:
            raise ValueError(f"step_budget must be >= 1, got {spec.step_budget}")
        tools = P.available_tools(demonstration=False)
        if spec.protocol == "passive":  # passive requests carry only the current bundle
            tools = tuple(t for t in tools if t != "camera.history")
        self.ctx = P.DecisionContext(self.arms, spec.protocol, tools)
        self.available = P.available_actions(self.arms, spec.protocol, tools)
        endpoint = services.llm.endpoint(spec.model).config
        self.output_limit = endpoint.generation.merge(
            services.settings.generation
        ).resolved_max_output_tokens
        self.conv = Conversation(
            system_prompt(self.arms, spec.protocol, list(tools), task=spec.task),
            protocol=spec.protocol,
            limits=model_limits(services.settings.limits, endpoint.context_window),
        )
        self.options = request_options(endpoint, services.settings.generation)
        self.rec = EpisodeRecorder(spec.out_dir, frames=spec.frames)
        self.counts = _Counts()
        self.spend = Spend()  # every model call, compaction summaries included
        self.kinds: list[str] = []  # decision kinds executed, for the camera-chain rule
        self.executed: list[str] = []  # labels shown to the model
        self.frames: dict[int, Image] = {}  # observation step -> the image the model saw
        self.feedback = ActionFeedback()
        self.camera: cam.CameraPose | None = None
        self.snapshot: SlotSnapshot | None = None
        self.success = False
        self._last_summary: CompletionResult | None = None
        self.t0 = time.time()

    # -- the loop ---------------------------------------------------------------------------
    async def run(self) -> EpisodeResult:
        spec = self.spec
        self.rec.event(
            "episode_start",
            task=spec.task,
            seed=spec.seed,
            model=spec.model,
            protocol=spec.protocol,
            run=spec.run,
            step_budget=self.budget,
            arms=list(self.arms),
            tools=list(self.ctx.tools),
            protocol_version=PROTOCOL_VERSION,
            request_options=self.options.model_dump(exclude_none=True),
            frames=spec.frames,
        )
        slot = self.svc.sim.acquire()
        try:
            await self._reset(slot)
            while self.counts.steps_used < self.budget:
                started = time.monotonic()
                await self._decide_and_act(slot)
                if self.svc.on_decision is not None:
                    self.svc.on_decision(self.spec, time.monotonic() - started)
            raise SessionEnd("failure", "budget_exhausted")
        except SessionEnd as end:
            return self._finish(end.status, end.reason, end.error)
        except InfrastructureError as err:
            self.rec.event(
                "llm_failure",
                step=self.counts.steps_used + 1,
                attempts=err.attempts,
                elapsed_s=round(err.elapsed_s, 3),
                failures=list(err.failures),
            )
            return self._finish("infrastructure_error", "infrastructure_error", str(err))
        except DeviceFailure:  # the process's GPU, not this episode: no result; sweep stops
            raise
        except (RenderError, SimulationError) as err:
            await _raise_if_device_failed(err)
            return self._finish("infrastructure_error", "infrastructure_error", str(err))
        except RequestRejected as err:
            if err.fatal:  # the endpoint's refusal, not this episode's: no result; sweep stops
                step = self.counts.steps_used + 1
                self.rec.event("endpoint_refused", step=step, status=err.status, error=str(err))
                raise
            return self._finish("error", "request_rejected", f"{err.kind}: {err}")
        except Exception as err:  # a harness bug: recorded, never scored
            await _raise_if_device_failed(err)
            self.rec.event("harness_error", error=f"{type(err).__name__}: {err}")
            return self._finish("error", "harness_error", f"{type(err).__name__}: {err}")
        finally:
            self.svc.sim.release(slot)
            self.rec.close()

    async def _reset(self, slot: int) -> None:
        reply = await self.svc.sim.reset(slot, self.spec.seed)
        assert reply.report is not None
        self.rec.event(
            "reset",
            slot=slot,
            ok=reply.report.ok,
            reason=reply.report.reason,
            drift_deg=round(reply.report.max_drift_deg, 4),
            objects=reply.snapshot.objects,  # evaluator-only: the viewer's marked panel
        )
        if reply.report.infrastructure_error is not None:
            raise SimulationError(reply.report.infrastructure_error)
        if not reply.report.ok:
            raise SessionEnd("error", "reset_failed", reply.report.reason)
        self.snapshot = reply.snapshot
        if self.spec.protocol == "active":
            self.camera = cam.head_view(reply.snapshot.gcs, self.arms)

    async def _decide_and_act(self, slot: int) -> None:
        step = self.counts.steps_used + 1
        text, images = await self._observe(step)
        self.conv.add_observation(text, images, step)
        decision = await self._decide(step, text)
        label = P.decision_label(decision)
        self.rec.event(
            "decision",
            step=step,
            kind=decision.kind,
            label=label,
            reason=decision.reason,
            decision=decision.model_dump(exclude_none=True),
        )
        if isinstance(decision, P.Stop):
            raise SessionEnd("failure", "model_stop")
        self.counts.steps_used += 1
        self.kinds.append(decision.kind)
        self.executed.append(label)
        if isinstance(decision, P.CameraAction):
            self._camera_action(step, decision)
        else:
            await self._robot_action(slot, step, decision)

    # -- observing ----------------------------------------------------------------------------
    async def _observe(self, step: int) -> tuple[str, Image | dict[str, Image]]:
        snap = self.snapshot
        assert snap is not None
        if self.spec.protocol == "active":
            assert self.camera is not None
            poses, view = [self.camera], self.camera.label
        else:
            poses, view = cam.passive_bundle(snap.gcs, self.arms), PASSIVE_VIEW_NAME
        jpegs = await self.svc.render.render(
            [RenderItem(snap.qpos, snap.variant, p, slot=snap.slot) for p in poses]
        )
        text = observation_text(
            step=step,
            step_budget=self.budget,
            instruction=self.task.instruction,
            proprio=snap.proprio,
            arms=self.arms,
            feedback=self.feedback,
            executed_actions=self.executed,
            demonstration_summary=self.spec.demonstration_summary,
            available_actions=self.available,
            history_steps=list(self.frames) if "camera.history" in self.ctx.tools else None,
        )
        if self.spec.protocol == "active":
            image = Image(jpegs[0])
            self.frames[step] = image
            frame = self.rec.frame(step, jpegs[0])
            self.rec.event("observation", step=step, view=view, frames=[frame])
            return text, image
        # Keyed by the plain view name: in dual-arm tasks the camera names its poses after
        # their target ("both_topdown"), which is not a passive view name.
        views = [_passive_view(p.view) for p in poses]
        bundle = {v: Image(j) for v, j in zip(views, jpegs, strict=True)}
        files = [
            self.rec.frame(step, j, v, i) for i, (v, j) in enumerate(zip(views, jpegs, strict=True))
        ]
        self.rec.event("observation", step=step, view="passive_bundle", frames=files)
        return text, bundle

    # -- deciding -----------------------------------------------------------------------------
    async def _call_model(self, step: int) -> CompletionResult:
        await self._log_compaction(step, await self.conv.compact_if_needed(self._summarize))
        try:
            result = await self._request(step)
        except RequestRejected as err:
            if not err.context_exceeded:
                raise
            self.rec.event("context_exceeded", step=step, status=err.status, error=str(err))
            try:
                event = await self.conv.compact(self._summarize)
            except RequestRejected as again:  # the summary request did not fit either
                if not again.context_exceeded:
                    raise
                event = None
            if event is None:
                raise SessionEnd(
                    "failure", "context_exceeded", f"nothing left to compact: {err}"
                ) from None
            await self._log_compaction(step, event)
            try:
                result = await self._request(step)
            except RequestRejected as again:
                if not again.context_exceeded:
                    raise
                raise SessionEnd(
                    "failure", "context_exceeded", f"after one compaction: {again}"
                ) from None
        self.spend.add(result)
        self.conv.add_reply(history_text(result))
        self.rec.event(
            "reply",
            step=step,
            **reply_fields(result),
            raw_finish_reason=result.raw_finish_reason,
            reasoning=result.reasoning,
            function_calls=[dataclasses.asdict(c) for c in result.function_calls],
            failures=list(result.failures),
        )
        return result

    async def _request(self, step: int) -> CompletionResult:
        request = self.conv.request(self.options)
        self.rec.event(
            "request",
            step=step,
            turns=len(request.turns),
            images=len(request.images),
            est_tokens=self.conv.estimate_tokens(),
        )
        return await self.svc.llm.complete(self.spec.model, request)

    async def _log_compaction(self, step: int, event: CompactionEvent | None) -> None:
        if event is not None:
            # The event's own record names its type and step; the log line takes both from
            # here (the step being decided), the rest as it is.
            fields = {k: v for k, v in event.record().items() if k not in ("event", "step")}
            # The summary was a model call: its usage and cost are logged with it, so the
            # events account for every call the result counts.
            summary = self._last_summary
            assert summary is not None
            self.rec.event(
                "compaction",
                step=step,
                **fields,
                usage=dataclasses.asdict(summary.usage),
                cost_usd=summary.cost_usd,
                attempts=summary.attempts,
            )

    async def _summarize(self, request: ChatRequest) -> str:
        result = await self.svc.llm.complete(self.spec.model, request)
        self.spend.add(result)
        self._last_summary = result
        return result.text

    async def _decide(self, step: int, text: str) -> P.Decision:
        repairs = 0
        for _ in range(P.MAX_TOOL_ROUND_TRIPS):
            reply = await self._call_model(step)
            ctx = dataclasses.replace(self.ctx, camera_chain=P.camera_chain_length(self.kinds))
            try:
                decision = read_decision(reply, ctx, self.output_limit)
            except ReplyRejected as err:
                self._count_rejection(err)
                self.rec.event(
                    "rejection",
                    step=step,
                    kind=err.kind,
                    field=err.field,
                    message=str(err),
                    repair=repairs + 1,
                )
                if repairs >= P.MAX_REPAIRS_PER_DECISION:
                    raise SessionEnd("failure", stop_reason_of(err.kind), str(err)) from None
                repairs += 1
                self.conv.add_repair(str(err), text, step)
                continue
            if isinstance(decision, P.ToolCall):
                self._tool(step, decision)
                continue
            return decision
        raise SessionEnd(
            "failure",
            "round_trip_limit",
            f"{P.MAX_TOOL_ROUND_TRIPS} model calls without an environment decision",
        )

    def _count_rejection(self, err: ReplyRejected) -> None:
        self.counts.invalid_outputs += 1
        self.counts.refusals += err.kind == "refusal"
        self.counts.truncations += err.kind == "truncation"
        self.counts.empty_replies += err.empty

    def _tool(self, step: int, call: P.ToolCall) -> None:
        self.counts.tool_calls += 1
        if call.name == "geometry.verify":
            result = geometry_result(self.arms)
        elif call.name == "camera.history":
            result = camera_history(self.frames, call.args.step)  # type: ignore[union-attr]
        else:  # demonstration tools arrive with the demonstrations issue
            raise SessionEnd("error", "harness_error", f"tool {call.name} is not implemented")
        self.rec.event(
            "tool",
            step=step,
            label=P.decision_label(call),
            ok=result.ok,
            result=result.text,
            images=len(result.images),
        )
        self.conv.add_tool_result(result.text, result.images, step=result.step)

    # -- acting -------------------------------------------------------------------------------
    def _camera_action(self, step: int, action: P.CameraAction) -> None:
        assert self.camera is not None and self.snapshot is not None
        self.camera = cam.apply_camera_action(
            self.camera, action.action, self.snapshot.gcs, self.arms
        )
        self.counts.camera_actions += 1
        self.feedback = ActionFeedback(valid=True, planner_success=True)
        self.rec.event(
            "camera", step=step, label=action.action, reason=action.reason, view=self.camera.label
        )

    async def _robot_action(self, slot: int, step: int, action: Any) -> None:
        reply = await self.svc.sim.act(slot, action)
        out = reply.outcome
        assert out is not None
        res = out.result
        self.snapshot = reply.snapshot
        self.counts.robot_actions += 1
        if not (res.valid and res.planner_success):
            self.counts.invalid_actions += 1
        self.feedback = ActionFeedback(valid=res.valid, planner_success=res.planner_success)
        if res.infrastructure_error is not None:
            raise SimulationError(res.infrastructure_error)
        self.rec.event(
            "action",
            step=step,
            label=res.label or P.decision_label(action),
            reason=action.reason,
            valid=res.valid,
            error=res.error,
            planner_success=res.planner_success,
            executed=res.executed,
            clipped=res.clipped,
            executed_mm=res.executed_mm,
            proprio=reply.snapshot.proprio,
            checks=out.checks,
            objects=reply.snapshot.objects,  # evaluator-only: the viewer's marked panel
            progress=out.progress,
            success=out.success,
        )
        if out.success:
            self.success = True
            raise SessionEnd("success", "success")

    # -- ending -------------------------------------------------------------------------------
    def _finish(self, status: str, stop_reason: str, error: str | None) -> EpisodeResult:
        progress = self.snapshot.progress if self.snapshot is not None else 0
        result = EpisodeResult(
            task=self.spec.task,
            seed=self.spec.seed,
            model=self.spec.model,
            protocol=self.spec.protocol,
            run=self.spec.run,
            status=status,  # type: ignore[arg-type]
            success=status == "success",
            stop_reason=stop_reason,
            error=error,
            **dataclasses.asdict(self.counts),
            step_budget=self.budget,
            model_calls=self.spend.calls,
            compactions=len(self.conv.compactions),
            checkpoints_reached=list(self.task.checkpoints[:progress]),
            progress=progress,
            n_checkpoints=len(self.task.checkpoints),
            tokens=self.spend.tokens(),
            cost_usd=round(self.spend.cost, 6),
            wall_s=round(time.time() - self.t0, 3),
            started_at=round(self.t0, 3),
            summary_mode=self.spec.summary_mode,
            summary_from=self.spec.summary_from,
            summary_status=self.spec.summary_status,
        )
        return self.rec.finish(result)


def model_limits(limits: ContextLimits, context_window: int) -> ContextLimits:
    """`limits` for a model whose context holds `context_window` tokens: the smaller window of
    the two, with an output reserve of at most half of it (a small local window still leaves
    room for the conversation)."""
    window = min(limits.window_tokens, context_window)
    if window == limits.window_tokens:
        return limits
    reserve = min(limits.output_reserve_tokens, window // 2)
    return dataclasses.replace(limits, window_tokens=window, output_reserve_tokens=reserve)


def _passive_view(camera_view: str) -> str:
    """The passive view name ("topdown") of a bundle pose named "topdown" or "<target>_topdown"."""
    for view in PASSIVE_VIEWS:
        if camera_view == view or camera_view.endswith(f"_{view}"):
            return view
    raise ValueError(f"camera view {camera_view!r} is not one of the passive views {PASSIVE_VIEWS}")


async def run_episode(spec: EpisodeSpec, services: TaskServices) -> EpisodeResult:
    return await Episode(spec, services).run()


async def run_episodes(specs: Sequence[EpisodeSpec], services: TaskServices) -> list[EpisodeResult]:
    """Run episodes of one task concurrently (at most the batch's slots at once)."""
    gate = asyncio.Semaphore(services.sim.n_slots)

    async def one(spec: EpisodeSpec) -> EpisodeResult:
        async with gate:
            return await run_episode(spec, services)

    return list(await asyncio.gather(*(one(s) for s in specs)))


async def _raise_if_device_failed(err: Exception) -> None:
    """An error that a failed GPU context caused is the process's, not the episode's: raised
    as `DeviceFailure` (no record; the sweep stops and the same command runs the episode). The
    check waits for the GPU's queued work: in a thread, off the event loop."""
    if not watched_devices():
        return
    failure = await asyncio.to_thread(device_failure, err)
    if failure is not None:
        raise failure from err
