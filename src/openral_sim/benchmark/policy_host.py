"""A row's policy served once (in this process or as a Ray actor) for its episodes to run as its clients."""

from __future__ import annotations

from typing import Any

from openral_core import BenchmarkRun, SimEnvironment
from openral_remote.admission import ServeLimits
from openral_sim.evaluation import Evaluator
from openral_sim.served import REMOTE_SKILL, PolicyHost, ray_policy_host

MAX_BATCH = 1024
"""The most requests one inference of a served row takes."""


class RowPolicyServer:
    """A row's policy server (a :class:`PolicyHost` here, or its Ray actor) and the skill its workers run.

    Args:
        host: The :class:`PolicyHost`, or the handle of the Ray actor holding one.
        ray: The ``ray`` module when ``host`` is an actor (its methods are then called remotely).
    """

    def __init__(self, host: Any, ray: Any = None) -> None:
        self._host = host
        self._ray = ray
        self.skill_id: str = REMOTE_SKILL
        self.params: dict[str, Any] = self._call("client_params")

    def _call(self, method: str) -> Any:
        if self._ray is None:
            return getattr(self._host, method)()
        return self._ray.get(getattr(self._host, method).remote())

    def close(self) -> dict[str, int]:
        """Stop the server; what it served."""
        try:
            return dict(self._call("stats"))
        finally:
            self._call("close")


def serve_row(
    scene: SimEnvironment, run: BenchmarkRun, *, evaluator: Evaluator, max_batch: int | None, gpus: float
) -> RowPolicyServer:
    """Serve ``run``'s policy for ``scene``: in this process, or as a Ray actor with ``gpus`` on the evaluator's Ray.

    Without ``max_batch`` one inference takes a request from each process that asks.

    Raises:
        ROSConfigError: The skill cannot be served (one row per request, or a bad parameter).
    """
    # On Ray the cluster's CPUs are the processes that ask: each is a client with a request in flight.
    processes = evaluator.processes or max(1, int(evaluator.ray().cluster_resources().get("CPU", 1)))
    limits = ServeLimits(
        max_batch=min(max_batch or processes, MAX_BATCH),
        max_clients=max(32, 2 * processes),
        max_pending=max(64, 4 * processes),
    )
    if evaluator.ray_address is None:
        return RowPolicyServer(PolicyHost(scene, run.skill, dict(run.skill_params), limits=limits))
    ray = evaluator.ray()  # initialised before the actor is asked for
    actor = ray_policy_host(scene, run.skill, dict(run.skill_params), limits=limits, num_gpus=gpus)
    return RowPolicyServer(actor, ray=ray)
