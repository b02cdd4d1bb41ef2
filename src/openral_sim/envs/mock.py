"""``mock``: a tiny deterministic reaching task, for fast tests and for trying the tools without a simulator.

A point on the unit square must reach a target drawn from the episode's seed. The action is a
``[dx, dy]`` step in ``[-1, 1]`` (scaled by ``step_size``); success (``info["is_success"]``) is
being within ``tolerance`` of the target, with reward ``-distance``. Its one camera, ``top``,
draws the point and the target.
"""

from __future__ import annotations

from typing import Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import ROSConfigError, SimEnvironment
from openral_core.config import validate_model
from openral_sim.env import EnvSpec, SimObservation, SimStep

CAMERA = "top"


class MockParams(BaseModel):
    """``env_kwargs`` of the ``mock`` environment."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    step_size: float = Field(default=0.05, gt=0, le=1)
    tolerance: float = Field(default=0.05, gt=0)
    success_key: str = Field(default="is_success", description="The info key success is reported under.")
    control_hz: float = Field(default=10.0, gt=0)


class MockReachEnv:
    """A point reaching a seeded target; ``target`` and ``position`` are its privileged values."""

    def __init__(self, params: MockParams | None = None) -> None:
        self.params = params or MockParams()
        self.spec = EnvSpec(
            state_names=("x", "y"),
            action_names=("dx", "dy"),
            action_low=(-1.0, -1.0),
            action_high=(1.0, 1.0),
            action_kind="delta",
            control_hz=self.params.control_hz,
            environment_state_names=("target_x", "target_y"),
        )
        self._position = np.zeros(2)
        self._target = np.zeros(2)

    @classmethod
    def from_scene(cls, scene: SimEnvironment) -> Self:
        if scene.env_id not in (None, "reach"):
            raise ROSConfigError(f"the mock environment has one task, 'reach', not {scene.env_id!r}", field="env_id")
        for camera in scene.cameras:
            if camera.name != CAMERA:
                raise ROSConfigError(f"the mock environment has one camera, {CAMERA!r}", field="cameras")
        return cls(validate_model(MockParams, scene.env_kwargs, field_prefix="env_kwargs"))

    def reset(self, seed: int) -> SimObservation:
        rng = np.random.default_rng(seed)
        self._position = rng.uniform(0.1, 0.9, size=2)
        self._target = rng.uniform(0.1, 0.9, size=2)
        return self._observe()

    def step(self, action: np.ndarray) -> SimStep:
        move = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0) * self.params.step_size
        self._position = np.clip(self._position + move, 0.0, 1.0)
        observation = self._observe()
        distance = float(np.linalg.norm(self._target - self._position))
        success = distance < self.params.tolerance
        return SimStep(observation, reward=-distance, terminated=success, truncated=False)

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        image = np.full((height, width, 3), 40, np.uint8)
        for point, colour in ((self._target, (220, 40, 40)), (self._position, (40, 220, 40))):
            col = int(point[0] * (width - 1))
            row = int((1.0 - point[1]) * (height - 1))
            image[max(row - 2, 0) : row + 3, max(col - 2, 0) : col + 3] = colour
        return image

    def close(self) -> None:
        pass

    def _observe(self) -> SimObservation:
        distance = float(np.linalg.norm(self._target - self._position))
        return SimObservation(
            state=self._position.copy(),
            privileged={
                "target": self._target.tolist(),
                "position": self._position.tolist(),
                "environment_state": self._target.tolist(),
            },
            info={self.params.success_key: distance < self.params.tolerance},
        )
