"""Building and running a ``SimRunner`` from a scene, a skill id and its parameters, once or again and again."""

from __future__ import annotations

import contextlib
import json
import os
import socket
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from openral_core import (
    EpisodeResult,
    ROSConfigError,
    ROSDependencyMissing,
    ROSSkillError,
    RSkillState,
    SimEnvironment,
    TickResult,
    WorldState,
)
from openral_observability.observer import TickObserver
from openral_rskill.base import RSkillBase
from openral_runner.composition import (
    OBSERVER_REGISTRY,
    SKILL_REGISTRY,
    build_fallback_skill,
    build_observers,
    close_observers,
)
from openral_runner.composition import build_skill as build_any_skill
from openral_sim.env import EnvSpec, SimEnv, make_env
from openral_sim.runner import SimRunner


@dataclass(frozen=True)
class SkillFields:
    """How errors name the skill, its parameters and the scene: the options of ``sim run``, or a suite's row.

    Attributes:
        scene: Named before a scene's own field in its errors (``runs[0].scene: env: ...``);
            ``None`` names the scene's fields alone (the scene is the ``--config`` file).
    """

    skill: str = "--skill"
    params: str = "--skill-params"
    scene: str | None = None

    @classmethod
    def of_row(cls, index: int) -> SkillFields:
        """The fields of row ``index`` of a benchmark suite."""
        return cls(skill=f"runs[{index}].skill", params=f"runs[{index}].skill_params", scene=f"runs[{index}].scene")

    def in_scene(self, exc: ROSConfigError) -> ROSConfigError:
        """``exc``, about a field of the scene, naming the scene first."""
        if self.scene is None or type(exc) is not ROSConfigError:
            return exc
        return ROSConfigError(str(exc), field=self.scene)


OPTION_FIELDS = SkillFields()
"""The fields of ``openral sim run``: its ``--skill`` and ``--skill-params`` options."""


def build_skill(
    scene: SimEnvironment,
    spec: EnvSpec,
    skill_id: str,
    skill_params: Mapping[str, Any] | None = None,
    *,
    fields: SkillFields = OPTION_FIELDS,
) -> RSkillBase:
    """The skill, unconfigured, built against ``spec``'s action space (its parameters validated).

    Raises:
        ROSConfigError: An unknown skill or bad parameters, naming ``fields``.
    """
    return build_any_skill(
        skill_id,
        skill_params or {},
        robot=spec.action_manifest(scene.robot or scene.env),
        rate_hz=spec.control_hz,
        field=fields.skill,
        params_field=fields.params,
    )


def check_evaluation(
    scene: SimEnvironment,
    skill_id: str,
    skill_params: Mapping[str, Any] | None = None,
    *,
    fields: SkillFields = OPTION_FIELDS,
    spec: EnvSpec | None = None,
    simulator_elsewhere: bool = False,
) -> EnvSpec | None:
    """Build the scene's environment, the skill, the scene's fallback skill and observers once, and let them go.

    What a run would refuse is refused here, before any episode of any run: an unknown
    environment, skill or observer, bad parameters (observers are built, not started: nothing
    is opened). Returns the environment's spec, to pass back as
    ``spec`` for the next check of the same scene (the environment is then not built again).

    Args:
        simulator_elsewhere: The episodes run on other machines (Ray): when this one lacks the
            simulator's package, only the names are checked here, and ``None`` is returned.

    Raises:
        ROSConfigError: Naming ``fields`` for the skill, the scene's own fields otherwise.
    """
    try:
        if spec is None:
            env = make_env(scene)
            spec = env.spec
            env.close()
        _fallback_skill(scene, spec)
        close_observers(build_observers(scene.observers, spec.observer_context(scene)))
    except ROSDependencyMissing:
        if not simulator_elsewhere:
            raise
        SKILL_REGISTRY.resolve(skill_id, field=fields.skill)
        for index, entry in enumerate(scene.observers):
            OBSERVER_REGISTRY.resolve(entry.id, field=f"observers[{index}].id")
        return None
    except ROSConfigError as exc:
        raise fields.in_scene(exc) from exc
    build_skill(scene, spec, skill_id, skill_params, fields=fields)
    return spec


