"""A prefix-conditioned LeRobot policy (``act_smooth`` from PyPI) fed the executor's prefix and past commands.

A tiny ``act_smooth`` is built offline (random weights, no pretrained backbone, state and
environment state, no camera) and saved as ``lerobot-train`` saves it, with action statistics in
the policy's units (degrees). Through the ``lerobot_policy`` skill: the rows for the committed
ticks equal the prefix, the model saw the prefix and the past commands in its units and
normalised, with the padding mask of the delay it was asked for (clipped to its trained range),
and its own rows follow them. The package is never openral's dependency: it is installed from
PyPI into a folder of the test's own (skipped without uv or the network) unless the environment
has it. Needs the ``lerobot`` extra (Python 3.12 or newer).
"""

from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

torch = pytest.importorskip("torch", reason=LEROBOT_REASON)
pytest.importorskip("lerobot", reason=LEROBOT_REASON)

from lerobot.configs.types import FeatureType, PolicyFeature  # noqa: E402
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402

from openral_core import JointState, PrivilegedState, ROSLicenseError, ROSSkillError, WorldState  # noqa: E402
from openral_hal.lerobot.units import UnitConversion  # noqa: E402
from openral_hal.manifests import load_robot_manifest  # noqa: E402
from openral_rskill.chunks import ChunkRequest  # noqa: E402
from openral_rskill.lerobot_policy import LeRobotPolicyParams, LeRobotPolicySkill  # noqa: E402

ACT_SMOOTH = "lerobot-policy-act-smooth==0.1.0"
"""A real prefix-conditioned policy plugin from PyPI; never a dependency of openral."""

SO101 = load_robot_manifest("so101_follower")
DIMS = len(SO101.joints)
PAST, FUTURE, CHUNK, ROWS = 2, 3, 10, 8
"""The checkpoint reads 2 past commands and was trained on delays 1..3; chunks of 10 rows, 8 used."""
MEAN = np.linspace(-20.0, 20.0, DIMS)
STD = np.linspace(5.0, 30.0, DIMS)
"""The action statistics, in degrees (the policy's units here)."""


