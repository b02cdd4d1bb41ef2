"""``lerobot_policy``: a checkpoint trained with LeRobot (ACT, Diffusion, ...) run as an openral skill.

.. code-block:: yaml

    vla:
      id: lerobot_policy
      params:
        path: outputs/train/act_so101/checkpoints/last/pretrained_model
        device: auto            # cpu | cuda | mps | auto
        joint_units: degrees    # radians (openral recordings) | degrees | range (LeRobot's SO-101 conventions)

Building the skill reads only the folder's JSON: the policy's inputs are matched to what the
deployment supplies (:mod:`openral_rskill.lerobot.observation`), its chunk size and history length
become the skill's, and nothing heavy is imported, so ``openral validate`` is quick and needs no
torch (whether LeRobot knows the policy type, built in or registered by an installed
``lerobot_policy_*`` plugin, is known only at ``configure``). ``configure`` imports LeRobot's
plugins and loads the policy through LeRobot's own API on the device, checks the joint units
against the saved normalisation statistics, and runs ``warmup_inferences`` real inferences there
(CUDA context, kernels, allocator), so the first tick is on time. A chunking policy runs behind the
chunk executor: its chunk is one array from the model to the executor, its first ``rows`` rows used
(the checkpoint's ``n_action_steps`` unless overridden).

A prefix-conditioned policy (``act_smooth``; :mod:`openral_rskill.lerobot.prefix`) is fed the
executor's prefix, the targets it sends while the inference runs, in the policy's units: held to
the request's delay as the executor holds it and clipped to the delays the checkpoint was trained
on (logged). With no prefix (an episode's first request, or a synchronous executor) the row that
stands for it is the last command sent, else the measured joints, else, for an action space of
another kind (a simulation's end-effector moves), the action the training statistics centre on.
Its chunk comes back aligned as every chunk is, row ``i`` for tick ``obs_tick + i``: the rows it
was fed, then the model's. Its past commands are those the executor hands back after the safety check.

A policy class from a plugin package runs only when the package's licence is accepted:
``params.accept_licenses`` lists the SPDX ids accepted (default: the open ones), and a package that
declares none is ``NOASSERTION``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal, Self

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import Action, ControlMode, RobotManifest, ROSConfigError, RSkillInfo, WorldState
from openral_hal.lerobot.units import JointUnits, UnitConversion, plausible_units
from openral_rskill.anchoring import AbsoluteAnchor, ActionRepresentation, Anchor, StateOffsetAnchor
from openral_rskill.base import ChunkingSkillBase, validate_params
from openral_rskill.chunks import ChunkRequest
from openral_rskill.lerobot.checkpoint import Checkpoint
from openral_rskill.lerobot.observation import ObservationMap
from openral_rskill.lerobot.prefix import PolicyPrefix, PrefixSpec, committed_rows
from openral_rskill.worker_threads import threads_per_worker

_log = structlog.get_logger(__name__)

SKILL_ID = "lerobot_policy"
MAX_BATCH = 256
"""Requests one forward pass takes at most (a policy server batches its robots' requests)."""


class LeRobotPolicyParams(BaseModel):
    """``params`` of the ``lerobot_policy`` skill."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    path: str = Field(min_length=1, description="The checkpoint folder (pretrained_model) lerobot-train wrote.")
    device: Literal["cpu", "cuda", "mps", "auto"] = Field(
        default="auto", description="Where the policy runs; cuda or mps without one refuses to configure."
    )
    joint_units: JointUnits = Field(
        default="radians",
        description="The units the policy's state and actions are in: radians (openral's recordings), degrees "
        "or range (LeRobot's SO-101 conventions, gripper 0-100).",
    )
    cameras: dict[str, str] = Field(
        default_factory=dict, description="Policy camera name -> sensor id, where they differ."
    )
    rows: int | None = Field(
        default=None, ge=1, le=10_000, description="Rows of each chunk used (default: the checkpoint's n_action_steps)."
    )
    representation: Literal["absolute", "relative_to_state"] = Field(
        default="absolute", description="absolute targets, or offsets from the state measured with the observation."
    )
    warmup_inferences: int = Field(default=3, ge=0, le=100, description="Inferences run at configure.")
    threads: int | None = Field(
        default=None,
        ge=1,
        le=256,
        description="PyTorch CPU threads (default: an evaluation worker's allowance, else PyTorch's own).",
    )
    accept_licenses: list[str] | None = Field(
        default=None,
        description="SPDX ids accepted for a policy from a plugin package (default: the open ones); "
        "NOASSERTION accepts one that declares no licence.",
    )


class LeRobotPolicySkill(ChunkingSkillBase):
    """A LeRobot checkpoint: observations mapped from the world state, chunks handed over as arrays.

    Args:
        robot: This robot (its joints are the state's and the action's order).
        params: The checkpoint and how to run it.
        rate_hz: The loop's rate.

    Raises:
        ROSConfigError: Not a complete local checkpoint, an input the deployment cannot supply,
            or an action of another size than the robot's.
    """

    def __init__(self, robot: RobotManifest, params: LeRobotPolicyParams, *, rate_hz: float) -> None:
        super().__init__()
        self.robot = robot
        self.params = params
        self.checkpoint = Checkpoint.read(params.path)
        action_dims = self.checkpoint.action.shape[0]
        if action_dims != len(robot.joints):
            raise ROSConfigError(
                f"the policy acts on {action_dims} dimensions but '{robot.robot_id}' has {len(robot.joints)} "
                f"({', '.join(robot.joint_names)})",
                field="params.path",
            )
        self.units = UnitConversion(robot, params.joint_units)
        self.inputs = ObservationMap(self.checkpoint, robot=robot, units=self.units, cameras=params.cameras)
        chunking = self.checkpoint.chunk_size > 1
        rows = params.rows or self.checkpoint.n_action_steps
        if rows > self.checkpoint.chunk_size:
            raise ROSConfigError(
                f"the policy predicts {self.checkpoint.chunk_size} rows per chunk; {rows} cannot be used",
                field="params.rows",
            )
        self.rows = rows if chunking else 1
        self.prefix: PrefixSpec | None = self.checkpoint.prefix if chunking else None
        if self.prefix is not None and params.representation != "absolute":
            raise ROSConfigError(
                f"the {self.checkpoint.policy_type} policy continues the targets already committed: its actions "
                "must be absolute",
                field="params.representation",
            )
        self._policy: Any = None
        self._clipped_logged = False
        self._limits = (np.array([j.lower for j in robot.joints]), np.array([j.upper for j in robot.joints]))
        """The robot's joint limits: a committed row beyond them is sent clamped, and is fed as sent."""
        self._info = RSkillInfo(
            skill_id=SKILL_ID,
            name=f"LeRobot {self.checkpoint.policy_type} {self.checkpoint.path.name}",
            control_mode=ControlMode.JOINT_POSITION,
            chunk_size=self.rows,
            description=f"{self.checkpoint.policy_type} checkpoint at {self.checkpoint.path}",
            observation=self.inputs.reads,
            observation_steps=self.checkpoint.observation_steps,
            # the last command sent also stands for an empty prefix
            past_actions=0 if self.prefix is None else max(self.prefix.past, 1),
        )

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(LeRobotPolicyParams, params, skill_id=SKILL_ID), rate_hz=rate_hz)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    @property
    def action_names(self) -> list[str]:
        return list(self.robot.joint_names)

    @property
    def device(self) -> str | None:
        """The device the policy runs on once configured."""
        return None if self._policy is None else str(self._policy.device)

    def check_robot_inputs(self) -> None:
        """On a robot: a state of the robot's joints, no simulator's environment state."""
        self.inputs.check_robot()

    def action_anchor(self) -> Anchor:
        if ActionRepresentation(self.params.representation) is ActionRepresentation.RELATIVE_TO_STATE:
            return StateOffsetAnchor(self.robot.joint_names)
        return AbsoluteAnchor()

    def _on_configure(self) -> None:
        # Loaded only here: torch and lerobot (the 'lerobot' extra) take seconds to import.
        from openral_rskill.lerobot.runtime import LoadedPolicy  # noqa: PLC0415

        params = self.params
        threads = params.threads if params.threads is not None else threads_per_worker()
        policy = LoadedPolicy(
            self.checkpoint, device=params.device, threads=threads, accept_licenses=params.accept_licenses
        )
        self._check_units(policy.state_bound())
        self._policy = policy
        self._mean_action = policy.action_mean() if self.prefix is not None else None
        blank = self.inputs.blank()
        warmup = ChunkRequest(WorldState(stamp_ns=0))
        for _ in range(params.warmup_inferences):  # on the device: the first tick must not pay for it
            self._infer([blank] * self.checkpoint.observation_steps, "", prefix=self._policy_prefix(warmup)[1])
        policy.reset(None)

    def _check_units(self, bound: float | None) -> None:
        """Refuse units the training statistics contradict (degrees read as radians moves the arm 57x too far)."""
        state = self.inputs.state
        if bound is None or state is None or state.shape[0] != len(self.robot.joints):
            return  # a simulator's state vector (velocities, positions in metres): no joint convention to check
        seen = plausible_units(bound)
        declared = self.params.joint_units
        if (declared == "radians") != (seen == "radians"):
            raise ROSConfigError(
                f"the policy's observation.state reached {bound:.3g} in training, which is "
                f"{'not ' if seen != 'radians' else ''}radians, but joint_units is {declared}",
                field="params.joint_units",
                hint="radians for openral recordings; degrees or range for LeRobot's SO-101 datasets",
            )

    def _on_shutdown(self) -> None:
        self._policy = None

    def _on_reset(self) -> None:
        self._clipped_logged = False
        if self._policy is not None:
            self._policy.reset(self.episode_seed)

    def _infer(
        self,
        observations: list[dict[str, np.ndarray]],
        task: str,
        seed: int | None = None,
        prefix: PolicyPrefix | None = None,
    ) -> np.ndarray:
        rows = self._policy.chunk(observations, task, seed, prefix)[: self.rows]
        return self._radians(rows)

    def _radians(self, rows: np.ndarray) -> np.ndarray:
        return rows if self.units.identity else self.units.to_radians(rows)

    def _policy_units(self, rows: np.ndarray) -> np.ndarray:
        return rows if self.units.identity else self.units.to_policy(rows)

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        worlds = request.observations(self.checkpoint.observation_steps)
        seed = request.draw_seed(self.episode_seed)
        committed, prefix = self._policy_prefix(request)
        rows = self._infer([self.inputs.arrays(w) for w in worlds], request.world.task or "", seed, prefix)
        return rows if committed is None else np.concatenate([committed, rows])

    def _policy_prefix(self, request: ChunkRequest) -> tuple[np.ndarray | None, PolicyPrefix | None]:
        """A prefix-conditioned policy's committed rows (the robot's units) and its prefix (the policy's units).

        ``(None, None)`` for a policy that reads no prefix.
        """
        spec = self.prefix
        if spec is None:
            return None, None
        delay = request.inference_delay
        if spec.max_delay is not None and delay > spec.max_delay and not self._clipped_logged:
            self._clipped_logged = True  # once an episode: it holds for the episode's requests alike
            _log.info(
                "prefix delay clipped to the trained range",
                delay=delay,
                trained=spec.max_delay,
                policy=self.checkpoint.policy_type,
                hint="the executor skips the rows beyond it; train with a longer prefix to condition on them",
            )
        # The buffered rows as the envelope will send them: a policy fed rows past the limits runs away.
        committed = np.clip(committed_rows(request.prefix, delay, spec, self._start_row(request)), *self._limits)
        past = request.past[len(request.past) - spec.past :] if spec.past else request.past[:0]
        prefix = PolicyPrefix(self._policy_units(committed), self._policy_units(past.reshape(-1, len(committed[0]))))
        return committed, prefix

    def _start_row(self, request: ChunkRequest) -> np.ndarray:
        """What stands for an empty prefix: the last command sent, the measured joints, or the mean action."""
        if len(request.past):
            return np.asarray(request.past[-1], dtype=np.float64)
        joints = request.world.joint_state
        if joints is not None:
            by_name = dict(zip(joints.names, joints.positions, strict=True))
            names = self.robot.joint_names
            if all(name in by_name for name in names):
                return np.array([by_name[name] for name in names], dtype=np.float64)
        assert self._mean_action is not None
        return self._radians(self._mean_action)

    def serves_many_episodes(self) -> bool:
        """A chunk policy's chunk is a function of its request; a per-tick one keeps a queue of actions.

        Its history comes with the request, and a sampling policy (Diffusion, flow matching) draws
        each request's noise from the request's episode seed and tick
        (:meth:`~openral_rskill.chunks.ChunkRequest.draw_seed`): shared between robots, each
        robot's run is reproducible from its own seed.
        """
        return self.checkpoint.chunk_size > 1

    def batch_capacity(self) -> int:
        return MAX_BATCH if self.checkpoint.chunk_size > 1 else 1

    def _chunks_impl(self, requests: Sequence[ChunkRequest]) -> list[np.ndarray]:
        """Several requests in one forward pass of the policy."""
        steps = self.checkpoint.observation_steps
        observations = [[self.inputs.arrays(w) for w in request.observations(steps)] for request in requests]
        tasks = [request.world.task or "" for request in requests]
        seeds = [request.draw_seed(self.episode_seed) for request in requests]
        prefixes = [self._policy_prefix(request) for request in requests]
        chunks = self._policy.chunks(observations, tasks, seeds, [prefix for _, prefix in prefixes])
        rows = [self._radians(chunk[: self.rows]) for chunk in chunks]
        return [
            r if committed is None else np.concatenate([committed, r])
            for (committed, _), r in zip(prefixes, rows, strict=True)
        ]

    def _step_impl(self, world_state: WorldState) -> Action:
        """A chunk policy's first row for this tick; a per-tick policy's next action from its own queue."""
        if self.prefix is not None:  # the rows after the one it was fed for this very tick
            return self._rows_action(world_state, self._chunk_impl(ChunkRequest(world_state))[1:2])
        if self.checkpoint.chunk_size > 1:
            return super()._step_impl(world_state)
        action = self._policy.select(self.inputs.arrays(world_state), world_state.task or "")
        row = action if self.units.identity else self.units.to_radians(action)
        return self._rows_action(world_state, row.reshape(1, -1))


__all__ = ["LeRobotPolicyParams", "LeRobotPolicySkill"]
