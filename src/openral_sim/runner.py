"""``SimRunner``: the runner's loop around a simulator, one ``env.step`` per tick.

A tick is a *reset tick* between episodes (``env.reset`` with the episode's seed, then the skill's
reset) or a *step tick*, the tick body every runner runs
(:class:`~openral_runner.skill_runner.SkillRunnerBase`): the skill sees the last observation, its
cameras rendered now, as a ``WorldState``; its action is checked by the safety client and sent to
``env.step``, exactly as on hardware (a withheld action steps the env with the hold action, as a
robot keeps holding). Step ticks carry ``episode_idx``, ``step_idx``, ``reward``, ``terminated``
and ``truncated``; the episodes' outcomes (:attr:`SimRunner.episode_results`) are derived from
them, and ``run()`` ends once ``n_episodes`` are done.

A skill that keeps failing stops the run at the fault limit, as on a robot: the episode under way
ends as ``faults`` (never as a cut-off at ``max_steps``) and is not kept by a recorder, and
:attr:`SimRunner.failure` says what failed, so a broken skill never reads as a 0 % success rate.

Observers hear the episode boundaries as on hardware, so a ``RolloutRecorder`` records simulated
episodes through the same path.

In real time (``virtual_latency: measured``) the wall clock paces the ticks and the world does not
wait for a late one: each slot a tick overran is an env step with the hold action (observers hear
ticks only), and each episode reports its stale or held steps (:mod:`openral_sim.real_time`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import structlog

from openral_core import (
    Action,
    EpisodeResult,
    EpisodeTiming,
    FrameEncoding,
    JointState,
    PrivilegedState,
    ROSConfigError,
    SensorFrame,
    SimEnvironment,
    StopReason,
    TickResult,
    WithheldReason,
    WorldState,
)
from openral_observability.queued_observer import QueuedObserver
from openral_rskill.base import RSkillBase
from openral_runner.frame_slot import frame_from_array
from openral_runner.safety import SafetyClient
from openral_runner.skill_runner import SkillRunnerBase
from openral_runner.tick_context import TickContext
from openral_sim.env import EndEffectorSensing, SimEnv, SimObservation
from openral_sim.real_time import RealTimeTally
from openral_sim.safety import ActionBoxSafetyClient
from openral_sim.smoothness import ActionGeometry, CommandLog

_log = structlog.get_logger(__name__)


class SimRunner(SkillRunnerBase):
    """Evaluates ``skill`` on ``env`` for the scene's episodes.

    Args:
        env: The simulator (built from ``scene``; closed with the runner).
        scene: Task, success key, step limit, episode count, seed and cameras.
        skill: An active skill, built against ``env.spec.action_manifest``.
        safety_client: By default the env's action box (:class:`ActionBoxSafetyClient`).
        first_episode: Global index of this runner's first episode: episode ``i`` uses seed
            ``scene.seed + i``, so a slice of episodes run anywhere reproduces the same outcomes.
        n_episodes: Episodes to run (the scene's count by default).
        close_env: Close ``env`` on ``deactivate``; ``False`` when the env outlives the runner (an
            evaluation worker keeps its env for the next slice of episodes).
        **base_kwargs: ``InferenceRunnerBase`` options; free-running unless the scene sets ``rate_hz``
            or runs in real time (``virtual_latency: measured``).
    """

    def __init__(
        self,
        *,
        env: SimEnv,
        scene: SimEnvironment,
        skill: RSkillBase,
        safety_client: SafetyClient | None = None,
        first_episode: int = 0,
        n_episodes: int | None = None,
        close_env: bool = True,
        **base_kwargs: Any,
    ) -> None:
        base_kwargs.setdefault("runner_name", scene.name)
        base_kwargs.setdefault("rate_hz", scene.rate_hz or env.spec.control_hz)
        base_kwargs.setdefault("free_running", scene.rate_hz is None and scene.timing != "measured")
        base_kwargs.setdefault("latency_budget_ms", scene.latency_budget_ms)
        latency = scene.simulated_latency
        super().__init__(
            skill=skill,
            safety_client=safety_client or ActionBoxSafetyClient(env.spec),
            task=scene.task,
            executor=scene.executor,
            action_names=list(env.spec.action_names),
            virtual_delay=None if latency is None else latency.sampler(scene.seed),
            **base_kwargs,
        )
        self.env = env
        self.close_env = close_env
        self.scene = scene
        self.first_episode = first_episode
        self.n_episodes = scene.n_episodes if n_episodes is None else n_episodes
        self.episode_results: list[EpisodeResult] = []
        self._spec = env.spec
        self._action_names = list(env.spec.action_names)
        self._observation: SimObservation | None = None
        """The observation of the last step (or reset): what the next step tick senses."""
        self._stamp_ns = 0
        self._frames: dict[str, SensorFrame] | None = None
        self._episode: _EpisodeTally | None = None
        self._frame_seq = 0
        self._opened = False
        self._failure: str | None = None
        self._geometry = ActionGeometry.of(env.spec)
        self._end_effector = env if isinstance(env, EndEffectorSensing) else None
        """Decided once: whether the env reports its end effector (for the path length)."""
        self._real_time: RealTimeTally | None = None
        """The episode under way's real-time tally (``virtual_latency: measured`` only)."""

    # -- lifecycle -------------------------------------------------------------------------

    def activate(self) -> None:
        """Start the telemetry worker; the first tick resets the env into the first episode."""
        super().activate()
        self._opened = True
        self._failure = None

    def deactivate(self) -> None:
        """End an episode under way (as stopped: not successful, and kept), close the observers and the owned env."""
        if self._episode is not None:
            self._finish_episode("stopped", success=False)
        super().deactivate()
        if self._opened:
            self._opened = False
            for observer in list(self.observers):
                try:
                    observer.close()
                except Exception as exc:  # one failing close must not keep the others open
                    _log.warning("observer close failed", observer=type(observer).__name__, error=str(exc))
            if self.close_env:
                self.env.close()

    def _should_terminate(self) -> bool:
        if self.stop_requested is StopReason.FAULTS:
            return False  # the run ends on its faults, even when the faulted episode was the last
        return len(self.episode_results) >= self.n_episodes

    @property
    def episodes_done(self) -> int:
        return len(self.episode_results)

    @property
    def failure(self) -> str | None:
        """What stopped the run at the fault limit (the skill's own error when it raised one), else ``None``.

        Such a run is no evaluation of the skill: its episodes were cut short by failures, not
        judged by the task.
        """
        return self._failure

    # -- the tick --------------------------------------------------------------------------

    def _tick_impl(self, tick: TickContext) -> None:
        """A reset tick between episodes, else the base's tick body around one ``env.step``."""
        if self._episode is None:
            self._reset_tick(tick)
            return
        super()._tick_impl(tick)

    def _reset_tick(self, tick: TickContext) -> None:
        """Reset the env into the next episode with its seed, and the skill with it (timed as ``hal_ms``).

        The reset's observation is sensed by the episode's first step tick, where the skill sees it.
        """
        now = self._clock.now
        t0 = now()
        index = self.first_episode + len(self.episode_results)
        seed = self.scene.seed + index
        self._observation = self.env.reset(seed)
        latency = self.scene.simulated_latency
        if self.executor is not None and latency is not None:
            self.executor.virtual_delay = latency.sampler(seed)
        self._reset_skill(seed)
        tick.hal_ms = (now() - t0) * 1e3
        self._episode = episode = _EpisodeTally(index, seed)
        if self._end_effector is not None:
            episode.log.position(self._end_effector.end_effector_positions())
        self._real_time = RealTimeTally(self.period_s) if self.scene.timing == "measured" else None
        tick.episode_idx = index
        self._tell_episode_start(index, self.scene.task)

    def _sense(self, tick: TickContext) -> None:
        """Render the scene's cameras on the observation of the last step (or the reset); its state is already read."""
        episode = self._episode
        assert episode is not None  # a step tick runs inside an episode
        tick.episode_idx = episode.index
        tick.step_idx = episode.steps
        self._stamp_ns = stamp = self._clock.now_ns()
        if not self.scene.cameras:
            return
        self._frame_seq += 1
        self._frames = {
            cam.name: frame_from_array(
                cam.name,
                self.env.render(cam.name, cam.width, cam.height),
                stamp_ns=stamp,
                seq=self._frame_seq,
                encoding=FrameEncoding.RGB8,
            )
            for cam in self.scene.cameras
        }

    def _world_state(self, tick: TickContext) -> WorldState:
        """The last observation's state, privileged values and camera frames, as the skill sees them."""
        observation = self._observation
        assert observation is not None  # set by the reset tick
        stamp = self._stamp_ns
        return WorldState(
            stamp_ns=stamp,
            joint_state=JointState(
                names=list(self._spec.state_names), positions=observation.state.tolist(), stamp_ns=stamp
            ),
            image_frames=self._frames,
            privileged=PrivilegedState(values=observation.privileged),
            task=self.scene.task,
        )

    def _actuate(self, tick: TickContext, action: Action | None) -> WithheldReason | None:
        """Step the env with ``action``, or with the hold action when it was withheld (as a robot keeps holding)."""
        episode = self._episode
        assert episode is not None
        if action is not None:
            command = np.asarray(action.first, dtype=np.float64)
            episode.last_sent = command
        else:
            command = self._spec.hold_action(episode.last_sent)
        episode.log.command(command, tick.chunk_id, held=action is None)
        step = self.env.step(command)
        if self._end_effector is not None:
            episode.log.position(self._end_effector.end_effector_positions())
        observation = step.observation
        self._observation = observation
        tick.reward = step.reward
        tick.terminated = step.terminated
        tick.truncated = step.truncated

        episode.steps += 1
        episode.sum_reward += step.reward
        episode.max_reward = max(episode.max_reward, step.reward)
        success = self._success(observation, episode)
        if success and episode.steps_to_success is None:
            episode.steps_to_success = episode.steps
        episode.pending_end = _ended_by(  # closed once the tick's result has reached the observers
            success=success and self.scene.end_on_success,
            terminated=step.terminated,
            truncated=step.truncated,
            max_steps=episode.steps >= self.scene.max_steps,
            skill_done=episode.skill_done,
        )
        return None

    def _run_tick(self, tick: TickContext, *, slot_start_s: float | None = None) -> TickResult:
        """Run the tick; an episode it ended is closed after the observers have seen its last step."""
        real_time = self._real_time
        if real_time is not None:
            real_time.before_tick(self.executor)
        result = super()._run_tick(tick, slot_start_s=slot_start_s)
        if real_time is not None and result.step_idx is not None:
            real_time.after_tick(result, self.executor, start_s=tick.start_s)
        faulted = self.stop_requested is StopReason.FAULTS
        if faulted and self._failure is None:
            self._failure = self._describe_failure(result)
        episode = self._episode
        if episode is not None and result.step_idx is not None:
            episode.inference_ms += result.inference_ms
            episode.step_ms_total += result.tick_ms
            episode.step_ms_max = max(episode.step_ms_max, result.tick_ms)
            if self.latency_budget_ms is not None and result.tick_ms > self.latency_budget_ms:
                episode.budget_violations += 1
            ended_by = episode.pending_end
            if faulted and ended_by in (None, "max_steps"):
                # The fault limit cut the episode short: not an episode of the task, and not a demonstration.
                self._finish_episode("faults", success=episode.steps_to_success is not None, keep=False)
            elif ended_by is not None:
                self._require_success_key(episode)
                self._finish_episode(ended_by, success=episode.steps_to_success is not None)
        if self.free_running:
            # No tick has a deadline here: rather than outrun a recorder and lose frames, wait for it.
            for observer in self.observers:
                if isinstance(observer, QueuedObserver):
                    observer.wait_for_room()
        return result

    def _on_missed_slots(self, skipped: int) -> None:
        """In real time the world does not wait for a late tick: each skipped slot is an env step with the hold action.

        Only once the episode has had its first step; the executor's ticks count slots, so the
        rows meant for the skipped slots are past when the next tick runs.
        """
        if self.scene.timing != "measured":
            return
        self._tick_idx += skipped
        for _ in range(skipped):
            episode, real_time = self._episode, self._real_time
            if episode is None or real_time is None or episode.steps == 0 or self.stop_requested is not None:
                return
            real_time.held_slot(self._clock.now())
            self._actuate(TickContext(self._tick_idx, 0.0, 0.0), None)
            if episode.pending_end is not None:
                self._require_success_key(episode)
                self._finish_episode(episode.pending_end, success=episode.steps_to_success is not None)

    def _on_skill_done(self, reason: str, tick_idx: int) -> None:
        """In simulation a skill that is done ends its episode, not the evaluation."""
        if self._episode is not None:
            self._episode.skill_done = True

    def _describe_failure(self, result: TickResult) -> str:
        """What stopped the run at the fault limit: the skill's latched exception, else the withheld reason."""
        skill_id = self.skill.info.skill_id
        error = self.skill.last_error
        if error is not None:
            detail = f"{type(error).__name__}: {error}"
        elif result.withheld_reason == WithheldReason.INVALID_ACTION:
            detail = "it returned invalid actions (the log names the problem)"
        elif result.withheld_reason == WithheldReason.STARVED:
            detail = "its chunks stopped arriving (starved, or the policy's source is down)"
        else:
            detail = f"its actions were withheld ({result.withheld_reason or 'faults'})"
        where = "" if result.episode_idx is None else f" in episode {result.episode_idx}"
        if result.step_idx is not None:
            where += f" (step {result.step_idx + 1})"
        return (
            f"skill '{skill_id}' failed, and the run stopped at the fault limit{where}: {detail} "
            "(no success rate is computed for a skill that cannot run: fix the skill, its parameters, "
            "or the scene it runs on)"
        )

    def _finish_episode(self, ended_by: str, *, success: bool, keep: bool = True) -> None:
        episode = self._episode
        assert episode is not None
        self._episode = None
        steps = max(episode.steps, 1)
        result = EpisodeResult(
            episode_idx=episode.index,
            seed=episode.seed,
            success=success,
            steps=episode.steps,
            steps_to_success=episode.steps_to_success,
            sum_reward=episode.sum_reward,
            max_reward=episode.max_reward if episode.steps else 0.0,
            ended_by=ended_by,
            control_hz=self._spec.control_hz,
            smoothness=episode.log.metrics(self._geometry),
            timing=EpisodeTiming(
                step_ms_mean=episode.step_ms_total / steps,
                step_ms_max=episode.step_ms_max,
                inference_ms_mean=episode.inference_ms / steps,
                budget_violations=episode.budget_violations,
            ),
            real_time=None if self._real_time is None else self._real_time.stats(),
        )
        self._real_time = None
        self.episode_results.append(result)
        self._tell_episode_end(episode.index, success=success, keep=keep)

    def _success(self, observation: SimObservation, episode: _EpisodeTally) -> bool:
        key = self.scene.success_key
        if key not in observation.info:
            episode.info_keys = sorted(observation.info)
            return False
        episode.saw_success_key = True
        return bool(observation.info[key])

    def _require_success_key(self, episode: _EpisodeTally) -> None:
        """An episode that never reported the scene's success key would read as a failure: refuse it."""
        if not episode.saw_success_key:
            key = self.scene.success_key
            raise ROSConfigError(
                f"the environment never reported {key!r} in episode {episode.index}'s info "
                f"(it reports {episode.info_keys})",
                field="success_key",
                hint="set success_key to the key the environment reports success under",
            )


class _EpisodeTally:
    """What the ticks of the episode under way have added up to."""

    __slots__ = (
        "budget_violations",
        "index",
        "inference_ms",
        "info_keys",
        "last_sent",
        "log",
        "max_reward",
        "pending_end",
        "saw_success_key",
        "seed",
        "skill_done",
        "step_ms_max",
        "step_ms_total",
        "steps",
        "steps_to_success",
        "sum_reward",
    )

    def __init__(self, index: int, seed: int) -> None:
        self.index = index
        self.seed = seed
        self.steps = 0
        self.steps_to_success: int | None = None
        self.sum_reward = 0.0
        self.max_reward = -float("inf")
        self.inference_ms = 0.0
        self.step_ms_total = 0.0
        self.step_ms_max = 0.0
        self.budget_violations = 0
        self.last_sent: np.ndarray | None = None
        self.saw_success_key = False
        self.info_keys: list[str] = []
        self.skill_done = False
        self.pending_end: str | None = None
        self.log = CommandLog()
        """The commands sent, for the episode's smoothness."""


def _ended_by(*, success: bool, terminated: bool, truncated: bool, max_steps: bool, skill_done: bool) -> str | None:
    if success:
        return "success"
    if terminated:
        return "terminated"
    if truncated:
        return "truncated"
    if skill_done:
        return "skill_done"
    if max_steps:
        return "max_steps"
    return None