@pytest.fixture(scope="module")
def act_smooth(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """The ``lerobot_policy_act_smooth`` module: this environment's, or installed by uv into a folder of the test's."""
    try:
        yield importlib.import_module("lerobot_policy_act_smooth")
        return
    except ImportError:
        pass
    uv = shutil.which("uv")
    if uv is None:
        pytest.skip(f"needs {ACT_SMOOTH}, which uv installs into a folder of the test's own, and there is no uv")
    site = tmp_path_factory.mktemp("act_smooth_site")
    done = subprocess.run(
        [uv, "pip", "install", "--quiet", "--no-deps", "--target", str(site), ACT_SMOOTH],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot install {ACT_SMOOTH} from PyPI (no network?): {done.stderr.strip()[-300:]}")
    sys.path.insert(0, str(site))
    importlib.invalidate_caches()
    try:
        yield importlib.import_module("lerobot_policy_act_smooth")
    finally:
        sys.path.remove(str(site))
        importlib.invalidate_caches()


@pytest.fixture(scope="module")
def checkpoint(act_smooth: Any, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny act_smooth saved with its processors, as lerobot-train leaves it."""
    inputs = {
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(DIMS,)),
        "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(3,)),
    }
    config = act_smooth.ACTSmoothConfig(
        input_features=inputs,
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(DIMS,))},
        chunk_size=CHUNK,
        n_action_steps=ROWS,
        length_prefix_past=PAST,
        length_prefix_future=FUTURE,
        dim_model=32,
        n_heads=4,
        dim_feedforward=64,
        n_encoder_layers=1,
        n_decoder_layers=1,
        n_vae_encoder_layers=1,
        latent_dim=8,
        device="cpu",
        pretrained_backbone_weights=None,
    )
    torch.manual_seed(0)
    policy = act_smooth.ACTSmoothPolicy(config)
    stats = {
        "observation.state": _stats(np.zeros(DIMS), np.full(DIMS, 40.0)),
        "observation.environment_state": _stats(np.zeros(3), np.full(3, 0.1)),
        "action": _stats(MEAN, STD),
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    folder = tmp_path_factory.mktemp("act_smooth") / "pretrained_model"
    for part in (policy, pre, post):
        part.save_pretrained(folder)
    return folder


def _stats(mean: np.ndarray, std: np.ndarray) -> dict[str, Any]:
    return {
        "mean": torch.tensor(mean, dtype=torch.float32),
        "std": torch.tensor(std, dtype=torch.float32),
        "min": torch.tensor(mean - 3 * std, dtype=torch.float32),
        "max": torch.tensor(mean + 3 * std, dtype=torch.float32),
    }


class Spy:
    """What the policy's ``predict_action_chunk`` was given and returned, for the last call."""

    def __init__(self, policy: Any) -> None:
        self.batch: dict[str, Any] = {}
        self.output: Any = None
        original = policy.predict_action_chunk

        def spied(batch: dict[str, Any], **kwargs: Any) -> Any:
            self.batch = {key: value.clone() if hasattr(value, "clone") else value for key, value in batch.items()}
            self.output = original(batch, **kwargs)
            return self.output

        policy.predict_action_chunk = spied


def _skill(checkpoint: Path, **params: Any) -> LeRobotPolicySkill:
    settings = {
        "path": str(checkpoint),
        "device": "cpu",
        "joint_units": "degrees",
        "warmup_inferences": 1,
        "accept_licenses": ["NOASSERTION"],
        **params,
    }
    return LeRobotPolicySkill(SO101, LeRobotPolicyParams.model_validate(settings), rate_hz=30.0)


@pytest.fixture(scope="module")
def skill(checkpoint: Path) -> Iterator[tuple[LeRobotPolicySkill, Spy]]:
    built = _skill(checkpoint)
    built.configure()
    built.activate()
    try:
        yield built, Spy(built._policy.policy)
    finally:
        built.shutdown()


def _world(joints: np.ndarray) -> WorldState:
    return WorldState(
        stamp_ns=1,
        joint_state=JointState(names=SO101.joint_names, positions=joints.tolist()),
        privileged=PrivilegedState(values={"environment_state": [0.3, 0.0, 0.02]}),
    )


def _normalised(radians: np.ndarray) -> np.ndarray:
    """In the policy's units (degrees, the jaw 0..100), normalised with the checkpoint's action statistics."""
    return (UnitConversion(SO101, "degrees").to_policy(radians) - MEAN) / (STD + 1e-8)


def _rows(start: float, count: int) -> np.ndarray:
    """``count`` rows of joint targets in radians, each a little further on."""
    return np.array([np.linspace(-0.3, 0.3, DIMS) + start + 0.01 * i for i in range(count)])


def _model_rows(skill: LeRobotPolicySkill, spy: Spy) -> np.ndarray:
    """The model's own rows of the last call, in radians (what follows the committed ones)."""
    degrees = skill._policy.post(spy.output).detach().to("cpu", torch.float64).numpy()[0]
    return UnitConversion(SO101, "degrees").to_radians(degrees)[:ROWS]


def test_the_rows_for_committed_ticks_are_the_prefix_and_the_model_saw_it_normalised_with_its_past(
    skill: tuple[LeRobotPolicySkill, Spy],
) -> None:
    policy, spy = skill
    assert policy.info.past_actions == PAST
    prefix, past = _rows(0.1, 2), _rows(-0.2, 3)
    request = ChunkRequest(
        _world(np.zeros(DIMS)), obs_tick=10, prefix=prefix, inference_delay=2, past=past, past_ticks=(7, 8, 9)
    )
    chunk = policy.step_chunk(request)
    assert chunk.shape == (2 + ROWS, DIMS)
    np.testing.assert_array_equal(chunk[:2], prefix)  # row i is for tick obs_tick + i: the committed ones as sent
    np.testing.assert_allclose(chunk[2:], _model_rows(policy, spy), atol=1e-9)  # then the model's, from tick 12
    seen = spy.batch["inference_action"][0].numpy()
    assert spy.batch["inference_action_is_pad"].tolist() == [[False, False, False, False, True]]
    np.testing.assert_allclose(seen[:PAST], _normalised(past[-PAST:]), atol=1e-5)  # the last two sent, in order
    np.testing.assert_allclose(seen[PAST : PAST + 2], _normalised(prefix), atol=1e-5)


def test_committed_rows_past_the_joint_limits_are_fed_and_returned_as_the_envelope_sends_them(
    skill: tuple[LeRobotPolicySkill, Spy],
) -> None:
    policy, spy = skill
    upper = np.array([joint.upper for joint in SO101.joints])
    prefix = np.array([upper + 0.5, upper - 0.01])  # the first row beyond every limit, the second inside
    chunk = policy.step_chunk(ChunkRequest(_world(np.zeros(DIMS)), obs_tick=5, prefix=prefix, inference_delay=2))
    np.testing.assert_array_equal(chunk[:2], [upper, upper - 0.01])
    seen = spy.batch["inference_action"][0].numpy()
    np.testing.assert_allclose(seen[PAST : PAST + 2], _normalised(np.array([upper, upper - 0.01])), atol=1e-5)


def test_an_episode_starts_from_the_measured_joints(skill: tuple[LeRobotPolicySkill, Spy]) -> None:
    policy, spy = skill
    measured = np.linspace(0.2, -0.15, DIMS)  # inside every limit (the gripper opens from -0.17)
    chunk = policy.step_chunk(ChunkRequest(_world(measured), obs_tick=0))  # no prefix, no past, no delay
    assert chunk.shape == (1 + ROWS, DIMS)
    np.testing.assert_allclose(chunk[0], measured, atol=1e-12)  # row 0, for the observation's tick: where it is
    assert spy.batch["inference_action_is_pad"].tolist() == [[True, True, False, True, True]]
    np.testing.assert_allclose(spy.batch["inference_action"][0, PAST].numpy(), _normalised(measured), atol=1e-5)


def test_a_delay_past_the_trained_range_is_clipped_and_logged(skill: tuple[LeRobotPolicySkill, Spy]) -> None:
    policy, spy = skill
    policy.reset()
    prefix = _rows(0.0, 5)
    with capture_logs() as logs:
        chunk = policy.step_chunk(ChunkRequest(_world(np.zeros(DIMS)), obs_tick=4, prefix=prefix, inference_delay=5))
        policy.step_chunk(ChunkRequest(_world(np.zeros(DIMS)), obs_tick=9, prefix=prefix, inference_delay=5))
    np.testing.assert_array_equal(chunk[:FUTURE], prefix[:FUTURE])  # the executor skips the rest as ticks gone
    assert chunk.shape == (FUTURE + ROWS, DIMS)
    assert spy.batch["inference_action_is_pad"].tolist() == [[True, True, False, False, False]]
    clipped = [entry for entry in logs if entry["event"] == "prefix delay clipped to the trained range"]
    assert [(entry["delay"], entry["trained"]) for entry in clipped] == [(5, FUTURE)]  # once an episode


def test_a_prefix_shorter_than_the_delay_is_held_as_the_executor_holds_it(
    skill: tuple[LeRobotPolicySkill, Spy],
) -> None:
    policy, spy = skill
    prefix = _rows(0.05, 1)
    chunk = policy.step_chunk(ChunkRequest(_world(np.zeros(DIMS)), obs_tick=3, prefix=prefix, inference_delay=3))
    np.testing.assert_array_equal(chunk[:3], np.repeat(prefix, 3, axis=0))
    np.testing.assert_allclose(
        spy.batch["inference_action"][0, PAST:].numpy(), np.repeat(_normalised(prefix), 3, axis=0), atol=1e-5
    )


def test_the_package_declares_no_licence_so_it_runs_only_once_accepted(checkpoint: Path) -> None:
    refused = _skill(checkpoint, accept_licenses=None)
    with pytest.raises(ROSSkillError):
        refused.configure()
    error = refused.last_error
    assert isinstance(error, ROSLicenseError)
    assert "licence 'NOASSERTION' of the package lerobot_policy_act_smooth" in str(error)
    assert "policy type 'act_smooth'" in str(error)
    assert "declares no licence" in str(error)
    assert error.field == "params.accept_licenses"
