"""The numpy training tool: a dataset in, an ONNX chunk policy out that computes what the trained network does."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from openral_core import SimEnvironment

pytest.importorskip("onnx", reason="needs the 'policy' extra")
ort = pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

from openral_cli.recording import dataset_entry, with_observers  # noqa: E402
from openral_sim.build import run_episodes  # noqa: E402
from openral_sim.train_mlp import export_onnx, load_samples, main, train  # noqa: E402

SCENE = SimEnvironment(
    name="reach", env="mock", task="reach", success_key="is_success", max_steps=30, n_episodes=4, seed=0
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("ds") / "reach"
    recorded = with_observers(SCENE, dataset_entry(root, resume=False, vcodec="h264"))
    run_episodes(recorded, "mock_reach_expert")
    return root


def test_samples_pair_each_observation_with_the_actions_that_followed(dataset: Path) -> None:
    samples = load_samples(dataset, chunk=3)
    assert samples.observation_names == ["x", "y", "target_x", "target_y"]
    assert samples.action_names == ["dx", "dy"]
    assert samples.chunks.shape[1:] == (3, 2)
    # Row t's chunk is actions t, t+1, t+2 (the episode's last action repeated past its end).
    np.testing.assert_allclose(samples.chunks[0, 1], samples.chunks[1, 0])
    np.testing.assert_allclose(samples.chunks[0, 2], samples.chunks[2, 0])


def test_the_exported_graph_computes_the_trained_network_with_its_normalisation(dataset: Path) -> None:
    samples = load_samples(dataset, chunk=3)
    model, norm = train(samples, hidden=16, epochs=3, batch=32, lr=1e-3, seed=1)
    proto = export_onnx(model, norm, samples, 3, {"chunk_size": "3"})
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    obs = samples.observations[5]
    (onnx_out,) = session.run(None, {"observation": obs[None, :].astype(np.float32)})
    x = (obs - norm["obs_mean"]) / norm["obs_std"]
    out, _ = model.forward(x[None, :])
    expected = (out[0] * norm["act_std"] + norm["act_mean"]).reshape(1, 3, 2)
    np.testing.assert_allclose(onnx_out, expected, rtol=1e-4, atol=1e-4)


def test_training_reduces_the_loss_and_the_tool_writes_metadata(dataset: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "policy.onnx"
    main(["--dataset", str(dataset), "--out", str(out), "--chunk", "4", "--hidden", "32", "--epochs", "20"])
    losses = [float(line.split()[-1]) for line in capsys.readouterr().out.splitlines() if line.startswith("epoch")]
    assert losses[-1] < losses[0] / 2
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    metadata = session.get_modelmeta().custom_metadata_map
    assert metadata["chunk_size"] == "4"
    assert json.loads(metadata["observation"]) == ["x", "y", "target_x", "target_y"]
    assert session.get_outputs()[0].shape == ["batch", 4, 2]  # a server batches many robots through it
