"""The policy server's waiting requests: per client, taken in turn, bounded, and gathered into batches.

* **Latest wins** per client: an inference still waiting when the same client asks again is
  taken out (the caller answers it ``superseded``). A client therefore has at most one
  inference waiting, behind its resets.
* **In turn**: clients are served round-robin in the order they started waiting, one job each
  per turn, so a client that asks often cannot push the others back.
* **Bounded**: at most ``max_pending`` jobs wait. When full, a request from a client the server
  has already served (a robot under way) displaces the newest job of a client it has never
  served; anything else is refused at once. A flood of requests under fresh client ids can
  therefore not lock a robot out.
* **Batches**: :meth:`FairQueue.take` hands out either one reset or up to ``max_batch``
  inferences of different clients, waiting at most ``max_wait_s`` after the oldest of them for
  the batch to fill, and not at all when every active client is already in it.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

RESET = "reset"
INFER = "infer"


@dataclass
class Job:
    """One request waiting for the worker."""

    query: Any
    kind: str
    client: str = ""
    attachment: dict[str, Any] = field(default_factory=dict)
    payload: bytes = b""
    received_ns: int = field(default_factory=time.monotonic_ns)
    established: bool = False
    """Its client had been served before it came (a robot under way, not a newcomer)."""


@dataclass
class Admission:
    """What :meth:`FairQueue.put` did: the job taken or not, and the jobs it pushed out (to be answered)."""

    accepted: bool
    superseded: list[Job] = field(default_factory=list)
    displaced: list[Job] = field(default_factory=list)


class FairQueue:
    """Jobs per client, served in turn (thread-safe: Zenoh's threads put, the worker takes)."""

    def __init__(self, max_pending: int) -> None:
        self.max_pending = max_pending
        self._clients: collections.OrderedDict[str, collections.deque[Job]] = collections.OrderedDict()
        self._pending = 0
        self._closed = False
        self._wake = threading.Condition()

    def __len__(self) -> int:
        return self._pending

    def put(self, job: Job) -> Admission:
        """Queue ``job``, pushing out what it supersedes or (when full and ``job.established``) displaces."""
        with self._wake:
            if self._closed:
                return Admission(accepted=False)
            waiting = self._clients.get(job.client)
            superseded = []
            if job.kind == INFER and waiting:
                superseded = [old for old in waiting if old.kind == INFER]
                for old in superseded:
                    waiting.remove(old)
                self._pending -= len(superseded)
            displaced: list[Job] = []
            if self._pending >= self.max_pending:
                victim = self._newest_of_newcomers(job.client) if job.established else None
                if victim is None:
                    self._drop_empty(job.client)
                    return Admission(accepted=False, superseded=superseded)
                displaced.append(victim)
            self._clients.setdefault(job.client, collections.deque()).append(job)
            self._pending += 1
            self._wake.notify()
            return Admission(accepted=True, superseded=superseded, displaced=displaced)

    def take(self, max_batch: int, max_wait_s: float, active_clients: Callable[[], int]) -> list[Job]:
        """The next reset alone, or up to ``max_batch`` inferences of different clients; ``[]`` once closed.

        Blocks until there is work. A batch short of ``max_batch`` waits for more clients until
        ``max_wait_s`` after its oldest request, unless it already holds every active client.
        """
        with self._wake:
            while not self._pending and not self._closed:
                self._wake.wait()
            if self._closed:
                return []
            head = next(iter(self._clients.values()))
            if head[0].kind == RESET:
                return [self._pop(head[0].client)]
            batch = self._heads(max_batch)
            if max_batch > 1 and max_wait_s > 0:
                deadline_ns = min(job.received_ns for job in batch) + int(max_wait_s * 1e9)
                while len(batch) < min(max_batch, active_clients()) and not self._closed:
                    remaining = (deadline_ns - time.monotonic_ns()) / 1e9
                    if remaining <= 0:
                        break
                    self._wake.wait(remaining)
                    batch = self._heads(max_batch)
                if self._closed:
                    return []
            return [self._pop(job.client) for job in batch]

    def drain(self) -> list[Job]:
        """Close the queue and hand back every job still waiting (to be answered)."""
        with self._wake:
            self._closed = True
            jobs = [job for waiting in self._clients.values() for job in waiting]
            self._clients.clear()
            self._pending = 0
            self._wake.notify_all()
            return jobs

    def _heads(self, limit: int) -> list[Job]:
        """The first job of each client in turn, where that job is an inference, up to ``limit``."""
        heads = [waiting[0] for waiting in self._clients.values() if waiting[0].kind == INFER]
        return heads[:limit]

    def _pop(self, client: str) -> Job:
        waiting = self._clients[client]
        job = waiting.popleft()
        self._pending -= 1
        del self._clients[client]
        if waiting:
            self._clients[client] = waiting  # to the back of the turn
        return job

    def _newest_of_newcomers(self, exempt: str) -> Job | None:
        """Take out the newest job of a client never served before it asked."""
        newest: Job | None = None
        for client, waiting in self._clients.items():
            if client == exempt:
                continue
            for job in waiting:
                if not job.established and (newest is None or job.received_ns > newest.received_ns):
                    newest = job
        if newest is not None:
            self._clients[newest.client].remove(newest)
            self._pending -= 1
            self._drop_empty(newest.client)
        return newest

    def _drop_empty(self, client: str) -> None:
        if client in self._clients and not self._clients[client]:
            del self._clients[client]


__all__ = ["INFER", "RESET", "Admission", "FairQueue", "Job"]
