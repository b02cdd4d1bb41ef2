"""A served LeRobot Diffusion checkpoint is the same policy as the local one, robot by robot.

A tiny Diffusion policy reading two observations (``n_obs_steps=2``) is built offline, then run
behind the chunk executor (virtual delay: inline and reproducible) over short seeded episodes, once
locally and once through a real in-process policy server and the ``remote_policy`` skill on
loopback. The history, the prefix and the episode's seed travel with each request, so the chunks
must be equal, bit for bit; and robots sharing the server must each get what they would alone.
Needs the ``lerobot`` extra (Python 3.12 or newer) and the ``remote`` extra.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

torch = pytest.importorskip("torch", reason=LEROBOT_REASON)
pytest.importorskip("lerobot", reason=LEROBOT_REASON)
pytest.importorskip("zenoh", reason="needs the 'remote' extra")

from lerobot.configs.types import FeatureType, PolicyFeature  # noqa: E402
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # noqa: E402
from lerobot.policies.factory import get_policy_class, make_pre_post_processors  # noqa: E402

from openral_core import ExecutorConfig, FrameEncoding, JointState, SensorFrame, WorldState  # noqa: E402
from openral_hal.manifests import load_robot_manifest  # noqa: E402
from openral_remote.config import ZenohConfig  # noqa: E402
from openral_remote.keys import PolicyKeys  # noqa: E402
from openral_remote.meta import describe, model_hash  # noqa: E402
from openral_remote.server import PolicyServer  # noqa: E402
from openral_remote.skill import RemotePolicySkill  # noqa: E402
from openral_remote.testing import free_endpoint  # noqa: E402
from openral_rskill.base import RSkillBase  # noqa: E402
from openral_rskill.chunks import ChunkRequest  # noqa: E402
from openral_rskill.executor import ChunkedExecutor  # noqa: E402
from openral_rskill.lerobot_policy import LeRobotPolicySkill  # noqa: E402

pytestmark = pytest.mark.timeout(300)

SO101 = load_robot_manifest("so101_follower")
HEIGHT, WIDTH = 48, 64
RATE_HZ = 30.0
TICKS = 14
"""Ticks per episode: three requests of an 8-row chunk with a two-tick delay."""


def _stats(dim: int) -> dict[str, Any]:
    """Normalisation statistics of a camera's three channels, or of a ``dim``-vector."""
    if dim == 3:
        mean, std = torch.full((3, 1, 1), 0.5), torch.full((3, 1, 1), 0.25)
    else:
        mean, std = torch.zeros(dim), torch.full((dim,), 0.5)
    return {"mean": mean, "std": std, "min": mean - 3 * std, "max": mean + 3 * std}


