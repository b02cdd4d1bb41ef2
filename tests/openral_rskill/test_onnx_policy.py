"""The onnx_policy skill: a real ONNX Runtime session, its metadata, its observation, its errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openral_core import JointSpec, JointState, PrivilegedState, RobotManifest, ROSConfigError, WorldState

onnx = pytest.importorskip("onnx", reason="needs the 'policy' extra")
pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from openral_rskill.anchoring import EndEffectorDeltaAnchor, UnanchoredRows  # noqa: E402
from openral_rskill.chunks import ChunkRequest  # noqa: E402
from openral_rskill.onnx_policy import OnnxPolicySkill  # noqa: E402
from openral_rskill.worker_threads import THREADS_PER_WORKER_VARIABLE  # noqa: E402

ROBOT = RobotManifest(
    robot_id="arm",
    joints=[JointSpec(name=n, lower=-1, upper=1, velocity_limit=1) for n in ("a", "b")],
)


def tiny_model(path: Path, *, chunk: int = 3, obs_dim: int = 3, dynamic_batch: bool = False) -> Path:
    """actions[0, j] = [obs[0] + j, obs[1] * 2]: row j of the chunk is checkable by hand."""
    batch: int | str = "batch" if dynamic_batch else 1
    pick = np.zeros((obs_dim, 2), dtype=np.float32)
    pick[0, 0] = 1.0
    pick[1, 1] = 2.0
    offsets = np.array([[j, 0.0] for j in range(chunk)], dtype=np.float32).reshape(1, chunk, 2)
    nodes = [
        helper.make_node("MatMul", ["observation", "pick"], ["row"]),
        helper.make_node("Reshape", ["row", "row_shape"], ["row3"]),
        helper.make_node("Add", ["row3", "offsets"], ["actions"]),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, [batch, obs_dim])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, [batch, chunk, 2])],
        [
            numpy_helper.from_array(pick, "pick"),
            numpy_helper.from_array(np.array([-1, 1, 2], dtype=np.int64), "row_shape"),
            numpy_helper.from_array(offsets, "offsets"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"chunk_size": str(chunk), "description": "test model"})
    path.write_bytes(model.SerializeToString())
    return path


def world() -> WorldState:
    return WorldState(
        stamp_ns=1,
        joint_state=JointState(names=["a", "b"], positions=[0.5, 0.25]),
        privileged=PrivilegedState(values={"block": [7.0]}),
    )


def test_chunk_size_comes_from_the_models_metadata_and_rows_from_the_session(tmp_path: Path) -> None:
    skill = OnnxPolicySkill.from_config(
        {"model": str(tiny_model(tmp_path / "m.onnx")), "observation": ["joint_state", "privileged.block"]},
        robot=ROBOT,
        rate_hz=10,
    )
    assert skill.info.chunk_size == 3
    skill.configure()
    skill.activate()
    rows = skill.step_chunk(ChunkRequest(world()))
    assert isinstance(rows, np.ndarray)  # the model's array, handed over as it is
    np.testing.assert_allclose(rows, [[0.5, 0.5], [1.5, 0.5], [2.5, 0.5]])
    assert skill.step(world()).targets == [[0.5, 0.5]]  # step, tick by tick: the chunk's first row
    np.testing.assert_allclose(skill.observation_vector(world()), [[0.5, 0.25, 7.0]])


def test_normalisation_outside_the_graph_is_applied(tmp_path: Path) -> None:
    skill = OnnxPolicySkill.from_config(
        {
            "model": str(tiny_model(tmp_path / "m.onnx")),
            "observation": ["joint_state", "privileged.block"],
            "obs_mean": [0.5, 0.0, 0.0],
            "obs_std": [1.0, 0.5, 1.0],
        },
        robot=ROBOT,
        rate_hz=10,
    )
    skill.configure()
    skill.activate()
    np.testing.assert_allclose(skill.step(world()).targets[0], [0.0, 1.0])


def test_delta_ee_rows_are_anchored_where_the_parameters_say(tmp_path: Path) -> None:
    skill = OnnxPolicySkill.from_config(
        {
            "model": str(tiny_model(tmp_path / "m.onnx")),
            "observation": ["joint_state", "privileged.block"],
            "representation": "delta_ee",
            "anchor_key": "grasp_pos",
            "action_scale": 0.025,
            "position_dims": [0],
        },
        robot=ROBOT,
        rate_hz=10,
    )
    anchor = skill.action_anchor()
    assert isinstance(anchor, EndEffectorDeltaAnchor)
    assert (anchor.position_key, anchor.scale, anchor.dims) == ("grasp_pos", 0.025, [0])


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"model": "missing.onnx", "observation": ["joint_state"]}, "params.model"),
        ({"observation": ["joint_state"], "dt_s": 0.05}, "params.dt_s"),
    ],
)
def test_bad_parameters_name_the_field(tmp_path: Path, params: dict[str, object], field: str) -> None:
    params = {"model": str(tiny_model(tmp_path / "m.onnx")), **params}
    with pytest.raises(ROSConfigError) as caught:
        OnnxPolicySkill.from_config(params, robot=ROBOT, rate_hz=10).action_anchor()
    assert caught.value.field == field


def test_delta_rows_without_a_position_to_anchor_at_run_unanchored(tmp_path: Path) -> None:
    skill = OnnxPolicySkill.from_config(
        {"model": str(tiny_model(tmp_path / "m.onnx")), "observation": ["joint_state"], "representation": "delta_ee"},
        robot=ROBOT,
        rate_hz=10,
    )
    assert isinstance(skill.action_anchor(), UnanchoredRows)


def test_a_file_that_is_not_a_model_is_a_configuration_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(ROSConfigError, match="cannot load"):
        OnnxPolicySkill.from_config({"model": str(bad), "observation": ["joint_state"]}, robot=ROBOT, rate_hz=10)


def _worlds(n: int) -> list[WorldState]:
    return [
        WorldState(
            stamp_ns=1,
            joint_state=JointState(names=["a", "b"], positions=[0.1 * i, -0.2 * i]),
            privileged=PrivilegedState(values={"block": [float(i)]}),
        )
        for i in range(n)
    ]


def test_a_dynamic_batch_model_runs_many_requests_in_one_inference_with_each_ones_chunk(tmp_path: Path) -> None:
    model = tiny_model(tmp_path / "batched.onnx", dynamic_batch=True)
    skill = OnnxPolicySkill.from_config(
        {"model": str(model), "observation": ["joint_state", "privileged.block"]}, robot=ROBOT, rate_hz=10
    )
    skill.configure()
    skill.activate()
    requests = [ChunkRequest(world) for world in _worlds(5)]
    batched = skill.step_chunks(requests)
    assert skill.batch_capacity() > 1
    assert skill.serves_many_episodes()
    assert skill.step_count == 1  # one inference for the five
    for request, chunk in zip(requests, batched, strict=True):
        np.testing.assert_allclose(chunk, skill.step_chunk(request), rtol=0, atol=1e-6)
    assert batched[3][2, 0] == pytest.approx(0.3 + 2)  # row j: [obs[0] + j, obs[1] * 2]


def test_a_fixed_batch_model_answers_a_batch_one_request_at_a_time(tmp_path: Path) -> None:
    skill = OnnxPolicySkill.from_config(
        {"model": str(tiny_model(tmp_path / "one.onnx")), "observation": ["joint_state", "privileged.block"]},
        robot=ROBOT,
        rate_hz=10,
    )
    skill.configure()
    skill.activate()
    assert skill.batch_capacity() == 1
    chunks = skill.step_chunks([ChunkRequest(world) for world in _worlds(3)])
    assert [chunk[0, 1] for chunk in chunks] == pytest.approx([0.0, -0.4, -0.8])


@pytest.mark.parametrize(
    ("allowance", "asked", "expected"),
    [(None, None, 1), ("3", None, 3), ("3", 2, 2), (None, 0, 0)],
)
def test_the_sessions_threads_are_the_parameters_else_the_evaluation_workers_allowance_else_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, allowance: str | None, asked: int | None, expected: int
) -> None:
    if allowance is None:
        monkeypatch.delenv(THREADS_PER_WORKER_VARIABLE, raising=False)
    else:
        monkeypatch.setenv(THREADS_PER_WORKER_VARIABLE, allowance)
    params: dict[str, object] = {"model": str(tiny_model(tmp_path / "m.onnx")), "observation": ["joint_state"]}
    if asked is not None:
        params["intra_op_threads"] = asked
    skill = OnnxPolicySkill.from_config(params, robot=ROBOT, rate_hz=30)
    skill.configure()
    options = skill._session.get_session_options()
    assert (options.intra_op_num_threads, options.inter_op_num_threads) == (expected, 1)
