"""Train a small chunking policy from a recorded LeRobotDataset, in numpy, and export it to ONNX.

Reads the dataset with pyarrow (``observation.state``, ``observation.environment_state`` when
present, and ``action``), fits an MLP that maps one observation to the next ``chunk`` actions
(Adam on the mean squared error of normalised actions), and writes an ONNX graph built with
``onnx.helper`` in which the normalisation is folded: raw observation in, raw action rows out,
``(1, chunk, action_dim)``. The chunk size, observation fields and action representation go in the
model's metadata, where the ``onnx_policy`` skill reads them. No torch.

    uv run python -m openral_sim.train_mlp --dataset data/so101_pick_expert --out so101_pick_mlp.onnx
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from openral_core import ROSDependencyMissing
from openral_dataset import layout, schema

try:
    import onnx
    import pyarrow.parquet as pq
    from onnx import TensorProto, helper, numpy_helper
except ImportError as exc:
    raise ROSDependencyMissing("onnx", extra="policy", needed_for="exporting trained policies") from exc


@dataclass
class Samples:
    """Observations and the action chunks that followed them."""

    observations: np.ndarray
    chunks: np.ndarray
    observation_names: list[str]
    action_names: list[str]


def load_samples(root: Path, chunk: int) -> Samples:
    """One sample per row: its observation, and its action and the ``chunk - 1`` after it (the last repeated)."""
    info = layout.read_info(root)
    if info is None:
        raise ValueError(f"{root} holds no dataset (no meta/info.json)")
    features = info["features"]
    keys = [schema.STATE] + ([schema.ENVIRONMENT_STATE] if schema.ENVIRONMENT_STATE in features else [])
    observations, chunks = [], []
    for episode in range(int(info["total_episodes"])):
        table = pq.read_table(layout.data_file(root, episode), columns=[*keys, schema.ACTION])
        obs = np.concatenate([np.asarray(table.column(k).to_pylist(), dtype=np.float64) for k in keys], axis=1)
        actions = np.asarray(table.column(schema.ACTION).to_pylist(), dtype=np.float64)
        index = np.minimum(np.arange(len(actions))[:, None] + np.arange(chunk)[None, :], len(actions) - 1)
        observations.append(obs)
        chunks.append(actions[index])
    names = [name for key in keys for name in features[key]["names"]]
    return Samples(np.concatenate(observations), np.concatenate(chunks), names, features[schema.ACTION]["names"])


class MLP:
    """``obs -> hidden -> hidden -> chunk * action_dim`` with ReLU, trained with Adam."""

    def __init__(self, sizes: list[int], rng: np.random.Generator) -> None:
        self.weights = [rng.normal(0, np.sqrt(2 / a), (a, b)) for a, b in itertools.pairwise(sizes)]
        self.biases = [np.zeros(b) for b in sizes[1:]]
        self._m = [np.zeros_like(p) for p in self.parameters]
        self._v = [np.zeros_like(p) for p in self.parameters]
        self._t = 0

    @property
    def parameters(self) -> list[np.ndarray]:
        return [*self.weights, *self.biases]

    def forward(self, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        activations = [x]
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = x @ w + b
            if i < len(self.weights) - 1:
                x = np.maximum(x, 0.0)
            activations.append(x)
        return x, activations

    def train_step(self, x: np.ndarray, y: np.ndarray, lr: float) -> float:
        out, activations = self.forward(x)
        error = out - y
        loss = float(np.mean(error**2))
        grad = 2 * error / error.size
        grads_w: list[np.ndarray] = []
        grads_b: list[np.ndarray] = []
        for i in reversed(range(len(self.weights))):
            grads_w.insert(0, activations[i].T @ grad)
            grads_b.insert(0, grad.sum(axis=0))
            if i > 0:
                grad = (grad @ self.weights[i].T) * (activations[i] > 0)
        self._adam([*grads_w, *grads_b], lr)
        return loss

    def _adam(self, grads: list[np.ndarray], lr: float, b1: float = 0.9, b2: float = 0.999) -> None:
        self._t += 1
        # In place: the moments and parameters are the arrays the model holds.
        for param, grad, first, second in zip(self.parameters, grads, self._m, self._v, strict=True):
            np.multiply(first, b1, out=first)
            np.add(first, (1 - b1) * grad, out=first)
            np.multiply(second, b2, out=second)
            np.add(second, (1 - b2) * grad**2, out=second)
            step = lr * (first / (1 - b1**self._t)) / (np.sqrt(second / (1 - b2**self._t)) + 1e-8)
            np.subtract(param, step, out=param)


def train(
    samples: Samples, *, hidden: int, epochs: int, batch: int, lr: float, seed: int
) -> tuple[MLP, dict[str, np.ndarray]]:
    """Fit the MLP on normalised data; returns it and the normalisation to fold into the graph."""
    rng = np.random.default_rng(seed)
    obs_mean = samples.observations.mean(axis=0)
    obs_std = samples.observations.std(axis=0) + 1e-6
    flat = samples.chunks.reshape(len(samples.chunks), -1)
    act_mean = flat.mean(axis=0)
    act_std = flat.std(axis=0) + 1e-6
    x = (samples.observations - obs_mean) / obs_std
    y = (flat - act_mean) / act_std
    model = MLP([x.shape[1], hidden, hidden, y.shape[1]], rng)
    for epoch in range(epochs):
        order = rng.permutation(len(x))
        losses = [model.train_step(x[idx], y[idx], lr) for idx in np.array_split(order, max(1, len(x) // batch))]
        if epoch % max(1, epochs // 10) == 0 or epoch == epochs - 1:
            print(f"epoch {epoch:4d}  loss {np.mean(losses):.5f}")
    return model, {"obs_mean": obs_mean, "obs_std": obs_std, "act_mean": act_mean, "act_std": act_std}


def export_onnx(
    model: MLP, norm: dict[str, np.ndarray], samples: Samples, chunk: int, metadata: dict[str, str]
) -> onnx.ModelProto:
    """The MLP with its normalisation folded in: ``observation (1, obs_dim)`` → ``actions (1, chunk, action_dim)``."""
    action_dim = len(samples.action_names)
    initializers = [
        numpy_helper.from_array(norm["obs_mean"].astype(np.float32), "obs_mean"),
        numpy_helper.from_array(norm["obs_std"].astype(np.float32), "obs_std"),
        numpy_helper.from_array(norm["act_mean"].astype(np.float32), "act_mean"),
        numpy_helper.from_array(norm["act_std"].astype(np.float32), "act_std"),
        numpy_helper.from_array(np.array([-1, chunk, action_dim], dtype=np.int64), "out_shape"),
    ]
    nodes = [
        helper.make_node("Sub", ["observation", "obs_mean"], ["centred"]),
        helper.make_node("Div", ["centred", "obs_std"], ["h0"]),
    ]
    for i, (w, b) in enumerate(zip(model.weights, model.biases, strict=True)):
        initializers += [
            numpy_helper.from_array(w.astype(np.float32), f"w{i}"),
            numpy_helper.from_array(b.astype(np.float32), f"b{i}"),
        ]
        last = i == len(model.weights) - 1
        nodes.append(helper.make_node("Gemm", [f"h{i}", f"w{i}", f"b{i}"], ["z_out" if last else f"z{i}"]))
        if not last:
            nodes.append(helper.make_node("Relu", [f"z{i}"], [f"h{i + 1}"]))
    nodes += [
        helper.make_node("Mul", ["z_out", "act_std"], ["scaled"]),
        helper.make_node("Add", ["scaled", "act_mean"], ["flat_actions"]),
        helper.make_node("Reshape", ["flat_actions", "out_shape"], ["actions"]),
    ]
    graph = helper.make_graph(
        nodes,
        "mlp_chunk_policy",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", len(samples.observation_names)])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", chunk, action_dim])],
        initializers,
    )
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="openral")
    proto.ir_version = 8
    helper.set_model_props(proto, metadata)
    onnx.checker.check_model(proto)
    return proto


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--chunk", type=int, default=8)
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--representation", default="delta_ee", help="How the rows are meant (for the skill).")
    parser.add_argument(
        "--observation-fields",
        default="joint_state,privileged.environment_state",
        help="World-state fields the skill builds the input from, in the dataset's order.",
    )
    parser.add_argument("--anchor-key", default="target_pos", help="delta_ee: the privileged position rows move.")
    parser.add_argument("--action-scale", default="0.025", help="delta_ee: metres per unit of action.")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    samples = load_samples(args.dataset, args.chunk)
    print(f"{len(samples.observations)} samples of {len(samples.observation_names)} observations")
    model, norm = train(samples, hidden=args.hidden, epochs=args.epochs, batch=args.batch, lr=args.lr, seed=args.seed)
    metadata = {
        "chunk_size": str(args.chunk),
        "observation": json.dumps(samples.observation_names),
        "action": json.dumps(samples.action_names),
        "openral.observation": json.dumps(args.observation_fields.split(",")),
        "openral.representation": args.representation,
        "openral.anchor_key": args.anchor_key,
        "openral.action_scale": args.action_scale,
        "description": f"MLP chunk policy trained on {args.dataset.name}",
        "license": "Apache-2.0",
    }
    proto = export_onnx(model, norm, samples, args.chunk, metadata)
    args.out.write_bytes(proto.SerializeToString())
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KiB) in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
