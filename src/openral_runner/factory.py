"""From a ``RobotEnvironment`` to a live ``HardwareRunner``: the one seam ``openral deploy`` goes through.

Every component is found through its entry-point group, built-ins included, so a third-party
skill, HAL, sensor backend or safety client is used exactly like a built-in one. Each
registry is read once here, at build time, never per tick.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import structlog

from openral_core import ObserverContext, RobotEnvironment, RobotManifest, ROSConfigError
from openral_core.config_files import resolve_user_path
from openral_core.plugins import (
    HALS_GROUP,
    SAFETY_CLIENTS_GROUP,
    SENSOR_BACKENDS_GROUP,
    PluginRegistry,
)
from openral_hal.manifests import load_robot_manifest
from openral_hal.protocol import HAL, HALPlugin
from openral_observability.observer import TickObserver
from openral_rskill.base import OfflineConfigCheck, OfflineObservation, RobotInputCheck, RSkillBase
from openral_rskill.manifest import RSkillManifest
from openral_runner.clock import Clock
from openral_runner.composition import (
    OBSERVER_REGISTRY,
    SKILL_REGISTRY,
    build_fallback_skill,
    build_observers,
    build_skill,
    close_observers,
)
from openral_runner.envelope import EnvelopeSafetyClient
from openral_runner.hardware import HardwareRunner
from openral_runner.safety import SafetyClient, SafetyClientPlugin
from openral_runner.sensor_reader import SensorBackendPlugin, SensorReader
from openral_runner.takeover import Takeover
from openral_world_state import WorldStateAggregator

_log = structlog.get_logger(__name__)

SENSOR_BACKEND_REGISTRY: PluginRegistry[SensorBackendPlugin] = PluginRegistry(
    SENSOR_BACKENDS_GROUP, kind="sensor backend", field="sensors[].backend"
)
"""Backend id → reader class (``Cls.from_config(config, hal=..., robot=..., base_dir=...)``).

