"""The seam between ``SimRunner`` and a simulator: ``SimEnv``, what it observes, and how one is built from a scene.

An adapter wraps one simulator (a gymnasium environment, usually) and translates: its
observation into a state vector with names, rendered camera frames and privileged values; its
action space into a manifest the skill factory and the safety check understand; its ``info``
into a success flag under the scene's key.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from openral_core import CameraSize, JointSpec, ObserverContext, RobotManifest, SimEnvironment
from openral_core.plugins import SIM_ENVS_GROUP, PluginRegistry

ActionKind = Literal["delta", "absolute"]
"""How the env reads an action: a change from where it is (hold = zero motion) or a target (hold = repeat)."""


@dataclass(frozen=True)
class EnvSpec:
    """What a skill and the runner need to know of an environment's spaces.

    Attributes:
        state_names: Names of the state vector (``observation.state`` when recorded).
        action_names: Names of the action vector.
        action_low / action_high: The action space's bounds (the safety check clamps into them).
        action_kind: ``delta`` or ``absolute``; ``hold_dims`` are absolute even in a delta space
            (a gripper command).
        control_hz: Env steps per simulated second (the recording's fps).
        environment_state_names: Names of ``PrivilegedState`` value ``environment_state``, when
            the env exposes a flat object state (recorded as ``observation.environment_state``).
    """

    state_names: tuple[str, ...]
    action_names: tuple[str, ...]
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    action_kind: ActionKind
    control_hz: float
    hold_dims: tuple[int, ...] = ()
    environment_state_names: tuple[str, ...] = ()

    def hold_action(self, last_sent: np.ndarray | None) -> np.ndarray:
        """The action that keeps the robot where it is: what a withheld tick sends to the env.

        A delta space holds with zero motion (absolute dimensions keep their last command); an
        absolute space repeats the last command sent, or the middle of the space before the first.
        """
        low = np.asarray(self.action_low, dtype=np.float64)
        high = np.asarray(self.action_high, dtype=np.float64)
        if self.action_kind == "absolute":
            return np.array(last_sent, dtype=np.float64) if last_sent is not None else (low + high) / 2
        hold = np.zeros(len(self.action_names))
        for dim in self.hold_dims:
            hold[dim] = last_sent[dim] if last_sent is not None else (low[dim] + high[dim]) / 2
        return np.clip(hold, low, high)

    def action_manifest(self, robot_id: str) -> RobotManifest:
        """The action space in a robot manifest's shape (one entry per action dimension, bounds as limits).

        Skills are built from a manifest (``from_config(params, robot=...)``); in simulation this
        one tells them the action's names and bounds.
        """
        joints = [
            JointSpec(name=name, lower=lo, upper=hi, velocity_limit=max(hi - lo, 1e-6) * self.control_hz)
            for name, lo, hi in zip(self.action_names, self.action_low, self.action_high, strict=True)
        ]
        return RobotManifest(robot_id=robot_id, name=f"{robot_id} action space", joints=joints)

    def observer_context(self, scene: SimEnvironment) -> ObserverContext:
        """The loop ``scene``'s observers watch: this env's names and rate, the scene's cameras and task.

        A simulation is free-running for its observers: nothing moves on while a recorder's encoders
        catch up, so it waits for them rather than repeat frames.
        """
        return ObserverContext(
            robot_id=scene.robot or scene.env_id or scene.env,
            rate_hz=self.control_hz,
            joint_names=self.state_names,
            action_names=self.action_names,
            environment_state_names=self.environment_state_names,
            cameras=tuple(CameraSize(c.name, c.width, c.height) for c in scene.cameras),
            task=scene.task,
            free_running=True,
            base_dir=None if scene.base_dir is None else Path(scene.base_dir),
        )


@dataclass
class SimObservation:
    """One observation, translated: the state vector, privileged values, and the env's ``info``."""

    state: np.ndarray
    privileged: dict[str, list[float]] = field(default_factory=dict)
    info: Mapping[str, Any] = field(default_factory=dict)


@dataclass
class SimStep:
    """The outcome of one ``step``."""

    observation: SimObservation
    reward: float
    terminated: bool
    truncated: bool


@runtime_checkable
class SimEnv(Protocol):
    """One simulator instance. Single-threaded: every call comes from the runner's tick thread."""

    spec: EnvSpec

    def reset(self, seed: int) -> SimObservation:
        """Start an episode whose every random draw comes from ``seed``."""
        ...

    def step(self, action: np.ndarray) -> SimStep:
        """Apply one action for one control period."""
        ...

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        """An ``(height, width, 3)`` RGB frame of the current state from ``camera``."""
        ...

    def close(self) -> None:
        """Free the simulator (and its renderers)."""
        ...


@runtime_checkable
class EndEffectorSensing(Protocol):
    """An env that knows where its end effector is: the optional capability the path-length metric reads.

    Decided once per runner (``isinstance``), never per step.
    """

    def end_effector_positions(self) -> np.ndarray:
        """Where the end effector(s) are after the last reset or step: ``(3,)`` or ``(effectors, 3)``, metres."""
        ...


class SimEnvPlugin(Protocol):
    """What the ``openral.sim_envs`` group holds: an adapter class with a ``from_scene`` classmethod."""

    def from_scene(self, scene: SimEnvironment) -> SimEnv:
        """Build the environment the scene names.

        Raises:
            ROSConfigError: A bad ``env_id``, ``env_kwargs`` or camera name, naming the field.
            ROSDependencyMissing: The simulator's package is not installed (naming the extra).
        """
        ...


SIM_ENV_REGISTRY: PluginRegistry[SimEnvPlugin] = PluginRegistry(
    SIM_ENVS_GROUP, kind="simulation environment", field="env"
)
"""Env name → adapter class (``Cls.from_scene(scene)``)."""


def make_env(scene: SimEnvironment) -> SimEnv:
    """The environment of ``scene``, from the ``openral.sim_envs`` plugin it names."""
    return SIM_ENV_REGISTRY.resolve(scene.env, field="env").from_scene(scene)
