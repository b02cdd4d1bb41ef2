"""``metaworld``: the 50 MetaWorld v3 tasks (Sawyer arm, ``env_id`` such as ``pick-place-v3``).

The action is ``[dx, dy, dz, grip]`` in ``[-1, 1]``: a move of the hand's mocap target (a delta,
1 cm per unit; holding is zero motion with the grip command kept) and an absolute grip effort. The
env steps ``frame_skip`` (5) physics steps of 2.5 ms: 12.5 ms per action, so ``control_hz`` is
80. The state is what the robot knows: hand position and gripper opening (the observation's
first 4 values). Privileged values: ``obs``, the full 39-d observation the scripted experts read
(current frame, previous frame, goal), and ``environment_state``, its object and goal part (two
padded object poses, 14 values, then the goal position, 3). Success is ``info["success"]``, a
float, passed on as MetaWorld reports it; MetaWorld never terminates an episode.

Episodes: reset with seed ``s`` reseeds the env's own generator with ``s`` and draws the task's
object and goal positions from it (the goal-observable MT1 set-up with an unfrozen, seeded random
vector), so an episode depends on its seed alone, whatever ran on the instance before. MetaWorld's
500-step horizon is lifted: the scene's ``max_steps`` is the one step limit, and the env is
stepped directly, not through gymnasium's wrappers (no passive checker, no time limit).

MuJoCo compatibility: metaworld 3.0.0's ``SawyerMocapBase.reset_mocap_welds`` writes an 11-value
row into ``model.eq_data``, whose weld rows have 12 values in MuJoCo 3.17, so constructing any
task fails with a broadcast error. Importing this module replaces that one method with one that
writes the same 11 values into the first 11 entries of each weld row and leaves the rest at
MuJoCo's defaults; on older MuJoCo (11-value rows) it does exactly what the original did.

Cameras are the model's named cameras (``topview``, ``corner``, ``corner2``, ``corner3``,
``behindGripper``, ``gripperPOV``), rendered headless on first use. Frames are oriented as
MetaWorld's own renderer gives them: the ``corner`` views come out upside down.
"""

from __future__ import annotations

import difflib
import pickle
import sys
from typing import Any, Literal, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import ROSConfigError, ROSDependencyMissing, ROSRuntimeError, SimEnvironment
from openral_core.config import validate_model
from openral_sim.env import EnvSpec, SimObservation, SimStep
from openral_sim.envs.mujoco_views import MujocoViews, check_cameras

try:
    import mujoco
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS
    from metaworld.sawyer_xyz_env import SawyerMocapBase, SawyerXYZEnv
    from metaworld.types import Task
except ImportError as exc:
    raise ROSDependencyMissing(exc.name or "metaworld", extra="sim", needed_for="the MetaWorld tasks") from exc

TASKS: tuple[str, ...] = tuple(ALL_V3_ENVIRONMENTS)
"""The task ids ``env_id`` may name."""

_WELD_DATA = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0])
_STATE_DIM = 4
_OBJECT_SLICE = slice(4, 18)
_GOAL_SLICE = slice(36, 39)
_OBS_DIM = 39


def _reset_mocap_welds(self: Any) -> None:
    """Reset the mocap welds as metaworld does, writing only the 11 entries it knows of each weld row."""
    model = self.model
    if model.nmocap > 0 and model.eq_data is not None:
        for i in range(model.eq_data.shape[0]):
            if model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                model.eq_data[i, : _WELD_DATA.size] = _WELD_DATA


SawyerMocapBase.reset_mocap_welds = _reset_mocap_welds  # type: ignore[method-assign]


def _environment_state_names() -> tuple[str, ...]:
    names: list[str] = []
    for obj in range(2):
        names += [f"obj{obj}_{axis}" for axis in ("x", "y", "z")]
        names += [f"obj{obj}_q{i}" for i in range(4)]
    return (*names, "goal_x", "goal_y", "goal_z")