``base_dir`` is the deployment file's directory: relative device paths resolve against it.
"""

HAL_REGISTRY: PluginRegistry[HALPlugin] = PluginRegistry(HALS_GROUP, kind="HAL adapter", field="hal.adapter")
"""Adapter id → HAL class (``Cls(manifest, params)``)."""

SAFETY_CLIENT_REGISTRY: PluginRegistry[SafetyClientPlugin] = PluginRegistry(
    SAFETY_CLIENTS_GROUP, kind="safety client", field="safety.client"
)
"""Client id → safety client class (``Cls.from_config(config, robot=..., rate_hz=...)``)."""

JOINT_STATE_MAX_AGE_TICKS = 3
"""A joint state older than this many periods is stale (it is read every tick)."""


def build_runner(
    env: RobotEnvironment,
    *,
    base_dir: Path | None = None,
    clock: Clock | None = None,
) -> tuple[HardwareRunner, RSkillBase]:
    """Compose HAL, skill, world state, sensor readers and safety client into a runner.

    The skill is returned unconfigured alongside the runner: the caller drives its
    lifecycle (configure, activate, ... shutdown) around ``runner.activate()``.

    Args:
        env: The validated deployment.
        base_dir: Directory relative paths in ``env`` are resolved against (the deployment file's).
        clock: Scheduling clock; the system clock when ``None``.

    Raises:
        ROSConfigError: An unknown plugin id, robot id, bad plugin parameters, or a rejected licence.
    """
    robot = load_robot_manifest(env.hal.robot_id)
    skill_params = _skill_params(env, robot, base_dir)
    hal = HAL_REGISTRY[env.hal.adapter](robot, env.hal.params)
    skill = build_skill(env.vla.id, skill_params, robot=robot, rate_hz=env.rate_hz)
    _check_cameras(skill, env)
    if isinstance(skill, RobotInputCheck):
        skill.check_robot_inputs()
    safety = _safety_client(env, robot)
    readers = [_build_reader(index, env, hal, robot, base_dir) for index, _ in enumerate(env.sensors)]
    aggregator_kwargs: dict[str, Any] = {
        "joint_max_age_ms": JOINT_STATE_MAX_AGE_TICKS * 1e3 / env.rate_hz,
        "sensors": env.sensors,
    }
    if clock is not None:
        aggregator_kwargs["clock"] = clock.now_ns
    fallback = build_fallback_skill(env.executor, robot=robot, rate_hz=env.rate_hz)
    takeover = _takeover(env, robot, safety)
    runner = HardwareRunner(
        hal=hal,
        skill=skill,
        aggregator=WorldStateAggregator(**aggregator_kwargs),
        sensor_readers=readers,
        safety_client=safety,
        task=env.task.instruction or None,
        rate_hz=env.rate_hz,
        deadline_overrun_policy=env.deadline_overrun_policy,
        latency_budget_ms=env.latency_budget_ms,
        clock=clock,
        max_consecutive_failures=env.faults.max_consecutive_failures,
        sensor_ready_timeout_s=env.faults.sensor_ready_timeout_s,
        runner_name=env.name,
        realtime=env.realtime,
        garbage_collection=env.realtime.garbage_collection,
        sync=env.sync,
        observers=build_observers(env.observers, ObserverContext.of_deployment(env, robot, base_dir)),
        executor=env.executor,
        action_names=robot.joint_names,
        fallback_skill=fallback,
        takeover=takeover,
    )
    return runner, skill


def check_deployment(env: RobotEnvironment, *, base_dir: Path | None = None) -> None:
    """Everything :func:`build_runner` checks, without connecting, listening or touching hardware.

    What ``openral validate`` runs: plugins are resolved, parameters validated and files read; no
    link is opened and no port bound. A skill whose building needs a peer (a policy server) checks
    its parameters alone (:class:`~openral_rskill.base.OfflineConfigCheck`), and the parts are then
    checked one by one instead of composed into a runner. Whatever was built is released again.

    Raises:
        ROSConfigError: What :func:`build_runner` would raise for the same file.
    """
    robot = load_robot_manifest(env.hal.robot_id)
    skill_params = _skill_params(env, robot, base_dir)
    skill_cls = SKILL_REGISTRY[env.vla.id]
    if not isinstance(skill_cls, OfflineConfigCheck):
        runner, skill = build_runner(env, base_dir=base_dir)
        _release(skill, runner.fallback_skill, runner.observers)
        return
    skill_cls.check_config(skill_params, robot=robot, rate_hz=env.rate_hz)
    if isinstance(skill_cls, OfflineObservation):
        _check_camera_names(env.vla.id, skill_cls.offline_observation(skill_params), env)
    hal = HAL_REGISTRY[env.hal.adapter](robot, env.hal.params)
    _safety_client(env, robot)
    for index, _ in enumerate(env.sensors):
        _build_reader(index, env, hal, robot, base_dir)
    takeover = _takeover(env, robot, _safety_client(env, robot))
    observers = build_observers(env.observers, ObserverContext.of_deployment(env, robot, base_dir))
    _release(None, build_fallback_skill(env.executor, robot=robot, rate_hz=env.rate_hz), observers)
    if takeover is not None:
        takeover.skill.shutdown()


def _check_cameras(skill: RSkillBase, env: RobotEnvironment) -> None:
    """Every camera the skill says it reads must be a sensor of the deployment: refused now, not at the first tick."""
    _check_camera_names(skill.info.skill_id, skill.info.observation, env)


def _check_camera_names(skill_id: str, observation: list[str], env: RobotEnvironment) -> None:
    sensors = [sensor.sensor_id for sensor in env.sensors]
    wanted = [name.removeprefix("images.") for name in observation if name.startswith("images.")]
    missing = [name for name in wanted if name not in sensors]
    if missing:
        raise ROSConfigError(
            f"skill '{skill_id}' reads camera(s) {missing}, which the deployment does not have "
            f"(sensors: {sensors or 'none'})",
            field="sensors",
            hint="add the camera under sensors:, or map the policy's camera to one you have",
        )


def _release(skill: RSkillBase | None, fallback: RSkillBase | None, observers: list[TickObserver]) -> None:
    for built in (skill, fallback):
        if built is not None:
            built.shutdown()
    close_observers(observers)


def _skill_params(env: RobotEnvironment, robot: RobotManifest, base_dir: Path | None) -> dict[str, Any]:
    """The skill's parameters: the deployment's, over its rSkill manifest's defaults when it names one."""
    if env.vla.manifest is None:
        return dict(env.vla.params)
    manifest_path = resolve_user_path(env.vla.manifest, base_dir, field="vla.manifest")
    rskill = RSkillManifest.from_yaml(manifest_path, accept_licenses=env.vla.accept_licenses)
    rskill.check_compatible(robot.robot_id)
    if rskill.kind != "policy":
        raise ROSConfigError(f"manifest {manifest_path} is a {rskill.kind}, not a policy", field="vla.manifest")
    if rskill.skill != env.vla.id:
        raise ROSConfigError(
            f"manifest {manifest_path} is for skill '{rskill.skill}', not '{env.vla.id}'",
            field="vla.id",
            hint=f"set vla.id: {rskill.skill}",
        )
    return rskill.merged_params(env.vla.params)


def _safety_client(env: RobotEnvironment, robot: RobotManifest) -> SafetyClient:
    return SAFETY_CLIENT_REGISTRY[env.safety.client].from_config(env.safety, robot=robot, rate_hz=env.rate_hz)


def _takeover(env: RobotEnvironment, robot: RobotManifest, safety: SafetyClient) -> Takeover | None:
    """The takeover skill and its switch; a switch ramps at the envelope's step limit (the robot's, without one)."""
    spec = env.takeover
    if spec is None:
        return None
    skill = build_skill(
        spec.skill,
        spec.params,
        robot=robot,
        rate_hz=env.rate_hz,
        field="takeover.skill",
        params_field="takeover.params",
    )
    if isinstance(safety, EnvelopeSafetyClient):
        max_step = safety.max_step
    else:
        max_step = tuple(joint.velocity_limit / env.rate_hz for joint in robot.joints)
    return Takeover(skill, joint_names=robot.joint_names, max_step=max_step, policy_labels=spec.policy_labels)


def _build_reader(
    index: int, env: RobotEnvironment, hal: HAL, robot: RobotManifest, base_dir: Path | None
) -> SensorReader:
    config = env.sensors[index]
    backend = SENSOR_BACKEND_REGISTRY.resolve(config.backend, field=f"sensors[{index}].backend")
    return backend.from_config(config, hal=hal, robot=robot, base_dir=base_dir)


__all__ = [
    "HAL_REGISTRY",
    "OBSERVER_REGISTRY",
    "SAFETY_CLIENT_REGISTRY",
    "SENSOR_BACKEND_REGISTRY",
    "SKILL_REGISTRY",
    "build_runner",
    "check_deployment",
]
