"""``onnx_policy``: a policy exported to ONNX, run with ONNX Runtime on the CPU, one chunk per inference.

The parameters name the observation: an ordered list of fields concatenated into the model's
one input (``joint_state`` for the measured joints, ``privileged.<name>`` for a simulator's
values), optional normalisation (or none, when it is folded into the graph), and how the model's
rows are meant (the action representation, anchored by the chunk executor). The chunk size is
read from the model's metadata (``chunk_size``) when it has it; the chunk goes to the chunk
executor as the model's array (``step`` gives its first row). One warm-up inference runs at
``configure``, and ONNX Runtime's intra-op threads are set: as the parameters say, else the
evaluation worker's allowance (:mod:`openral_rskill.worker_threads`), else one (the tick's machine
has other work).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import (
    ControlMode,
    RobotManifest,
    ROSConfigError,
    ROSDependencyMissing,
    RSkillInfo,
    WorldState,
)
from openral_core.config_files import require_user_file
from openral_rskill.anchoring import (
    AbsoluteAnchor,
    ActionRepresentation,
    Anchor,
    EndEffectorDeltaAnchor,
    StateOffsetAnchor,
    UnanchoredRows,
)
from openral_rskill.base import ChunkingSkillBase, validate_params
from openral_rskill.chunks import ChunkRequest
from openral_rskill.worker_threads import threads_per_worker

try:
    import onnxruntime as ort
except ImportError as exc:
    raise ROSDependencyMissing("onnxruntime", extra="policy", needed_for="ONNX policies") from exc

SKILL_ID = "onnx_policy"
META_OBSERVATION = "openral.observation"
"""Model metadata: the observation fields, a JSON list (what ``params.observation`` would say)."""
META_REPRESENTATION = "openral.representation"
META_ANCHOR_KEY = "openral.anchor_key"
META_ACTION_SCALE = "openral.action_scale"
MAX_BATCH = 256
"""Requests one inference takes at most, for a model with a dynamic batch dimension."""


class OnnxPolicyParams(BaseModel):
    """``params`` of the ``onnx_policy`` skill."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    model: str = Field(min_length=1, description="The .onnx file (relative to the working directory).")
    observation: list[str] | None = Field(
        default=None,
        min_length=1,
        description="Fields concatenated into the input: joint_state, privileged.<name>; from the model's metadata.",
    )
    obs_mean: list[float] | None = Field(default=None, description="Subtracted from the input (not in the graph).")
    obs_std: list[float] | None = Field(default=None, description="The input is divided by it (not in the graph).")
    chunk_size: int | None = Field(default=None, ge=1, description="Rows per chunk; from the model's metadata.")
    representation: ActionRepresentation | None = Field(default=None, description="From the metadata, else absolute.")
    anchor_key: str | None = Field(default=None, description="delta_ee: the privileged position the rows move.")
    action_scale: float | None = Field(default=None, gt=0, description="delta_ee: metres per unit of action.")
    position_dims: list[int] = Field(default_factory=lambda: [0, 1, 2], description="delta_ee: the moving dims.")
    intra_op_threads: int | None = Field(
        default=None,
        ge=0,
        description="ONNX Runtime intra-op threads (0: its default; unset: an evaluation worker's allowance, else 1).",
    )
    dt_s: float | None = Field(default=None, gt=0, description="The policy's step; must match the tick period.")