def _diffusion(folder: Path) -> Path:
    inputs = {
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
        "observation.images.front": PolicyFeature(type=FeatureType.VISUAL, shape=(3, HEIGHT, WIDTH)),
    }
    config = DiffusionConfig(
        input_features=inputs,
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
        n_obs_steps=2,
        horizon=16,
        n_action_steps=8,
        down_dims=(32, 64),
        kernel_size=3,
        n_groups=4,
        diffusion_step_embed_dim=32,
        spatial_softmax_num_keypoints=16,
        noise_scheduler_type="DDIM",
        num_inference_steps=3,
        device="cpu",
        pretrained_backbone_weights=None,
    )
    torch.manual_seed(0)
    policy = get_policy_class(config.type)(config)
    stats = {key: _stats(feature.shape[0]) for key, feature in {**inputs, **config.output_features}.items()}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def params(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = _diffusion(tmp_path_factory.mktemp("served") / "diffusion")
    return {"path": str(folder), "device": "cpu", "warmup_inferences": 1, "threads": 1}


@pytest.fixture(scope="module")
def local(params: dict[str, Any]) -> Iterator[LeRobotPolicySkill]:
    skill = LeRobotPolicySkill.from_config(params, robot=SO101, rate_hz=RATE_HZ)
    skill.configure()
    skill.activate()
    yield skill
    skill.shutdown()


@pytest.fixture(scope="module")
def server(params: dict[str, Any]) -> Iterator[tuple[PolicyServer, dict[str, Any]]]:
    """A policy server of the checkpoint on loopback, and the ``remote_policy`` parameters that reach it."""
    served = LeRobotPolicySkill.from_config(params, robot=SO101, rate_hz=RATE_HZ)
    keys = PolicyKeys.of(SO101.robot_id, "diffusion")
    meta = describe(
        served,
        policy=keys.policy,
        robot=SO101.robot_id,
        action_names=SO101.joint_names,
        rate_hz=RATE_HZ,
        model_hash=model_hash("lerobot_policy", params),
    )
    endpoint = free_endpoint()
    remote = {"policy": keys.policy, "zenoh": {"connect": [endpoint]}, "deadline_ms": 30_000, "connect_timeout_s": 60}
    with PolicyServer(served, keys=keys, zenoh=ZenohConfig(listen=[endpoint]), meta=meta) as running:
        yield running, remote


@pytest.fixture
def remote_skill(server: tuple[PolicyServer, dict[str, Any]]) -> Iterator[Callable[[], RemotePolicySkill]]:
    made: list[RemotePolicySkill] = []

    def build() -> RemotePolicySkill:
        skill = RemotePolicySkill.from_config(server[1], robot=SO101, rate_hz=RATE_HZ)
        made.append(skill)
        skill.configure()
        skill.activate()
        return skill

    yield build
    for skill in made:
        skill.shutdown()


def _world(stream: int, tick: int) -> WorldState:
    """What a robot observes: a function of its stream and the tick alone."""
    rng = np.random.default_rng([stream, tick])
    rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    stamp = 1 + tick
    frame = SensorFrame(
        sensor_id="front", stamp_ns=stamp, width=WIDTH, height=HEIGHT, encoding=FrameEncoding.RGB8, data=rgb
    )
    positions = rng.uniform(-0.5, 0.5, 6).tolist()
    return WorldState(
        stamp_ns=stamp,
        joint_state=JointState(names=SO101.joint_names, positions=positions, stamp_ns=stamp),
        image_frames={"front": frame},
        task="pick the cube",
    )


class _Robot:
    """One robot's loop: a skill behind a chunk executor (virtual delay), every chunk and request kept."""

    def __init__(self, skill: RSkillBase, stream: int) -> None:
        self.stream = stream
        self.chunks: list[np.ndarray] = []
        self.requests: list[ChunkRequest] = []
        infer = skill.step_chunk

        def recorded(request: ChunkRequest) -> np.ndarray:
            self.requests.append(request)
            self.chunks.append(np.array(infer(request)))
            return self.chunks[-1]

        skill.step_chunk = recorded  # type: ignore[method-assign]
        self.skill = skill
        self.executor = ChunkedExecutor.for_skill(
            skill, ExecutorConfig(), action_names=SO101.joint_names, virtual_delay=lambda _index: 2
        )
        self.ticks = 0
        """Ticks so far: a runner's tick index runs on across episodes."""

    def reset(self, seed: int) -> None:
        self.executor.reset(run=lambda: self.skill.reset(seed=seed))

    def tick(self) -> None:
        self.executor.step(self.ticks, _world(self.stream, self.ticks))
        self.ticks += 1

    def run(self, seeds: Sequence[int]) -> list[np.ndarray]:
        for seed in seeds:
            self.reset(seed)
            for _ in range(TICKS):
                self.tick()
        return self.chunks


def _equal(a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_a_served_diffusion_policy_gives_the_local_chunks_episode_by_episode(
    local: LeRobotPolicySkill, remote_skill: Callable[[], RemotePolicySkill]
) -> None:
    seeds = (3, 4, 3)  # the third episode repeats the first's seed, on other ticks and observations
    here = _Robot(local, stream=0)
    expected = here.run(seeds)
    served = remote_skill()
    assert served.info.observation_steps == 2  # the executor keeps the history the server's policy reads
    there = _Robot(served, stream=0)
    got = there.run(seeds)
    assert len(expected) >= 3 * len(seeds)
    assert all(chunk.shape == (8, 6) for chunk in got)
    assert _equal(got, expected)  # bit for bit, every chunk of every episode
    with_history = [r for r in there.requests if r.history and r.history[-1].stamp_ns != r.world.stamp_ns]
    assert len(with_history) >= 2 * len(seeds)  # chunks past an episode's first read a real history
    assert any(len(r.prefix) for r in there.requests)  # and the executor's prefix went along
    assert not np.array_equal(expected[0], expected[len(expected) // 3])  # the second episode samples anew


def test_robots_sharing_a_server_each_get_the_chunks_they_would_get_alone(
    remote_skill: Callable[[], RemotePolicySkill],
) -> None:
    alone = [_Robot(remote_skill(), stream=1).run((10, 11)), _Robot(remote_skill(), stream=2).run((20, 21))]
    robots = [_Robot(remote_skill(), stream=1), _Robot(remote_skill(), stream=2)]
    for episode in range(2):
        for robot, seeds in zip(robots, ((10, 11), (20, 21)), strict=True):
            robot.reset(seeds[episode])
        for _ in range(TICKS):
            for robot in robots:  # their requests interleave on the server
                robot.tick()
    for robot, own in zip(robots, alone, strict=True):
        assert _equal(robot.chunks, own)
    assert not np.array_equal(alone[0][0], alone[1][0])


def test_seeded_requests_batched_on_a_server_get_the_chunks_they_get_alone(local: LeRobotPolicySkill) -> None:
    requests = [
        ChunkRequest(_world(stream, tick), obs_tick=tick, history=(_world(stream, tick - 1),), seed=seed)
        for stream, tick, seed in ((5, 7, 1), (6, 9, 2), (5, 7, 1))
    ]
    batched = local.step_chunks(requests)  # each row's noise from its own request's seed
    alone = [local.step_chunk(request) for request in requests]
    for one, many in zip(alone, batched, strict=True):
        assert np.abs(one - many).max() <= 1e-5  # the kernels' float rounding
    assert np.array_equal(alone[0], alone[2])
    assert not np.array_equal(alone[0], alone[1])
