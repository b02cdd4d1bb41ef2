import json
from pathlib import Path

import pytest

from openral_core import ROSConfigError
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta, model_hash
from openral_remote.testing import ChunkSkill, chunk_meta
from openral_rskill.anchoring import (
    AbsoluteAnchor,
    AnchorSpec,
    EndEffectorDeltaAnchor,
    StateOffsetAnchor,
    UnanchoredRows,
)


def test_the_hash_follows_the_model_file_not_its_name(tmp_path: Path):
    model = tmp_path / "policy.onnx"
    model.write_bytes(b"weights v1")
    first = model_hash("onnx_policy", {"model": "policy.onnx"}, tmp_path)
    model.write_bytes(b"weights v2")
    assert model_hash("onnx_policy", {"model": "policy.onnx"}, tmp_path) != first
    assert model_hash("onnx_policy", {"model": "policy.onnx", "chunk_size": 4}, tmp_path) != model_hash(
        "onnx_policy", {"model": "policy.onnx"}, tmp_path
    )


def test_meta_survives_the_wire_and_names_its_differences():
    meta = chunk_meta(ChunkSkill(["a", "b"]), rate_hz=10.0, model_hash="h1")
    again = PolicyMeta.from_bytes(meta.to_bytes())
    assert again == meta
    assert meta.differences(again.model_copy(update={"warmup_ms": 5.0})) == []
    assert meta.differences(again.model_copy(update={"model_hash": "h2", "chunk_size": 4})) == [
        "chunk_size",
        "model_hash",
    ]


def test_meta_from_a_newer_server_names_the_fields_and_says_to_upgrade_the_robot():
    meta = chunk_meta(ChunkSkill(["a", "b"]), rate_hz=10.0, model_hash="h1")
    newer = json.loads(meta.to_bytes())
    newer["observation_window"] = 4
    with pytest.raises(ValueError, match=r"fields this openral does not know \(observation_window\).*upgrade"):
        PolicyMeta.from_bytes(json.dumps(newer).encode())
    with pytest.raises(ValueError, match="not JSON"):
        PolicyMeta.from_bytes(b"{")
    with pytest.raises(ValueError, match="chunk_size"):  # a field missing or wrong is still pydantic's line
        PolicyMeta.from_bytes(json.dumps({**json.loads(meta.to_bytes()), "chunk_size": 0}).encode())


@pytest.mark.parametrize(
    "anchor",
    [
        AbsoluteAnchor(),
        UnanchoredRows(),
        StateOffsetAnchor(["shoulder", "elbow"]),
        EndEffectorDeltaAnchor("target_pos", 0.02, (0, 1, 2), limit=0.5),
    ],
)
def test_an_anchor_is_rebuilt_from_its_spec_as_it_was(anchor):
    rebuilt = AnchorSpec.model_validate_json(AnchorSpec.of(anchor).model_dump_json()).build()
    assert type(rebuilt) is type(anchor)
    assert vars(rebuilt) == vars(anchor)


def test_keys_refuse_wildcards_and_slashes():
    assert PolicyKeys.of("so101", "pi0").infer == "openral/so101/policy/pi0/infer"
    for bad in ("a/b", "**", "x y", "$*"):
        with pytest.raises(ROSConfigError, match="key expression"):
            PolicyKeys.of("so101", bad)


def test_a_bad_endpoint_names_the_field_and_the_form():
    with pytest.raises(ValueError, match=r"tcp/192\.168\.1\.20:7447"):
        ZenohConfig(connect=["192.168.1.20:7447"])
    settings = ZenohConfig(listen=["tcp/0.0.0.0:7447"]).settings()
    assert settings["transport/link/tx/lease"] == 1000
    assert settings["scouting/multicast/enabled"] is False


def test_a_checkpoint_folder_contributes_every_file_in_it(tmp_path: Path) -> None:
    folder = tmp_path / "pretrained_model"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    (folder / "model.safetensors").write_bytes(b"weights one")
    first = model_hash("lerobot_policy", {"path": "pretrained_model"}, tmp_path)
    (folder / "model.safetensors").write_bytes(b"weights two")
    second = model_hash("lerobot_policy", {"path": "pretrained_model"}, tmp_path)
    assert second != first
    (folder / "policy_postprocessor_step_0_unnormalizer_processor.safetensors").write_bytes(b"stats")
    assert model_hash("lerobot_policy", {"path": "pretrained_model"}, tmp_path) != second