def build_sim_runner(
    scene: SimEnvironment,
    skill_id: str,
    skill_params: Mapping[str, Any] | None = None,
    *,
    first_episode: int = 0,
    n_episodes: int | None = None,
    fields: SkillFields = OPTION_FIELDS,
    **runner_kwargs: Any,
) -> SimRunner:
    """The scene's environment, the skill built against its action space, and the runner around them.

    The skill is returned unconfigured inside the runner (``runner.skill``).

    Raises:
        ROSConfigError: An unknown environment or skill, or bad parameters (the env is closed again).
    """
    env = make_env(scene)
    try:
        skill = build_skill(scene, env.spec, skill_id, skill_params, fields=fields)
        fallback = _fallback_skill(scene, env.spec)
        if fallback is not None:
            runner_kwargs.setdefault("fallback_skill", fallback)
        return SimRunner(
            env=env, scene=scene, skill=skill, first_episode=first_episode, n_episodes=n_episodes, **runner_kwargs
        )
    except BaseException:
        env.close()
        raise


def _fallback_skill(scene: SimEnvironment, spec: EnvSpec) -> RSkillBase | None:
    """The skill that acts while the scene's chunking skill is starved, if the scene names one."""
    return build_fallback_skill(
        scene.executor, robot=spec.action_manifest(scene.robot or scene.env), rate_hz=spec.control_hz
    )


class SkillFailed(ROSSkillError):
    """The skill kept failing and the fault limit stopped the episodes: they are no evaluation of it.

    Args:
        message: What failed (the skill's own error when it raised one).
        batch: The episodes run until then (the last one ``ended_by="faults"``).
    """

    def __init__(self, message: str, *, batch: EpisodeBatch) -> None:
        super().__init__(message)
        self.batch = batch

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild_skill_failed, (str(self), self.batch))


def _rebuild_skill_failed(message: str, batch: EpisodeBatch) -> SkillFailed:
    return SkillFailed(message, batch=batch)


@dataclass
class EpisodeBatch:
    """The outcomes of a run of episodes, with every step's tick and inference time for percentiles."""

    episodes: list[EpisodeResult]
    tick_ms: list[float] = field(default_factory=list)
    inference_ms: list[float] = field(default_factory=list)
    failure: str | None = None
    """Set when the skill kept failing and the fault limit stopped the episodes (see :class:`SkillFailed`)."""
    env_builds: dict[str, int] = field(default_factory=dict)
    """Environments built to run these episodes, by the process that ran them (``host:pid``; 0: it reused one)."""

    def raise_for_failure(self) -> None:
        """Raise if the episodes were stopped by a failing skill.

        Raises:
            SkillFailed: Carrying this batch.
        """
        if self.failure is not None:
            raise SkillFailed(self.failure, batch=self)


def run_episodes(
    scene: SimEnvironment,
    skill_id: str,
    skill_params: Mapping[str, Any] | None = None,
    *,
    first_episode: int = 0,
    n_episodes: int | None = None,
    on_runner: Callable[[SimRunner], None] | None = None,
    fields: SkillFields = OPTION_FIELDS,
) -> EpisodeBatch:
    """Run episodes ``first_episode ..`` of ``scene`` with the skill, start to finish, and return their outcomes.

    The environment and the skill are built for this call and let go at its end; :class:`SimCache`
    keeps them for the next call instead.

    The scene's ``observers:`` entries are built for the env's spaces and rate, started with the
    runner and closed with it.

    Args:
        on_runner: Called with the active runner before the first tick (a signal handler's hook).
        fields: How errors name the skill and its parameters.

    Raises:
        SkillFailed: The skill kept failing until the fault limit stopped the episodes (the
            episodes run until then are in its ``batch``).
    """
    runner = build_sim_runner(
        scene, skill_id, skill_params, first_episode=first_episode, n_episodes=n_episodes, fields=fields
    )
    try:
        batch = _drive(runner, on_runner=on_runner, start_skill=True)
    finally:
        runner.skill.shutdown()
    batch.env_builds = {process_name(): 1}
    batch.raise_for_failure()
    return batch


