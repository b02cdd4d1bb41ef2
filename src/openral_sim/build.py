"""Building and running a ``SimRunner`` from a scene, a skill id and its parameters."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from openral_core import EpisodeResult, SimEnvironment, TickResult, WorldState
from openral_rskill.base import RSkillBase
from openral_runner.factory import SKILL_REGISTRY
from openral_runner.observer import TickObserver
from openral_sim.env import EnvSpec, make_env
from openral_sim.runner import SimRunner


def build_sim_runner(
    scene: SimEnvironment,
    skill_id: str,
    skill_params: Mapping[str, Any] | None = None,
    *,
    first_episode: int = 0,
    n_episodes: int | None = None,
    **runner_kwargs: Any,
) -> SimRunner:
    """The scene's environment, the skill built against its action space, and the runner around them.

    The skill is returned unconfigured inside the runner (``runner.skill``).

    Raises:
        ROSConfigError: An unknown environment or skill, or bad parameters (the env is closed again).
    """
    env = make_env(scene)
    try:
        manifest = env.spec.action_manifest(scene.robot or scene.env)
        skill_class = SKILL_REGISTRY.resolve(skill_id, field="--skill")
        skill: RSkillBase = skill_class.from_config(
            dict(skill_params or {}), robot=manifest, rate_hz=env.spec.control_hz
        )
        fallback = scene.executor.fallback_skill
        if fallback is not None:
            runner_kwargs.setdefault(
                "fallback_skill",
                SKILL_REGISTRY.resolve(fallback.id, field="executor.fallback_skill.id").from_config(
                    fallback.params, robot=manifest, rate_hz=env.spec.control_hz
                ),
            )
        return SimRunner(
            env=env, scene=scene, skill=skill, first_episode=first_episode, n_episodes=n_episodes, **runner_kwargs
        )
    except BaseException:
        env.close()
        raise


@dataclass
class EpisodeBatch:
    """The outcomes of a run of episodes, with every step's tick and inference time for percentiles."""

    episodes: list[EpisodeResult]
    tick_ms: list[float] = field(default_factory=list)
    inference_ms: list[float] = field(default_factory=list)


def run_episodes(
    scene: SimEnvironment,
    skill_id: str,
    skill_params: Mapping[str, Any] | None = None,
    *,
    first_episode: int = 0,
    n_episodes: int | None = None,
    observers: Sequence[Callable[[EnvSpec], TickObserver]] = (),
    recorder: Callable[[EnvSpec], TickObserver] | None = None,
    on_runner: Callable[[SimRunner], None] | None = None,
) -> EpisodeBatch:
    """Run episodes ``first_episode ..`` of ``scene`` with the skill, start to finish, and return their outcomes.

    Args:
        observers: Make the observers of the ticks (a video writer) for the env's spaces and rate;
            closed with the runner.
        recorder: Makes the recorder of the episodes (a ``RolloutRecorder``) for the env's spaces.
        on_runner: Called with the active runner before the first tick (a signal handler's hook).
    """
    runner = build_sim_runner(scene, skill_id, skill_params, first_episode=first_episode, n_episodes=n_episodes)
    made: list[TickObserver] = []
    try:
        if recorder is not None:
            made.append(recorder(runner.env.spec))
            runner.attach_recorder(made[-1])
        for make in observers:
            made.append(make(runner.env.spec))
            runner.observers.append(made[-1])
    except BaseException:
        runner.env.close()
        for observer in made:
            observer.close()
        raise
    skill = runner.skill
    batch = EpisodeBatch(episodes=runner.episode_results)
    runner.observers.append(_StepCollector(batch))
    try:
        skill.configure()
        skill.activate()
        runner.activate()
        if on_runner is not None:
            on_runner(runner)
        ceiling = runner.n_episodes * (scene.max_steps + 1) + 1
        runner.run(max_ticks=ceiling)
    finally:
        runner.deactivate()
        skill.shutdown()
    return batch


class _StepCollector(TickObserver):
    """Keeps each step tick's tick and inference time (reset ticks excluded), for latency percentiles."""

    def __init__(self, batch: EpisodeBatch) -> None:
        self._batch = batch

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        if tick.step_idx is not None:
            self._batch.tick_ms.append(tick.tick_ms)
            self._batch.inference_ms.append(tick.inference_ms)

    def close(self) -> None:
        return
