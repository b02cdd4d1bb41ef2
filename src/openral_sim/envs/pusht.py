"""``pusht``: gym-pusht's Push-T table (``env_id`` ``gym_pusht/PushT-v0``), state observations.

A disc pushes a T-shaped block onto a fixed goal pose on a 512 × 512 table. The action is an
absolute target ``[x, y]`` in ``[0, 512]`` the disc is driven to by a PD controller (holding
repeats the last target); one action lasts 0.1 s of simulation, so ``control_hz`` is 10. The
state is the disc's position; privileged values are ``environment_state`` (the block's
``x, y, angle``), ``goal`` (the goal pose, same layout) and ``obs`` (gym-pusht's 5-d state
observation). Success is ``info["is_success"]`` (more than 95 % of the goal covered), with
``coverage`` beside it; the env terminates on success.

Each reset reseeds the env's generator with the episode's seed, so an episode depends on its
seed alone. The env is stepped directly, not through gymnasium's wrappers: the scene's
``max_steps`` is the one step limit (gym-pusht registers 300, which LeRobot's evaluations use),
and no passive checker runs every step.

The one camera, ``top``, is the table seen from above: the image gym-pusht's ``pixels``
observation shows (no action marker), drawn at 512 × 512 and resized to the requested size.
"""

from __future__ import annotations

import warnings
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import ROSConfigError, ROSDependencyMissing, SimEnvironment
from openral_core.config import validate_model
from openral_sim.env import EnvSpec, SimObservation, SimStep

try:
    with warnings.catch_warnings():
        # pygame (under gym-pusht) imports setuptools' deprecated pkg_resources when it is installed.
        warnings.filterwarnings("ignore", message="pkg_resources is deprecated", category=UserWarning)
        from gym_pusht.envs.pusht import PushTEnv as _GymPushTEnv
except ImportError as exc:
    # gym-pusht draws with OpenCV; openral installs OpenCV's headless build through the extra 'opencv'.
    missing = exc.name or "gym_pusht"
    extra = "opencv" if missing == "cv2" else "sim"
    raise ROSDependencyMissing(missing, extra=extra, needed_for="the Push-T environment") from exc

TASK = "gym_pusht/PushT-v0"
CAMERA = "top"
TABLE_SIZE = 512.0
CONTROL_HZ = 10.0
"""gym-pusht's fixed control rate (``metadata["render_fps"]``): ten 10 ms physics steps per action."""

_DEFAULT_IMAGE_SIZE = 96


class PushTParams(BaseModel):
    """``env_kwargs`` of the ``pusht`` environment (gym-pusht's own physics options)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    damping: float | None = Field(default=None, ge=0, description="Space damping; gym-pusht's default is none.")
    block_cog: tuple[float, float] | None = Field(
        default=None, description="The block's centre of gravity in its own frame; by default its origin."
    )


class PushTEnv:
    """One Push-T table, state observations, seeded block and disc start poses."""

    def __init__(self, params: PushTParams | None = None) -> None:
        self.params = params or PushTParams()
        self._env: Any = _GymPushTEnv(
            obs_type="state",
            render_mode="rgb_array",
            block_cog=self.params.block_cog,
            damping=self.params.damping,
            observation_width=_DEFAULT_IMAGE_SIZE,
            observation_height=_DEFAULT_IMAGE_SIZE,
        )
        self.spec = EnvSpec(
            state_names=("agent_x", "agent_y"),
            action_names=("x", "y"),
            action_low=(0.0, 0.0),
            action_high=(TABLE_SIZE, TABLE_SIZE),
            action_kind="absolute",
            control_hz=CONTROL_HZ,
            environment_state_names=("block_x", "block_y", "block_angle"),
        )

    @classmethod
    def from_scene(cls, scene: SimEnvironment) -> Self:
        """The Push-T table, with the scene's task and cameras checked.

        Raises:
            ROSConfigError: An ``env_id`` other than ``gym_pusht/PushT-v0``, a bad ``env_kwargs``
                key, or a camera other than ``top``.
        """
        if scene.env_id not in (None, TASK):
            raise ROSConfigError(f"gym-pusht has one task, {TASK!r}, not {scene.env_id!r}", field="env_id")
        for camera in scene.cameras:
            if camera.name != CAMERA:
                raise ROSConfigError(
                    f"Push-T has no camera {camera.name!r}", field="cameras", hint=f"choose from {[CAMERA]}"
                )
        return cls(validate_model(PushTParams, scene.env_kwargs, field_prefix="env_kwargs"))

    def reset(self, seed: int) -> SimObservation:
        obs, info = self._env.reset(seed=seed)
        return self._observe(obs, is_success=bool(info["is_success"]), coverage=None)

    def step(self, action: np.ndarray) -> SimStep:
        target = np.clip(np.asarray(action, dtype=np.float64), 0.0, TABLE_SIZE)
        obs, reward, terminated, truncated, info = self._env.step(target)
        observation = self._observe(obs, is_success=bool(info["is_success"]), coverage=float(info["coverage"]))
        return SimStep(observation, reward=float(reward), terminated=bool(terminated), truncated=bool(truncated))

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        """An ``(height, width, 3)`` RGB frame of the table seen from above.

        Raises:
            ROSConfigError: ``camera`` is not ``top``.
        """
        if camera != CAMERA:
            raise ROSConfigError(f"Push-T has no camera {camera!r}", field="cameras", hint=f"choose from {[CAMERA]}")
        env = self._env
        env.observation_width, env.observation_height = width, height
        # What gym-pusht's ``pixels`` observation returns: the table without the action marker.
        frame = env._render(visualize=False)
        return np.ascontiguousarray(frame, dtype=np.uint8)

    def close(self) -> None:
        self._env.close()

    def _observe(self, obs: np.ndarray, *, is_success: bool, coverage: float | None) -> SimObservation:
        obs = np.asarray(obs, dtype=np.float64)
        info: dict[str, Any] = {"is_success": is_success}
        if coverage is not None:
            info["coverage"] = coverage
        return SimObservation(
            state=obs[:2].copy(),
            privileged={
                "obs": obs.tolist(),
                "environment_state": obs[2:5].tolist(),
                "goal": [float(v) for v in self._env.goal_pose],
            },
            info=info,
        )