class SimCache:
    """The environment and the skills of one process, built once and reused by every run of episodes in it.

    Building an environment loads its model (about a second for a MuJoCo scene) and building a
    skill may load weights: an evaluation worker that runs slice after slice of the same scene
    pays that once. Reuse cannot change an outcome: every episode starts from ``env.reset`` with
    its own seed and ``skill.reset(seed=...)``, exactly as consecutive episodes of one run do.

    One environment is kept (a suite's rows run one after the other): a scene that needs another
    closes it and builds its own. A skill left in its error latch, and whatever a run that raised
    had built, are let go and built afresh when next asked for, as a new process would.
    """

    def __init__(self) -> None:
        self._env_key: str | None = None
        self._env: SimEnv | None = None
        self._skills: dict[str, RSkillBase] = {}
        self.envs_built = 0
        """Environments this cache has built (one per scene while the scenes keep coming back)."""
        self._reported = 0

    def run(
        self,
        scene: SimEnvironment,
        skill_id: str,
        skill_params: Mapping[str, Any] | None = None,
        *,
        first_episode: int = 0,
        n_episodes: int | None = None,
        fields: SkillFields = OPTION_FIELDS,
    ) -> EpisodeBatch:
        """Run episodes ``first_episode ..`` of ``scene`` as :func:`run_episodes` does, on the kept env and skill.

        Raises:
            SkillFailed: As :func:`run_episodes`.
        """
        clean = False
        try:
            env, skill = self.prepare(scene, skill_id, skill_params, fields=fields)
            runner = SimRunner(
                env=env,
                scene=scene,
                skill=skill,
                first_episode=first_episode,
                n_episodes=n_episodes,
                close_env=False,
                fallback_skill=_fallback_skill(scene, env.spec),
            )
            batch = _drive(runner, on_runner=None, start_skill=False)
            clean = True
        finally:
            if not clean:
                self.close()
            else:
                self._drop_latched()
        # Builds since the last report, a warm-up's (:meth:`prepare`) included.
        batch.env_builds = {process_name(): self.envs_built - self._reported}
        self._reported = self.envs_built
        batch.raise_for_failure()
        return batch

    def prepare(
        self,
        scene: SimEnvironment,
        skill_id: str,
        skill_params: Mapping[str, Any] | None = None,
        *,
        fields: SkillFields = OPTION_FIELDS,
    ) -> tuple[SimEnv, RSkillBase]:
        """The scene's environment and the active skill, built unless kept from an earlier run.

        Raises:
            ROSConfigError: An unknown environment or skill, or bad parameters.
        """
        env = self._env_for(scene)
        key = json.dumps([skill_id, dict(skill_params or {})], sort_keys=True, default=str)
        skill = self._skills.get(key)
        if skill is None:
            skill = build_skill(scene, env.spec, skill_id, skill_params, fields=fields)
            try:
                skill.configure()
                skill.activate()
            except BaseException:
                with contextlib.suppress(ROSSkillError):
                    skill.shutdown()
                raise
            self._skills[key] = skill
        return env, skill

    def close(self) -> None:
        """Shut the skills down and close the environment; the next run builds them again. Idempotent."""
        skills, self._skills = list(self._skills.values()), {}
        env, self._env, self._env_key = self._env, None, None
        try:
            for skill in skills:
                with contextlib.suppress(ROSSkillError):  # a hook failing at shutdown: nothing left to do
                    skill.shutdown()
        finally:
            if env is not None:
                env.close()

    def _env_for(self, scene: SimEnvironment) -> SimEnv:
        key = scene.model_dump_json(exclude={"name", "n_episodes", "seed", "observers"})
        if self._env is not None and key == self._env_key:
            return self._env
        self.close()
        self._env = make_env(scene)
        self._env_key = key
        self.envs_built += 1
        return self._env

    def _drop_latched(self) -> None:
        """Let go of the skills a run left in their error latch (built afresh when next asked for)."""
        for key, skill in list(self._skills.items()):
            if skill.state is not RSkillState.ACTIVE:
                del self._skills[key]
                with contextlib.suppress(ROSSkillError):
                    skill.shutdown()


def process_name() -> str:
    """This process, as ``host:pid``: where a slice of episodes ran."""
    return f"{socket.gethostname()}:{os.getpid()}"


def _drive(
    runner: SimRunner,
    *,
    on_runner: Callable[[SimRunner], None] | None,
    start_skill: bool,
) -> EpisodeBatch:
    """Build the scene's observers, run the runner's episodes and deactivate it; the failure is set, not raised."""
    try:
        runner.observers.extend(build_observers(runner.scene.observers, runner.env.spec.observer_context(runner.scene)))
    except BaseException:
        if runner.close_env:
            runner.env.close()
        raise
    batch = EpisodeBatch(episodes=runner.episode_results)
    runner.observers.append(_StepCollector(batch))
    try:
        if start_skill:
            runner.skill.configure()
            runner.skill.activate()
        runner.activate()
        if on_runner is not None:
            on_runner(runner)
        ceiling = runner.n_episodes * (runner.scene.max_steps + 1) + 1
        runner.run(max_ticks=ceiling)
    except BaseException:
        if not runner.is_active:  # refused while starting (a skill, a dataset folder, a port): nothing ran
            close_observers(runner.observers)
            if runner.close_env:
                runner.env.close()
        raise
    finally:
        runner.deactivate()
    batch.failure = runner.failure
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