class OnnxPolicySkill(ChunkingSkillBase):
    """Runs an ONNX model: input ``(1, obs_dim)``, output ``(1, chunk, action_dim)`` (or ``(1, action_dim)``)."""

    def __init__(self, robot: RobotManifest, params: OnnxPolicyParams, *, rate_hz: float) -> None:
        super().__init__()
        self.robot = robot
        self.params = params
        self.names = robot.joint_names
        path = require_user_file(
            params.model, field="params.model", what="model file", hint="give the path of a .onnx file"
        )
        if params.dt_s is not None and abs(params.dt_s * rate_hz - 1.0) > 1e-6:
            raise ROSConfigError(
                f"the policy steps every {params.dt_s} s but the loop ticks at {rate_hz:g} Hz",
                field="params.dt_s",
                hint="run the loop at the policy's rate",
            )
        self.path = path
        self._session: Any = None
        self._input = ""
        metadata = _read_metadata(path)
        self.chunk_size = params.chunk_size or int(metadata.get("chunk_size", "1"))
        # What the parameters leave open, the model's metadata says (the training tool writes it).
        fields = params.observation or json.loads(metadata.get(META_OBSERVATION, "null") or "null")
        if not fields:
            raise ROSConfigError(
                f"{path.name} does not say what it observes", field="params.observation", hint="list the fields"
            )
        self.observation_fields: list[str] = list(fields)
        self.representation = params.representation or ActionRepresentation(
            metadata.get(META_REPRESENTATION, ActionRepresentation.ABSOLUTE.value)
        )
        self.anchor_key = params.anchor_key or metadata.get(META_ANCHOR_KEY)
        self.action_scale = params.action_scale or float(metadata.get(META_ACTION_SCALE, "1.0"))
        self._info = RSkillInfo(
            skill_id=SKILL_ID,
            name=f"ONNX policy {path.name}",
            version=metadata.get("version", "0.0.0"),
            license=metadata.get("license", "Apache-2.0"),
            control_mode=ControlMode.EE_DELTA
            if self.representation is ActionRepresentation.DELTA_EE
            else ControlMode.JOINT_POSITION,
            chunk_size=self.chunk_size,
            description=metadata.get("description", ""),
            observation=self.observation_fields,
        )
        self._mean = None if params.obs_mean is None else np.asarray(params.obs_mean, dtype=np.float32)
        self._std = None if params.obs_std is None else np.asarray(params.obs_std, dtype=np.float32)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(OnnxPolicyParams, params, skill_id=SKILL_ID), rate_hz=rate_hz)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    @property
    def action_names(self) -> list[str]:
        return list(self.names)

    def action_anchor(self) -> Anchor:
        """How the executor anchors this model's rows (from ``representation``)."""
        if self.representation is ActionRepresentation.RELATIVE_TO_STATE:
            return StateOffsetAnchor(self.names)
        if self.representation is ActionRepresentation.DELTA_EE and self.anchor_key is not None:
            return EndEffectorDeltaAnchor(self.anchor_key, self.action_scale, self.params.position_dims)
        if self.representation in (ActionRepresentation.DELTA_EE, ActionRepresentation.UNANCHORED):
            return UnanchoredRows()  # no position to anchor at: the executor starts each chunk stale, and warns
        return AbsoluteAnchor()

    @property
    def intra_op_threads(self) -> int:
        """ONNX Runtime's intra-op threads: the parameter's, else the evaluation worker's allowance, else one."""
        if self.params.intra_op_threads is not None:
            return self.params.intra_op_threads
        return threads_per_worker() or 1

    def _on_configure(self) -> None:
        options = ort.SessionOptions()
        options.intra_op_num_threads = self.intra_op_threads
        options.inter_op_num_threads = 1
        try:
            self._session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for a bad file
            raise ROSConfigError(f"cannot load {self.path}: {exc}", field="params.model") from exc
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ROSConfigError(f"{self.path} has {len(inputs)} inputs; one is expected", field="params.model")
        self._input = inputs[0].name
        self._infer(np.zeros((1, self._obs_dim()), dtype=np.float32))  # warm-up: allocations, kernels

    def serves_many_episodes(self) -> bool:
        """A chunk is the model's output for one observation: nothing is carried between inferences."""
        return True

    def batch_capacity(self) -> int:
        """``MAX_BATCH`` when the model's batch dimension is dynamic (a name, not a number); else 1."""
        if self._session is None:
            return 1
        leading = self._session.get_inputs()[0].shape[0]
        return MAX_BATCH if not isinstance(leading, int) else max(1, leading)

    def _obs_dim(self) -> int:
        shape = self._session.get_inputs()[0].shape
        return int(shape[-1])

    def _infer(self, observation: np.ndarray) -> np.ndarray:
        (output,) = self._session.run(None, {self._input: observation})
        rows = np.asarray(output, dtype=np.float64)
        return rows.reshape(-1, len(self.names))

    def observation_vector(self, world: WorldState) -> np.ndarray:
        """The model's input for ``world``, normalised as the parameters say."""
        parts: list[Sequence[float]] = []
        for field in self.observation_fields:
            if field == "joint_state":
                if world.joint_state is None:
                    raise ValueError("the observation needs the measured joints")
                parts.append(world.joint_state.positions)
            elif field.startswith("privileged."):
                if world.privileged is None:
                    raise ValueError(f"{field} is a simulator's value: this policy runs in simulation only")
                parts.append(world.privileged.get(field.removeprefix("privileged.")))
            else:
                raise ValueError(f"unknown observation field {field!r} (joint_state, privileged.<name>)")
        vector = np.concatenate([np.asarray(p, dtype=np.float32) for p in parts])[None, :]
        if self._mean is not None:
            vector = vector - self._mean
        if self._std is not None:
            vector = vector / self._std
        return np.asarray(vector, dtype=np.float32)

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The model's ``(rows, joints)`` output for the request's observation, as one array."""
        return self._infer(self.observation_vector(request.world))

    def _chunks_impl(self, requests: Sequence[ChunkRequest]) -> list[np.ndarray]:
        """One inference over the stacked observations (one by one for a model without a dynamic batch dimension)."""
        if len(requests) == 1 or self.batch_capacity() == 1:
            return [self._chunk_impl(request) for request in requests]
        batch = np.concatenate([self.observation_vector(request.world) for request in requests])
        (output,) = self._session.run(None, {self._input: batch})
        rows = np.asarray(output, dtype=np.float64).reshape(len(requests), -1, len(self.names))
        return list(rows)


def _read_metadata(path: Path) -> dict[str, str]:
    """The model's ``metadata_props`` (chunk size, description, ...), read without building a session."""
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:
        raise ROSConfigError(f"cannot load {path}: {exc}", field="params.model") from exc
    return dict(session.get_modelmeta().custom_metadata_map)
