"""``aloha``: gym-aloha's bimanual ViperX tasks (``env_id`` ``AlohaTransferCube-v0`` or ``AlohaInsertion-v0``).

Two ViperX 300 arms on one table: the right arm picks a cube and hands it to the left
(transfer cube), or each arm picks one part and the peg goes into the socket (insertion). The
action is 14 absolute targets in the order of the ``aloha_bimanual_viperx`` manifest: each
arm's six joint angles (radians) and its gripper opening (0 closed, 1 open), left arm first;
one action lasts 20 ms (ten 2 ms physics steps), so ``control_hz`` is 50. The state is the same
14 values measured. Privileged values: ``environment_state`` (the objects' free-joint poses,
``x y z qw qx qy qz`` each) and ``qpos`` (the model's whole ``qpos``, fingers included) that the
scripted experts plan from. Success is gym-aloha's: the task's reward reaches 4 (the left
gripper holds the cube off the table; the peg touches the socket's pin), passed on as
``is_success`` with ``reward`` beside it; the env terminates on success. A step whose physics
diverges (targets flung across the joint ranges can do it) terminates the episode as a failure
with ``physics_error`` in ``info`` and the last sound observation, instead of raising.

The physics, the assets, the object sampling and the reward are gym-aloha's own task classes;
what this adapter changes is rendering. gym-aloha's ``get_observation`` renders three 480 × 640
cameras every step and returns one, about 200 ms a step; here a step renders nothing and
``render`` draws only the cameras the scene lists, at the scene's size, with the renderer the
other MuJoCo envs use (shadows and reflections off, so frames look flatter than gym-aloha's).

Episodes: reset with seed ``s`` places the objects where gym-aloha's ``reset(seed=s)`` does
(``sample_box_pose(s)``, ``sample_insertion_pose(s)``), so an episode depends on its seed alone
and matches the package's for the same seed. gym-aloha registers 300 steps; the scene's
``max_steps`` is the one limit. Measured on MuJoCo 3.17.0 with dm_control 1.0.50.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import ROSConfigError, ROSDependencyMissing, SimEnvironment
from openral_core.config import validate_model
from openral_hal import load_robot_manifest
from openral_sim.env import EnvSpec, SimObservation, SimStep

try:
    import mujoco  # noqa: F401  (the renderer below needs it; name the extra that installs it)
except ImportError as exc:
    raise ROSDependencyMissing("mujoco", extra="aloha", needed_for="the ALOHA tasks") from exc

from openral_runner.backends.mujoco_render import GLBackend, resolve_gl_backend

# dm_control picks its OpenGL platform once, at import, from MUJOCO_GL (probing GLFW, which warns
# without a display, when unset). This adapter renders with openral's own renderer; dm_control
# only needs to agree with it.
os.environ.setdefault("MUJOCO_GL", resolve_gl_backend(None))

try:
    from dm_control import mujoco as dm_mujoco
    from dm_control.rl.control import PhysicsError
    from gym_aloha.constants import ASSETS_DIR, DT, START_ARM_POSE, normalize_puppet_gripper_position
    from gym_aloha.tasks.sim import InsertionTask, TransferCubeTask
    from gym_aloha.utils import sample_box_pose, sample_insertion_pose
except ImportError as exc:
    raise ROSDependencyMissing(exc.name or "gym_aloha", extra="aloha", needed_for="the ALOHA tasks") from exc

from openral_sim.envs.mujoco_views import MujocoViews, check_cameras

ROBOT_ID = "aloha_bimanual_viperx"
SUCCESS_REWARD = 4
_ROBOT_QPOS = 16
"""The robot's entries at the front of ``qpos``: per arm six joints and two fingers."""
_GRIPPER_BODIES = ("vx300s_left/gripper_link", "vx300s_right/gripper_link")
"""The bodies whose positions are the arms' end effectors."""


@dataclass(frozen=True)
class AlohaTask:
    """One gym-aloha task: its model file, its task class and how reset places its objects."""

    xml: str
    task_class: type[Any]
    objects: tuple[str, ...]

    def object_pose(self, seed: int) -> np.ndarray:
        """The objects' free-joint poses for episode ``seed``, drawn as gym-aloha's reset draws them."""
        if self.task_class is TransferCubeTask:
            return np.asarray(sample_box_pose(seed), dtype=np.float64)
        return np.concatenate(sample_insertion_pose(seed)).astype(np.float64)


TASKS: dict[str, AlohaTask] = {
    "AlohaTransferCube-v0": AlohaTask("bimanual_viperx_transfer_cube.xml", TransferCubeTask, ("cube",)),
    "AlohaInsertion-v0": AlohaTask("bimanual_viperx_insertion.xml", InsertionTask, ("peg", "socket")),
}
"""gym-aloha's joint-space tasks by the id it registers them under (``gym_aloha/`` prefix optional)."""


