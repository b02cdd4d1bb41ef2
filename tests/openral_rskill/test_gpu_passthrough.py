"""gpu_passthrough: refuses CUDA it cannot have, and reduces frames on the CPU when asked to."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from openral_core import JointState, ROSConfigError, ROSDependencyMissing, ROSSkillError, WorldState
from openral_hal.manifests import load_robot_manifest
from openral_rskill.chunks import ChunkRequest
from openral_rskill.gpu_passthrough import GpuPassthroughSkill
from openral_runner.frame_slot import frame_from_array

ROBOT = load_robot_manifest("so101_follower")


def _cuda_available() -> bool:
    if importlib.util.find_spec("torch") is None:
        return False
    import torch  # noqa: PLC0415

    return bool(torch.cuda.is_available())


@pytest.mark.skipif(_cuda_available(), reason="this machine has CUDA: the refusal cannot happen here")
def test_cuda_without_a_cuda_device_is_refused_at_configure() -> None:
    skill = GpuPassthroughSkill.from_config({"device": "cuda"}, robot=ROBOT, rate_hz=30)
    with pytest.raises(ROSSkillError) as caught:
        skill.configure()
    # No silent CPU fallback: the refusal says why (no PyTorch, or no CUDA device).
    assert isinstance(caught.value.__cause__, ROSConfigError | ROSDependencyMissing)
    assert skill.state.value == "error"


def test_the_cpu_path_reports_each_frames_channel_means_and_holds_the_pose() -> None:
    skill = GpuPassthroughSkill.from_config({"device": "cpu"}, robot=ROBOT, rate_hz=30)
    skill.configure()
    skill.activate()
    pixels = np.zeros((4, 6, 3), np.uint8)
    pixels[..., 0] = 10
    pixels[..., 2] = 200
    pixels[0, :, 1] = 60
    names = ROBOT.joint_names
    world = WorldState(
        stamp_ns=5,
        joint_state=JointState(names=names, positions=[0.1] * len(names)),
        image_frames={"cam": frame_from_array("cam", pixels, stamp_ns=1, seq=1)},
    )
    action = skill.step(world)
    assert action.confidence == pytest.approx([10.0, 15.0, 200.0])
    assert action.first == pytest.approx([0.1] * len(names))


def test_served_its_chunk_is_the_held_pose_as_one_array_after_the_same_device_work() -> None:
    skill = GpuPassthroughSkill.from_config({"device": "cpu"}, robot=ROBOT, rate_hz=30)
    skill.configure()
    skill.activate()
    names = ROBOT.joint_names
    pixels = np.full((2, 2, 3), 7, np.uint8)
    world = WorldState(
        stamp_ns=5,
        joint_state=JointState(names=names, positions=[0.2] * len(names)),
        image_frames={"cam": frame_from_array("cam", pixels, stamp_ns=1, seq=1)},
    )
    rows = skill.step_chunk(ChunkRequest(world))
    assert isinstance(rows, np.ndarray)
    assert rows.shape == (1, len(names))
    np.testing.assert_allclose(rows[0], [0.2] * len(names))
    assert skill.last_means == pytest.approx([7.0, 7.0, 7.0])
