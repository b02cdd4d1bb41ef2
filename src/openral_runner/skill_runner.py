"""``SkillRunnerBase``: the one tick body every runner that closes a loop around a skill runs (hardware and sim).

A tick reads the world, asks the skill, checks the action and acts, in this order, and this module
times each phase itself::

    _sense()  ──►  _world_state()  ──►  skill (or executor), handover  ──►  safety  ──►  deadline, _actuate()
    sensors_ms     world_state_ms       inference_ms                        safety_ms    hal_ms

A subclass provides only the three hooks: what reading the world and acting on it mean for a robot
(HAL state, sensor frames, the aggregator's snapshot; ``HAL.send_action``) or a simulator (the
env's observation and camera renders; ``env.step``). Around the phases sits the supervisor
boundary: a skill's exception, an invalid action, a safety violation, an e-stop, a late action
each withhold the action and are traced and counted. The runner also owns the recorder and the
episode boundaries observers hear about.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable
from typing import Any

import structlog
from opentelemetry import context, trace
from opentelemetry.trace import Status, StatusCode

from openral_core import (
    Action,
    ExecutorConfig,
    ROSConfigError,
    ROSEStopRequested,
    ROSSafetyViolation,
    ROSStopRequested,
    RSkillState,
    RunResult,
    StopReason,
    WithheldReason,
    WorldState,
)
from openral_core.actions import action_problem
from openral_observability import metrics, record_error, semconv
from openral_rskill.base import RSkillBase
from openral_rskill.executor import ChunkedExecutor, Outcome
from openral_runner.base import InferenceRunnerBase
from openral_runner.safety import NullSafetyClient, SafetyClient
from openral_runner.takeover import Takeover
from openral_runner.tick_context import TickContext

_log = structlog.get_logger(__name__)


class SkillRunnerBase(InferenceRunnerBase):
    """A runner that asks ``skill`` for an action each tick and checks it with ``safety_client``.

    Args:
        skill: An active skill.
        safety_client: Checks every action; defaults to ``NullSafetyClient``.
        task: Instruction placed in every world state.
        executor: How a chunking skill (chunk size above 1) is executed; it then runs on the
            executor's worker and the tick takes its rows (:mod:`openral_rskill.executor`).
        action_names: The action's dimensions (the robot's joints, an env's action names): what
            a chunk's rows must match.
        fallback_skill: Acts while the chunking skill is starved (``executor.fallback: skill``).
        virtual_delay: Simulation only: ticks from a chunk request to its use, per request.
        takeover: A skill a person can take control with mid-run (:mod:`openral_runner.takeover`).
        **base_kwargs: ``InferenceRunnerBase`` options.
    """

    def __init__(
        self,
        *,
        skill: RSkillBase,
        safety_client: SafetyClient | None = None,
        task: str | None = None,
        executor: ExecutorConfig | None = None,
        action_names: list[str] | None = None,
        fallback_skill: RSkillBase | None = None,
        virtual_delay: Callable[[int], int] | None = None,
        takeover: Takeover | None = None,
        **base_kwargs: Any,
    ) -> None:
        base_kwargs.setdefault("skill_id", skill.info.skill_id)
        super().__init__(**base_kwargs)
        self.skill = skill
        self.safety_client: SafetyClient = safety_client or NullSafetyClient()
        self.task = task
        self.fallback_skill = fallback_skill
        self.takeover = takeover
        self._last_sent: list[float] | None = None
        """Row 0 of the last command the robot accepted: where a bumpless switch starts from."""
        self.executor: ChunkedExecutor | None = None
        if skill.info.chunk_size > 1:
            if action_names is None:
                raise ROSConfigError("a chunking skill needs the action's names", field="vla.id")
            self.executor = ChunkedExecutor.for_skill(
                skill, executor, action_names=action_names, virtual_delay=virtual_delay
            )

    def activate(self) -> None:
        """Start the fallback skill (a chunking skill's, if any) and the takeover skill, then the base."""
        for helper in self._helper_skills():
            if helper.state is RSkillState.UNCONFIGURED:
                helper.configure()
                helper.activate()
        super().activate()

    def deactivate(self) -> None:
        """Stop the base, the chunk executor's worker, the fallback and the takeover skill. Idempotent."""
        super().deactivate()
        self.close_executor()
        for helper in self._helper_skills():
            if helper.state is not RSkillState.UNCONFIGURED:
                helper.shutdown()

    def _helper_skills(self) -> list[RSkillBase]:
        """The skills besides the policy that this runner starts and stops itself."""
        helpers = [self.fallback_skill, self.takeover.skill if self.takeover is not None else None]
        return [skill for skill in helpers if skill is not None]

    # -- episode boundaries ----------------------------------------------------------------

    def _tell_episode_start(self, episode_idx: int, task: str) -> None:
        for observer in list(self.observers):
            self._tell(observer, observer.on_episode_start, episode_idx, task)

    def _tell_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        for observer in list(self.observers):
            self._tell(observer, observer.on_episode_end, episode_idx, success=success, keep=keep)

    # -- the tick ----------------------------------------------------------------------------

    def _tick_impl(self, tick: TickContext) -> None:
        """Sense, build the world state, ask the skill, hand over, check, apply the deadline, act: each phase timed.

        A reason to withhold the action, once given, stands (:meth:`TickContext.withhold`): a
        tick whose world state is unusable never asks the skill, and a withheld action is never
        sent, but ``_actuate`` still runs (with ``None``) so a simulator steps on.
        """
        # The phases that run user code (the skill, the safety client) make their span current,
        # so spans the skill or safety client opens, and the e-stop span, nest under them. A tick
        # the sampler did not record gets no phase spans at all: its phases use the tick's own
        # non-recording span, keeping a skill's spans in the tick's unsampled trace.
        now = self._clock.now
        t0 = now()
        self._sense(tick)
        t1 = now()
        world = self._world_state(tick)
        tick.world = world
        t2 = now()
        action: Action | None = None
        if tick.withheld is None:
            action, withheld = self._skill_phase(world, tick.tick_idx)
            if withheld is not None:
                tick.withhold(withheld)
        requested = action
        if action is not None and self.takeover is not None:
            action = self._handover(action, world)
        t3 = now()
        to_send: Action | None = None
        if action is not None:
            to_send, withheld = self._safety_phase(action, tick.safety_violations)
            if withheld is not None:
                tick.withhold(withheld)
        t4 = now()
        if to_send is not None and not self._deadline_allows_send():
            to_send = None
            tick.withhold(WithheldReason.DEADLINE)
            self._telemetry.span.add_event(
                semconv.EVENT_ACTION_DROPPED, {semconv.ATTR_WITHHELD_REASON: WithheldReason.DEADLINE.value}
            )
        failed = self._actuate(tick, to_send)
        t5 = now()

        tick.sensors_ms = (t1 - t0) * 1e3
        tick.world_state_ms = (t2 - t1) * 1e3
        tick.inference_ms = (t3 - t2) * 1e3
        tick.safety_ms = (t4 - t3) * 1e3
        tick.hal_ms = (t5 - t4) * 1e3
        if failed is not None:
            tick.withhold(failed)
        elif to_send is not None:
            tick.action_applied = True
            self._last_sent = to_send.targets[0]
            if self.executor is not None:
                self.executor.sent(tick.tick_idx, to_send.targets[0])  # what a policy reading executed actions sees
        if requested is not None and action is not None:
            tick.requested_action = requested.first
            if tick.action_applied and to_send is not None:
                tick.sent_action = to_send.first

    @abstractmethod
    def _sense(self, tick: TickContext) -> None:
        """Read the robot's state and its sensors for ``tick`` (timed as ``sensors_ms``).

        Also labels ``tick`` with its episode and step when one is under way. A read that fails
        withholds the tick's action (``tick.withhold``); the world state is still built.
        """

    @abstractmethod
    def _world_state(self, tick: TickContext) -> WorldState:
        """The world state the skill sees this tick, built from what ``_sense`` read (timed as ``world_state_ms``).

        A world state the skill must not act on (a required sensor stale) withholds the action.
        """

    @abstractmethod
    def _actuate(self, tick: TickContext, action: Action | None) -> WithheldReason | None:
        """Act on ``action`` (timed, with the deadline check, as ``hal_ms``); ``None`` when it was withheld.

        Returns:
            Why ``action`` did not reach the robot after all (``HAL_ERROR``), else ``None``.
        """

    # -- the skill and safety phases -------------------------------------------------------

    def _reset_skill(self, seed: int | None = None) -> None:
        """Start the skill's next episode: on the executor's worker for a chunking skill (never during inference)."""
        if self.executor is not None:
            skill = self.skill
            self.executor.reset(lambda: skill.reset(seed=seed))
        else:
            self.skill.reset(seed=seed)

    def close_executor(self) -> None:
        """Stop the chunk executor's worker (a hung inference is abandoned). Idempotent."""
        if self.executor is not None:
            self.executor.close()

    def _build_run_result(self, n_ticks: int, stop_reason: StopReason) -> RunResult:
        if self.executor is not None:
            stats = self.executor.stats
            self.metadata["executor"] = {
                "requests": stats.requests,
                "chunks_used": stats.chunks_used,
                "chunks_discarded": stats.chunks_discarded,
                "results_late": stats.results_late,
                "results_stale_epoch": stats.results_stale_epoch,
                "rows_skipped": stats.rows_skipped,
                "starved_ticks": stats.starved_ticks,
                "unavailable_ticks": stats.unavailable_ticks,
                "errors": stats.errors,
                "stale_rows": stats.stale_rows,
            }
        if self.takeover is not None:
            self.metadata["takeover"] = {
                "skill": self.takeover.skill_id,
                "switches": self.takeover.switches,
                "human_ticks": self.takeover.human_ticks,
            }
        return super()._build_run_result(n_ticks, stop_reason)

    def _skill_phase(self, world: WorldState, tick_idx: int) -> tuple[Action | None, WithheldReason | None]:
        """Ask the skill (or its executor) for an action; any failure withholds it (the skill is third-party code)."""
        if self.takeover is not None:
            return self._takeover_phase(self.takeover, world, tick_idx)
        return self._policy_phase(world, tick_idx)

    def _policy_phase(self, world: WorldState, tick_idx: int) -> tuple[Action | None, WithheldReason | None]:
        if self.executor is not None:
            return self._chunk_phase(self.executor, world, tick_idx)
        return self._step_phase(self.skill, world, tick_idx)

    # -- takeover ----------------------------------------------------------------------------

    def _takeover_phase(
        self, takeover: Takeover, world: WorldState, tick_idx: int
    ) -> tuple[Action | None, WithheldReason | None]:
        """The action of whoever drives this tick; the policy's proposal is kept for the recording."""
        tick = self._tick
        if takeover.begin_tick():
            self._on_switch(takeover, tick_idx)
        human = takeover.human_in_control
        tick.intervention = human
        if not human:
            tick.active_skill = self.skill.info.skill_id
            action, withheld = self._policy_phase(world, tick_idx)
            tick.policy_action = action.first if action is not None else None
            return action, withheld
        tick.active_skill = takeover.skill_id
        if takeover.policy_labels:
            tick.policy_action = self._policy_label(world, tick_idx)
        return self._step_phase(takeover.skill, world, tick_idx)

    def _on_switch(self, takeover: Takeover, tick_idx: int) -> None:
        """Control passed this tick; whoever takes it starts afresh from the measured state."""
        to = takeover.skill_id if takeover.human_in_control else self.skill.info.skill_id
        self._telemetry.span.add_event(semconv.EVENT_TAKEOVER, {semconv.ATTR_TAKEOVER_ACTIVE_SKILL: to})
        metrics.add(semconv.METRIC_TAKEOVER_SWITCHES, 1, {**self._metric_attrs, semconv.ATTR_TAKEOVER_ACTIVE_SKILL: to})
        _log.info("control passed", to=to, tick=tick_idx, human=takeover.human_in_control)
        if takeover.human_in_control:
            # A new turn: a device that integrates motion (a gamepad's deltas) starts from where the
            # robot is now, not from where the person's last turn ended.
            takeover.skill.reset()
        else:
            # A new epoch: no row computed before or during the person's turn is replayed, and the
            # policy's own queues start from what it observes now.
            self._reset_skill()

    def _policy_label(self, world: WorldState, tick_idx: int) -> list[float] | None:
        """What the policy would command this tick while the person drives (nothing is sent, nothing stops)."""
        if self.executor is not None:
            try:
                decision = self.executor.step(tick_idx, world, self._telemetry)
            except Exception as exc:
                _log.debug("policy label failed", error=str(exc), tick=tick_idx)
                return None
            return decision.action.first if decision.outcome is Outcome.ACTION and decision.action else None
        try:
            output = self.skill.step(world)
        except Exception as exc:  # a label is a by-product: a failing or finished policy labels nothing
            _log.debug("policy label failed", error=str(exc), tick=tick_idx)
            return None
        return output.first if action_problem(output) is None else None

    def _handover(self, action: Action, world: WorldState) -> Action:
        """``action`` limited to one envelope step from the last command while a switch ramps (bumpless)."""
        takeover = self.takeover
        if takeover is None:
            return action
        reference = self._last_sent
        if reference is None and world.joint_state is not None:
            reference = list(world.joint_state.positions)
        limited, ramped = takeover.limit(action, reference)
        self._tick.handover_ramp = ramped
        return limited

    def _chunk_phase(
        self, executor: ChunkedExecutor, world: WorldState, tick_idx: int
    ) -> tuple[Action | None, WithheldReason | None]:
        """This tick's row of the chunk executor (never waiting on inference), or why there is none."""
        span = self._telemetry.start_span(semconv.SPAN_SKILL_INFERENCE)
        try:
            decision = executor.step(tick_idx, world, self._telemetry)
        except Exception as exc:  # anchoring reads the world state the skill's parameters name
            record_error(span, exc)
            _log.warning("chunk execution failed", error=str(exc), tick=tick_idx)
            return None, WithheldReason.SKILL_ERROR
        finally:
            span.end()
        outcome = decision.outcome
        if outcome is Outcome.ACTION or outcome is Outcome.HOLD:
            self._tick.chunk_id = decision.chunk
            return decision.action, None
        if outcome is Outcome.NONE:
            return None, WithheldReason.AWAITING_CHUNK
        if outcome is Outcome.FALLBACK and self.fallback_skill is not None:
            return self._step_phase(self.fallback_skill, world, tick_idx)
        _log.error("the chunking policy has no action (starved, or its source is down); stopping", tick=tick_idx)
        self.request_stop(StopReason.FAULTS)
        return None, WithheldReason.STARVED

    def _step_phase(
        self, skill: RSkillBase, world: WorldState, tick_idx: int
    ) -> tuple[Action | None, WithheldReason | None]:
        span = self._telemetry.start_span(semconv.SPAN_SKILL_INFERENCE)
        token = context.attach(trace.set_span_in_context(span)) if self._spans_current else None
        try:
            output = skill.step(world)
            problem = action_problem(output)
            if problem is None:
                return output, None
            span.set_status(Status(StatusCode.ERROR, problem))
            span.add_event(semconv.EVENT_INVALID_ACTION, {semconv.ATTR_EXCEPTION_MESSAGE: problem})
            _log.warning("skill returned an invalid action; withheld", problem=problem, tick=tick_idx)
            return None, WithheldReason.INVALID_ACTION
        except ROSEStopRequested as exc:
            return None, self._estop(exc)
        except ROSStopRequested as exc:  # the skill's task is done: not a failure
            span.add_event(semconv.EVENT_SKILL_DONE, {semconv.ATTR_EXCEPTION_MESSAGE: str(exc)})
            self._on_skill_done(str(exc), tick_idx)
            return None, WithheldReason.SKILL_DONE
        except Exception as exc:
            record_error(span, exc)
            _log.warning("skill step failed", error=str(exc), tick=tick_idx)
            return None, WithheldReason.SKILL_ERROR
        finally:
            if token is not None:
                context.detach(token)
            span.end()

    def _on_skill_done(self, reason: str, tick_idx: int) -> None:
        """The skill finished its task: on a robot the run ends."""
        _log.info("the skill finished its task; stopping", reason=reason, tick=tick_idx)
        self.request_stop(StopReason.SKILL_DONE)

    def _safety_phase(self, action: Action, violations: list[str]) -> tuple[Action | None, WithheldReason | None]:
        """Check ``action``; returns what may be sent (the action or its replacement) or why nothing may."""
        span = self._telemetry.start_span(semconv.SPAN_SAFETY_CHECK)
        token = context.attach(trace.set_span_in_context(span)) if self._spans_current else None
        try:
            replacement = self.safety_client.check_action(action)
            to_send = action if replacement is None else replacement
            if span.is_recording():
                span.set_attributes(
                    {
                        semconv.ATTR_SAFETY_REQUESTED: action.first,
                        semconv.ATTR_SAFETY_SENT: to_send.first,
                        semconv.ATTR_SAFETY_REPLACED: replacement is not None,
                    }
                )
            return to_send, None
        except ROSSafetyViolation as exc:
            violations.append(exc.check_name)
            if span.is_recording():
                span.set_attribute(semconv.ATTR_SAFETY_REQUESTED, action.first)
            attrs = {semconv.ATTR_SAFETY_CHECK_NAME: exc.check_name, semconv.ATTR_SAFETY_SEVERITY: exc.severity}
            span.record_exception(exc)
            span.add_event(semconv.EVENT_SAFETY_VIOLATION, {**attrs, semconv.ATTR_EXCEPTION_MESSAGE: str(exc)})
            metrics.add(semconv.METRIC_SAFETY_VIOLATIONS, 1, attrs)
            _log.warning("action rejected by safety", check=exc.check_name, reason=str(exc))
            return None, WithheldReason.SAFETY
        except ROSEStopRequested as exc:
            return None, self._estop(exc)
        finally:
            if token is not None:
                context.detach(token)
            span.end()

    def _estop(self, exc: ROSEStopRequested) -> WithheldReason:
        """E-stop the robot and stop the loop; returns the withheld reason."""
        span = trace.get_current_span()
        span.add_event(semconv.EVENT_ESTOP_REQUESTED, {semconv.ATTR_ESTOP_REASON: str(exc)})
        _log.error("e-stop requested", reason=str(exc))
        self._estop_robot()
        self.request_stop(StopReason.ESTOP)
        return WithheldReason.ESTOP

    def _estop_robot(self) -> None:
        """Bring the robot to a safe stop now (a simulation has nothing to stop)."""