class AlohaParams(BaseModel):
    """``env_kwargs`` of the ``aloha`` environment."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    gl: GLBackend | None = Field(
        default=None, description="OpenGL backend for camera renders; by default the process's (egl if available)."
    )


def task_of(env_id: str | None) -> AlohaTask:
    """The task ``env_id`` names, with or without gym-aloha's ``gym_aloha/`` prefix.

    Raises:
        ROSConfigError: Naming ``env_id`` and the tasks there are.
    """
    name = (env_id or "").removeprefix("gym_aloha/")
    if name not in TASKS:
        raise ROSConfigError(f"gym-aloha has no task {env_id!r}", field="env_id", hint=f"choose from {sorted(TASKS)}")
    return TASKS[name]


class AlohaEnv:
    """One gym-aloha task on its dm_control physics, rendering only on request."""

    def __init__(self, env_id: str, params: AlohaParams | None = None) -> None:
        self.task = task_of(env_id)
        self.params = params or AlohaParams()
        self._physics: Any = dm_mujoco.Physics.from_xml_path(str(ASSETS_DIR / self.task.xml))
        self._task: Any = self.task.task_class()
        self._substeps = round(DT / float(self._physics.timestep()))
        manifest = load_robot_manifest(ROBOT_ID)
        names = tuple(manifest.joint_names)
        self.spec = EnvSpec(
            state_names=names,
            action_names=names,
            action_low=tuple(j.lower for j in manifest.joints),
            action_high=tuple(j.upper for j in manifest.joints),
            action_kind="absolute",
            control_hz=1.0 / DT,
            environment_state_names=tuple(
                f"{obj}_{axis}" for obj in self.task.objects for axis in ("x", "y", "z", "qw", "qx", "qy", "qz")
            ),
        )
        self._low, self._high = np.array(self.spec.action_low), np.array(self.spec.action_high)
        self._last = SimObservation(state=np.zeros(len(names)))
        self._views = MujocoViews(self.model, self._physics.data.ptr, env=f"gym-aloha {env_id}", gl=self.params.gl)

    @property
    def model(self) -> Any:
        """The task's ``mujoco.MjModel``."""
        return self._physics.model.ptr

    @classmethod
    def from_scene(cls, scene: SimEnvironment) -> Self:
        """The task ``scene.env_id`` names, with the scene's cameras checked against the model's.

        Raises:
            ROSConfigError: An unknown ``env_id``, a bad ``env_kwargs`` key, or a camera the model
                lacks (listing the ones it has).
        """
        params = validate_model(AlohaParams, scene.env_kwargs, field_prefix="env_kwargs")
        env = cls(scene.env_id or "", params)
        try:
            check_cameras(env.model, [c.name for c in scene.cameras], env=f"gym-aloha {scene.env_id}")
        except ROSConfigError:
            env.close()
            raise
        return env

    def reset(self, seed: int) -> SimObservation:
        physics = self._physics
        with physics.reset_context():
            physics.data.qpos[:_ROBOT_QPOS] = START_ARM_POSE
            physics.data.ctrl[:] = START_ARM_POSE
            physics.data.qpos[_ROBOT_QPOS:] = self.task.object_pose(seed)
        return self._observe(reward=0)

    def step(self, action: np.ndarray) -> SimStep:
        command = np.clip(np.asarray(action, dtype=np.float64), self._low, self._high)
        self._task.before_step(command, self._physics)
        try:
            for _ in range(self._substeps):
                self._physics.step()
        except PhysicsError as exc:
            # Targets that jump across the joint range each step can make the solver diverge. The
            # episode ends there, failed, with the last sound observation: one wild policy must not
            # end the whole evaluation, nor put NaN into a recording.
            last = self._last
            info = {**last.info, "is_success": False, "physics_error": str(exc)}
            observation = SimObservation(state=last.state, privileged=last.privileged, info=info)
            return SimStep(observation, reward=0.0, terminated=True, truncated=False)
        self._task.after_step(self._physics)
        reward = int(self._task.get_reward(self._physics))
        success = reward >= SUCCESS_REWARD
        return SimStep(self._observe(reward=reward), reward=float(reward), terminated=success, truncated=False)

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        return self._views.render(camera, width, height)

    def end_effector_positions(self) -> np.ndarray:
        """Both grippers' link origins in the world, left arm first: ``(2, 3)``, metres."""
        return np.array(self._physics.named.data.xpos[list(_GRIPPER_BODIES)], dtype=np.float64)

    def close(self) -> None:
        self._views.close()
        self._physics.free()

    def _observe(self, *, reward: int) -> SimObservation:
        qpos = np.array(self._physics.data.qpos, dtype=np.float64)
        state = np.concatenate(
            [
                qpos[0:6],
                [normalize_puppet_gripper_position(qpos[6])],
                qpos[8:14],
                [normalize_puppet_gripper_position(qpos[14])],
            ]
        )
        observation = SimObservation(
            state=state,
            privileged={"qpos": qpos.tolist(), "environment_state": qpos[_ROBOT_QPOS:].tolist()},
            info={"is_success": reward >= SUCCESS_REWARD, "reward": reward},
        )
        self._last = observation
        return observation
