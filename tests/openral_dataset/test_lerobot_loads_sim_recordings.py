"""LeRobot itself loads what ``openral sim run --dataset-out`` records on the ALOHA and LIBERO families.

Needs the ``lerobot`` extra (Python 3.12): ``.ci/run`` runs this module again there.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from openral_cli.main import cli
from openral_core import SimCamera, SimEnvironment
from openral_core.config import load_model_yaml

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"
pytest.importorskip("lerobot", reason=LEROBOT_REASON)

from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

SCENES = Path(__file__).resolve().parents[2] / "scenes" / "sim"
FAMILIES = [
    ("aloha_transfer_cube.yaml", "aloha_transfer_cube_expert", "gym_aloha", "top", 14),
    ("franka_libero_pnp.yaml", "libero_expert", "libero", "agentview", 8),
]


@pytest.mark.parametrize("family", FAMILIES, ids=lambda family: family[0].removesuffix(".yaml"))
def test_lerobot_loads_a_recorded_episode_frame_by_frame(
    tmp_path: Path, family: tuple[str, str, str, str, int]
) -> None:
    scene_name, expert, module, camera, state_dim = family
    pytest.importorskip(module, reason=f"needs the simulator package {module}")
    scene = load_model_yaml(SimEnvironment, SCENES / scene_name)
    scene = scene.model_copy(update={"cameras": [SimCamera(name=camera, width=64, height=48)], "max_steps": 30})
    scene_file = tmp_path / "scene.yaml"
    scene_file.write_text(yaml.safe_dump(scene.model_dump(mode="json")))
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(scene_file), "--skill", expert, "--n-episodes", "1",
         "--dataset-out", str(out), "--vcodec", "h264"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    dataset = LeRobotDataset("local/recording", root=out)
    info = json.loads((out / "meta" / "info.json").read_text())
    assert dataset.num_episodes == 1
    assert len(dataset) == info["total_frames"] > 0
    first, last = dataset[0], dataset[len(dataset) - 1]
    image = first[f"observation.images.{camera}"]
    assert tuple(image.shape) == (3, 48, 64)
    assert float(image.std()) > 0.01  # a rendered scene, not a blank frame
    assert tuple(first["observation.state"].shape) == (state_dim,)
    assert int(last["frame_index"]) == len(dataset) - 1
    assert not np.array_equal(first["observation.state"].numpy(), last["observation.state"].numpy())  # it moved
