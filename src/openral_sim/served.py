"""Served evaluation: one policy server for a suite row, its episodes run as ``remote_policy`` clients of it.

The model is loaded once (on the GPU where there is one) instead of once per worker, and the
workers' requests reach it concurrently, so a server started with ``max_batch`` above 1 batches
them. With the scene's ``virtual_latency`` (the default) a tick whose chunk is due waits for it,
so the outcomes are those of the local run for the same seeds; the server keeps an episode per
worker, reset with each episode's seed.

:class:`PolicyHost` serves in this process (on Zenoh's and the server's threads, while the
workers are other processes); :func:`ray_policy_host` starts the same as a Ray actor, given GPUs
when asked, for the episodes to run as Ray tasks on the cluster.
"""

from __future__ import annotations

import socket
from collections.abc import Mapping
from typing import Any

from openral_core import ROSConfigError, ROSDependencyMissing, SimEnvironment
from openral_remote.admission import ServeLimits
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import describe, model_hash
from openral_rskill.base import RSkillBase
from openral_runner.factory import SKILL_REGISTRY
from openral_sim.env import make_env

REMOTE_SKILL = "remote_policy"
SERVED_NAME = "evaluated"
"""The served policy's name in its key: one server per row, so one name will do."""


def _free_port(host: str) -> int:
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


class PolicyHost:
    """A policy server for ``skill_id`` on ``scene``'s action space, up from construction until :meth:`close`.

    Args:
        scene: The row's scene (its action space and rate are the policy's).
        skill_id: The skill to serve, with ``skill_params``.
        limits: Batching and admission (``max_batch`` above 1 batches the workers' requests).
        host: The address to listen on (``127.0.0.1`` for workers on this machine).
        advertise: The address workers connect to (default: ``host``).

    Raises:
        ROSConfigError: The skill cannot be served (one row per request, or a bad parameter).
    """

    def __init__(
        self,
        scene: SimEnvironment,
        skill_id: str,
        skill_params: Mapping[str, Any],
        *,
        limits: ServeLimits,
        host: str = "127.0.0.1",
        advertise: str | None = None,
    ) -> None:
        from openral_remote.server import PolicyServer  # noqa: PLC0415 (Zenoh: the 'remote' extra)

        env = make_env(scene)
        try:
            spec = env.spec
        finally:
            env.close()
        robot = spec.action_manifest(scene.robot or scene.env)
        plugin = SKILL_REGISTRY.resolve(skill_id, field="skill")
        params = dict(skill_params)
        skill: RSkillBase = plugin.from_config(params, robot=robot, rate_hz=spec.control_hz)
        if skill.info.chunk_size < 2:
            raise ROSConfigError(
                f"{skill_id} returns one row per request and cannot be served: a row cannot arrive in time",
                field="skill",
                hint="evaluate it locally (without --serve), or serve a chunking policy",
            )
        self.keys = PolicyKeys.of(robot.robot_id, SERVED_NAME)
        meta = describe(
            skill,
            policy=SERVED_NAME,
            robot=robot.robot_id,
            action_names=robot.joint_names,
            rate_hz=spec.control_hz,
            model_hash=model_hash(skill_id, params),
        )
        port = _free_port(host)
        self.endpoint = f"tcp/{advertise or host}:{port}"
        self.server = PolicyServer(
            skill,
            keys=self.keys,
            zenoh=ZenohConfig(listen=[f"tcp/{host}:{port}"]),
            meta=meta,
            limits=limits,
            factory=lambda: plugin.from_config(params, robot=robot, rate_hz=spec.control_hz),
        )
        self.server.start()

    def client_params(self) -> dict[str, Any]:
        """The ``remote_policy`` parameters of a worker of this server."""
        return remote_params(self.endpoint, self.keys.robot)

    def stats(self) -> dict[str, int]:
        """What the server did: requests served, the inferences they took, the largest batch."""
        stats = self.server.stats
        return {"served": stats.served, "inferences": stats.batches, "largest_batch": stats.largest_batch}

    def close(self) -> None:
        self.server.close()


def remote_params(endpoint: str, robot: str) -> dict[str, Any]:
    """``remote_policy`` parameters for a worker: generous deadlines, since a due tick waits for its chunk anyway."""
    return {
        "policy": SERVED_NAME,
        "robot": robot,
        "zenoh": {"connect": [endpoint]},
        "deadline_ms": 60_000.0,
        "connect_timeout_s": 120.0,
    }


def ray_policy_host(
    scene: SimEnvironment, skill_id: str, skill_params: Mapping[str, Any], *, limits: ServeLimits, num_gpus: float
) -> Any:
    """A :class:`PolicyHost` in a Ray actor (``num_gpus`` of the cluster's GPUs), listening on its node's address.

    Call ``client_params``, ``stats`` and ``close`` on it with ``.remote()``.
    """
    try:
        import ray  # noqa: PLC0415
    except ImportError as exc:
        raise ROSDependencyMissing("ray", extra="ray", needed_for="serving on a Ray cluster") from exc

    class _RayHost(PolicyHost):
        def __init__(self) -> None:
            super().__init__(
                scene,
                skill_id,
                skill_params,
                limits=limits,
                host="0.0.0.0",  # the cluster's workers connect from other nodes
                advertise=str(ray.util.get_node_ip_address()),  # type: ignore[no-untyped-call]
            )

    return ray.remote(num_gpus=num_gpus, num_cpus=0)(_RayHost).remote()


__all__ = ["REMOTE_SKILL", "SERVED_NAME", "PolicyHost", "ray_policy_host", "remote_params"]