class MetaWorldParams(BaseModel):
    """``env_kwargs`` of the ``metaworld`` environment."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    reward_function_version: Literal["v1", "v2"] = Field(default="v2", description="MetaWorld's reward shaping.")
    gl: Literal["egl", "osmesa"] | None = Field(
        default=None, description="OpenGL backend for camera renders; by default the process's (egl if available)."
    )


class MetaWorldEnv:
    """One MetaWorld v3 task, goal observable, with seeded object and goal positions."""

    def __init__(self, task: str, params: MetaWorldParams | None = None) -> None:
        if task not in ALL_V3_ENVIRONMENTS:
            raise ROSConfigError(f"MetaWorld has no task {task!r}", field="env_id", hint=_task_hint(task))
        self.task = task
        self.params = params or MetaWorldParams()
        env_class = ALL_V3_ENVIRONMENTS[task]
        env: SawyerXYZEnv = env_class(reward_function_version=self.params.reward_function_version)
        reset_space = env._random_reset_space
        assert reset_space is not None
        # The MT1 task encoding, goal observable; its random vector is a placeholder, drawn anew at every reset.
        data = {
            "rand_vec": (reset_space.low + reset_space.high) / 2,
            "env_cls": env_class,
            "partially_observable": False,
        }
        env.set_task(Task(env_name=task, data=pickle.dumps(data)))  # MetaWorld's own task format, made here
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        env.max_path_length = sys.maxsize
        self._env = env
        self.spec = EnvSpec(
            state_names=("hand_x", "hand_y", "hand_z", "gripper_distance"),
            action_names=("dx", "dy", "dz", "grip"),
            action_low=(-1.0, -1.0, -1.0, -1.0),
            action_high=(1.0, 1.0, 1.0, 1.0),
            action_kind="delta",
            control_hz=1.0 / float(env.dt),
            hold_dims=(3,),
            environment_state_names=_environment_state_names(),
        )
        # Tasks move bodies and sites in the model itself at reset (goal markers, drawers, doors).
        self._views = MujocoViews(
            self._env.model, self._env.data, env=f"MetaWorld task {task!r}", gl=self.params.gl, moves_model=True
        )

    @classmethod
    def from_scene(cls, scene: SimEnvironment) -> Self:
        """The task ``scene.env_id`` names, with the scene's cameras checked against the model's.

        Raises:
            ROSConfigError: An unknown ``env_id`` (naming the closest tasks), a bad ``env_kwargs``
                key, or a camera the model lacks (listing the ones it has).
        """
        if scene.env_id is None:
            raise ROSConfigError("the metaworld environment needs a task", field="env_id", hint=_task_hint(""))
        params = validate_model(MetaWorldParams, scene.env_kwargs, field_prefix="env_kwargs")
        env = cls(scene.env_id, params)
        try:
            check_cameras(env._env.model, [c.name for c in scene.cameras], env=f"MetaWorld task {scene.env_id!r}")
        except ROSConfigError:
            env.close()
            raise
        return env

    def reset(self, seed: int) -> SimObservation:
        self._env.seed(seed)
        obs, info = self._env.reset()
        return self._observe(obs, info)

    def step(self, action: np.ndarray) -> SimStep:
        command = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        obs, reward, terminated, _, info = self._env.step(command)
        return SimStep(self._observe(obs, info), reward=float(reward), terminated=bool(terminated), truncated=False)

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        return self._views.render(camera, width, height)

    def end_effector_positions(self) -> np.ndarray:
        """The hand's position in the world (the state's first three values), metres."""
        return np.array(self._env.get_endeff_pos(), dtype=np.float64)

    def close(self) -> None:
        self._views.close()
        self._env.close()  # type: ignore[no-untyped-call]

    def _observe(self, obs: np.ndarray, info: dict[str, Any]) -> SimObservation:
        obs = np.asarray(obs, dtype=np.float64)
        if obs.shape != (_OBS_DIM,):
            raise ROSRuntimeError(f"MetaWorld task {self.task!r} returned an observation of shape {obs.shape}")
        environment_state = np.concatenate([obs[_OBJECT_SLICE], obs[_GOAL_SLICE]])
        return SimObservation(
            state=obs[:_STATE_DIM].copy(),
            privileged={"obs": obs.tolist(), "environment_state": environment_state.tolist()},
            info={key: _plain(value) for key, value in info.items()},
        )


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python number it holds; anything else unchanged."""
    return value.item() if isinstance(value, np.generic) else value


def _task_hint(task: str) -> str:
    close = difflib.get_close_matches(task, TASKS, n=3)
    return f"did you mean {' or '.join(repr(c) for c in close)}?" if close else f"choose from {sorted(TASKS)}"
