"""``remote_policy``: a chunking policy that runs on another machine, served by ``openral serve``.

On the robot it is a skill like any other: its chunk size, action names, representation (so its
rows are anchored as they would be locally), observation and observation steps come from the
server's ``meta``, read once when the skill is built (the server must be up by then, within
``connect_timeout_s``). The chunk executor asks for each chunk (one array, as decoded) on its
worker thread, never on the tick. Each request carries what a local policy would be asked with:
the earlier observations it reads (kept by the executor, so a lost request or a reset leaves no
stale history on the server), the executor's prefix and the episode's seed. While the server is
down (:meth:`available` is ``False``) the executor's fallback acts: ``hold``, a local ``skill``
(e.g. an ONNX policy) or a safe ``stop``, configured under ``executor:``.

The server reached when the skill is built is pinned (its Zenoh id, or ``server_id`` given up
front): start-up and every later return must be that server unless ``on_server_change: accept``.
TLS files in the ``zenoh:`` block are checked when the file is validated and before connecting.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Self

import numpy as np

from openral_core import RobotManifest, ROSConfigError, RSkillInfo
from openral_remote.allocator import keep_message_memory
from openral_remote.client import SHAPE_FIELDS, RemotePolicyClient, check_compatible
from openral_remote.config import RemotePolicyParams
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta
from openral_remote.tls import check_tls
from openral_rskill.anchoring import Anchor
from openral_rskill.base import ChunkingSkillBase, validate_params
from openral_rskill.chunks import ChunkRequest

SKILL_ID = "remote_policy"


class RemotePolicySkill(ChunkingSkillBase):
    """Asks a policy server for each chunk.

    Args:
        robot: This robot (its id names the key unless ``params.robot`` does; its joints must
            match the policy's action dimensions).
        params: Which server, the deadline, what a changed model means.
        rate_hz: The loop's rate; must match the policy's step.
    """

    def __init__(self, robot: RobotManifest, params: RemotePolicyParams, *, rate_hz: float) -> None:
        super().__init__()
        self.params = params
        self.keys = PolicyKeys.of(params.robot or robot.robot_id, params.policy)
        self.server_id = params.server_id
        """The pinned server's Zenoh id: the one reached at build, unless pinned up front."""
        self.client = self._new_client()
        try:  # what the policy is decides how the runner is built: ask now, then let go until configure
            self.meta: PolicyMeta = self.client.connect(params.connect_timeout_s)
            self.server_id = self.client.server_id
        finally:
            self.client.close()
        check_compatible(self.meta, action_dims=len(robot.joint_names), rate_hz=rate_hz, field="params.policy")
        self._info = RSkillInfo(
            skill_id=SKILL_ID,
            name=f"{self.meta.policy} served at {self.keys.prefix}",
            version=self.meta.skill_version,
            control_mode=self.meta.control_mode,
            chunk_size=self.meta.chunk_size,
            description=f"{self.meta.skill_id} on a policy server (model {self.meta.model_hash[:12]}, "
            f"Zenoh id {self.server_id})",
            observation=self.meta.observation,
            observation_steps=self.meta.observation_steps,
        )

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        """Build the skill for a deployment; the process keeps its message memory from here on.

        A robot on a remote policy moves a camera-sized request every tick: glibc is told to keep
        that memory for reuse (:func:`~openral_remote.allocator.keep_message_memory`), once per process.
        """
        keep_message_memory()
        checked = validate_params(RemotePolicyParams, params, skill_id=SKILL_ID)
        _check_files(checked)
        return cls(robot, checked, rate_hz=rate_hz)

    @classmethod
    def check_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> None:
        """Check the parameters and TLS files without asking the server (what it serves is known once it answers)."""
        checked = validate_params(RemotePolicyParams, params, skill_id=SKILL_ID)
        PolicyKeys.of(checked.robot or robot.robot_id, checked.policy)
        _check_files(checked)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    @property
    def action_names(self) -> list[str]:
        return list(self.meta.action_names)

    def action_anchor(self) -> Anchor:
        """The anchor the served skill would use locally."""
        return self.meta.anchor.build()

    def available(self) -> bool:
        return self.client.available()

    def _new_client(self) -> RemotePolicyClient:
        params = self.params
        return RemotePolicyClient(
            self.keys,
            params.zenoh,
            deadline_ms=params.deadline_ms,
            on_model_change=params.on_model_change,
            jpeg_quality=params.jpeg_quality,
            server_id=self.server_id,
            on_server_change=params.on_server_change,
        )

    def _on_configure(self) -> None:
        self.client = self._new_client()
        meta = self.client.connect(self.params.connect_timeout_s)  # refuses a server with another id
        self.server_id = self.client.server_id
        changed = self.meta.differences(meta)
        if changed and (self.params.on_model_change == "refuse" or SHAPE_FIELDS.intersection(changed)):
            self.client.close()
            raise ROSConfigError(
                f"the policy server's {', '.join(changed)} changed between build and start",
                field="params.on_model_change",
            )
        self.client.meta = self.meta  # a later return is judged against the policy the runner was built for

    def _on_shutdown(self) -> None:
        self.client.close()

    def _on_reset(self) -> None:
        if self.client.available():
            self.client.reset(self.episode_seed)

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The server's chunk for the request (observation, history, prefix, seed): the decoded array, as it came."""
        return self.client.infer(request, seed=self.episode_seed)


def _check_files(params: RemotePolicyParams) -> None:
    """The ``zenoh.tls`` files, named by their place in the deployment."""
    if params.zenoh.tls is not None:
        check_tls(params.zenoh.tls, prefix="vla.params.zenoh.tls.")
