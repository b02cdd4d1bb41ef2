"""``gpu_passthrough``: a weight-less skill that proves where a skill's compute runs.

Each step it moves every camera frame of the world state to the configured device, reduces it to
per-channel means there, waits for the device to finish (so the inference span covers the real
work, not only its dispatch), and reports the means as the action's confidence while holding the
pose measured at the episode's start. ``device: cuda`` needs PyTorch with a CUDA device:
``configure()`` refuses to start without one, never falling back to the CPU in silence.
``device: cpu`` computes the same means with numpy. ``configure()`` warms the device up (a VGA
frame reduced three times), so the first tick does not pay for the CUDA context and kernels.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal, Self

import numpy as np
from pydantic import BaseModel, ConfigDict

from openral_core import (
    Action,
    ControlMode,
    RobotManifest,
    ROSConfigError,
    ROSDependencyMissing,
    RSkillInfo,
    WorldState,
)
from openral_rskill.base import RSkillBase, validate_params
from openral_rskill.chunks import ChunkRequest
from openral_rskill.pose import clamp_to_limits, measured_pose

SKILL_ID = "gpu_passthrough"


class GpuPassthroughParams(BaseModel):
    """``params`` of the ``gpu_passthrough`` skill."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    device: Literal["cuda", "cpu"] = "cuda"


class GpuPassthroughSkill(RSkillBase):
    """Per-channel means of every frame, computed on ``device``; holds the pose."""

    INFO = RSkillInfo(
        skill_id=SKILL_ID,
        name="GPU passthrough",
        version="1.0.0",
        control_mode=ControlMode.JOINT_POSITION,
        description="Moves each frame to the accelerator, reduces it there, and holds the pose.",
    )

    def __init__(self, robot: RobotManifest, params: GpuPassthroughParams) -> None:
        super().__init__()
        self.robot = robot
        self.device = params.device
        self._torch: Any = None
        self._pose: list[float] | None = None
        self._rows = np.zeros((0, len(robot.joint_names)))
        self.last_means: list[float] = []

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(GpuPassthroughParams, params, skill_id=SKILL_ID))

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _on_configure(self) -> None:
        if self.device == "cpu":
            return
        try:
            import torch  # noqa: PLC0415 - PyTorch with CUDA, installed for the driver by hand
        except ImportError as exc:
            raise ROSDependencyMissing(
                "torch",
                extra=None,
                needed_for="gpu_passthrough on device cuda",
                install="install PyTorch with CUDA for your driver (https://pytorch.org), e.g. uv pip install torch",
            ) from exc
        if not torch.cuda.is_available():
            raise ROSConfigError(
                "device cuda was asked for, but PyTorch sees no CUDA device",
                field="vla.params.device",
                hint="run on a machine with a CUDA GPU, or set device: cpu explicitly",
            )
        self._torch = torch
        warm = np.zeros((480, 640, 3), dtype=np.uint8)
        for _ in range(3):  # CUDA context, kernels and allocator now: the first tick must not pay for them
            self.channel_means(warm)

    def _on_reset(self) -> None:
        self._pose = None

    def _on_activate(self) -> None:
        self._pose = None

    def channel_means(self, pixels: np.ndarray) -> list[float]:
        """Per-channel means of one ``(H, W[, C])`` frame, computed on the device."""
        torch = self._torch
        if torch is None:
            data = pixels.reshape(pixels.shape[0], pixels.shape[1], -1)
            return [float(v) for v in data.mean(axis=(0, 1))]
        tensor = torch.from_numpy(np.ascontiguousarray(pixels)).to("cuda", non_blocking=True)
        means = tensor.reshape(tensor.shape[0], tensor.shape[1], -1).float().mean(dim=(0, 1))
        torch.cuda.synchronize()
        return [float(v) for v in means.cpu()]

    def _measure(self, world_state: WorldState) -> list[float]:
        """Reduce every frame on the device (kept in :attr:`last_means`); latch the pose at the episode's start."""
        means: list[float] = []
        for frame in (world_state.image_frames or {}).values():
            means.extend(self.channel_means(frame.as_array()))
        self.last_means = means
        if self._pose is None:
            self._pose = clamp_to_limits(measured_pose(world_state, self.robot.joint_names), self.robot)
            self._rows = np.array([self._pose], dtype=np.float64)
            self._rows.flags.writeable = False
        return self._pose

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The held pose as a one-row chunk, after the same device work as :meth:`step` (served, it is what replies)."""
        self._measure(request.world)
        return self._rows

    def _step_impl(self, world_state: WorldState) -> Action:
        pose = self._measure(world_state)
        return Action(
            control_mode=ControlMode.JOINT_POSITION,
            joint_names=self.robot.joint_names,
            targets=[pose],
            confidence=self.last_means or None,
            stamp_ns=world_state.stamp_ns,
            skill_id=SKILL_ID,
        )
