"""One episode per client of a policy server: a robot's reset and its chunks are its own.

A client is the id in its requests' attachment. A skill whose chunk depends on the request alone
(:meth:`~openral_rskill.base.RSkillBase.serves_many_episodes`: an ONNX or LeRobot chunk policy)
is loaded once and shared, and a client's episode is its seed and counters: its observation
history, the executor's prefix and its seed come with each request (a lost request, a reset or a
server restart leaves nothing stale behind); the seed kept here serves a client that sends it
with its reset alone. Any other skill (a scripted expert with a plan, a policy with a queue)
gets an instance per client from the server's factory, configured on that client's first
request, so one robot's reset never moves another robot's chunks.

At most ``max_clients`` episodes exist. A new client takes the place of the one silent longest
once that one has been silent ``client_idle_s``; until then it is refused (the robots under way
keep theirs).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import structlog

from openral_remote.admission import ServeLimits
from openral_rskill.base import RSkillBase

_log = structlog.get_logger(__name__)

ACTIVE_WINDOW_S = 1.0
"""A client that asked within this long counts as active (a batch waits for the active ones only)."""


@dataclass
class ClientEpisode:
    """What the server keeps of one client."""

    client: str
    seed: int | None = None
    served: int = 0
    resets: int = 0
    last_seen: float = 0.0
    skill: RSkillBase | None = None
    """Its own skill instance (``None``: the shared one)."""


class EpisodeTable:
    """The clients' episodes (thread-safe: Zenoh's threads admit, the worker serves).

    Args:
        shared: The configured, active skill: shared when it serves many episodes, else the
            first client's own.
        factory: Makes another unconfigured instance for each further client of a skill that
            cannot be shared; without one, such a skill serves one client at a time.
        limits: ``max_clients`` and ``client_idle_s``.
        clock: Monotonic seconds (a test's clock).
    """

    def __init__(
        self,
        shared: RSkillBase,
        *,
        factory: Callable[[], RSkillBase] | None,
        limits: ServeLimits,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.shared = shared.serves_many_episodes()
        self._primary = shared
        self._primary_owner: str | None = None
        self._factory = factory
        self._capacity = limits.max_clients if (self.shared or factory is not None) else 1
        self._idle_s = limits.client_idle_s
        self._clock = clock
        self._episodes: dict[str, ClientEpisode] = {}
        self._retired: list[RSkillBase] = []
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._episodes)

    def established(self, client: str) -> bool:
        """Whether ``client`` has been served a chunk (a robot under way)."""
        episode = self._episodes.get(client)
        return episode is not None and episode.served > 0

    def active(self) -> int:
        """Clients that asked within the last second."""
        since = self._clock() - ACTIVE_WINDOW_S
        return sum(1 for episode in list(self._episodes.values()) if episode.last_seen >= since)

    def admit(self, client: str) -> bool:
        """Make room for ``client`` (noting it was seen); ``False`` when every place is held by a recent client."""
        now = self._clock()
        with self._lock:
            episode = self._episodes.get(client)
            if episode is None:
                if len(self._episodes) >= self._capacity and not self._evict_idle(now):
                    return False
                episode = self._episodes[client] = ClientEpisode(client)
            episode.last_seen = now
            return True

    def episode(self, client: str) -> ClientEpisode:
        """The episode of ``client`` (admitted before), created if it was evicted meanwhile."""
        with self._lock:
            episode = self._episodes.get(client)
            if episode is None:
                episode = self._episodes[client] = ClientEpisode(client, last_seen=self._clock())
            return episode

    def skill_of(self, episode: ClientEpisode) -> RSkillBase:
        """The skill that serves ``episode``: the shared one, or its own (configured now on first use).

        Called on the worker thread only.

        Raises:
            ROSSkillError: Its instance failed to configure or activate.
        """
        self._shutdown_retired()
        if self.shared:
            return self._primary
        if episode.skill is None:
            with self._lock:
                handed_on = self._primary_owner is not None and self._primary_owner not in self._episodes
                if self._primary_owner is None or handed_on:
                    self._primary_owner = episode.client
                    episode.skill = self._primary
            if handed_on and episode.skill is self._primary:
                self._primary.reset(seed=None)  # its last client's episode ends here
            if episode.skill is None:
                assert self._factory is not None, "a skill that cannot be shared serves one client without a factory"
                skill = self._factory()
                skill.configure()
                skill.activate()
                episode.skill = skill
                _log.info("policy instance built for a client", client=episode.client, clients=len(self._episodes))
        return episode.skill

    def release(self, client: str) -> None:
        """Free the episode of ``client``, which left (its own instance is shut down by the worker)."""
        with self._lock:
            episode = self._episodes.pop(client, None)
            if episode is not None and episode.skill is not None and episode.skill is not self._primary:
                self._retired.append(episode.skill)

    def retire_all(self) -> None:
        """Shut down every per-client instance (the shared one is the server's to close)."""
        with self._lock:
            for episode in self._episodes.values():
                if episode.skill is not None and episode.skill is not self._primary:
                    self._retired.append(episode.skill)
            self._episodes.clear()
        self._shutdown_retired()

    def _evict_idle(self, now: float) -> bool:
        """Drop the client silent longest if it has been silent ``client_idle_s`` (lock held)."""
        oldest = min(self._episodes.values(), key=lambda e: e.last_seen)
        if now - oldest.last_seen < self._idle_s:
            return False
        del self._episodes[oldest.client]
        if oldest.skill is not None and oldest.skill is not self._primary:
            self._retired.append(oldest.skill)  # shut down by the worker, which may still hold it
        _log.info("idle client's episode given up", client=oldest.client, idle_s=round(now - oldest.last_seen, 1))
        return True

    def _shutdown_retired(self) -> None:
        with self._lock:
            retired, self._retired = self._retired, []
        for skill in retired:
            try:
                skill.shutdown()
            except Exception as exc:
                _log.warning("a client's policy instance failed to shut down", error=str(exc))


__all__ = ["ClientEpisode", "EpisodeTable"]
