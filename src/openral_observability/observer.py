"""``TickObserver``: the seam for everything that watches ticks (visualisers, recorders, dashboards).

Observers are called on the tick thread right after each tick is accounted, so they must
only hand data over (a reference into a queue) and do their work elsewhere
(:class:`~openral_observability.queued_observer.QueuedObserver` does that for work on every tick, in
order; :class:`~openral_observability.latest_observer.LatestPerKeyObserver` for work on the newest
item per camera, where an older one is worth nothing once a newer exists). An observer that
raises is logged and detached; it never stops the robot. Observers also hear the episode
boundaries the runner is given, and are closed (flushed) on every exit path.

A deployment lists observers in its ``observers:`` block; each is a plugin in the
``openral.observers`` entry-point group built with ``Cls.from_config(params, context)``
(:class:`ObserverPlugin`; a simulated scene's entries too), which validates ``params`` with
its own typed model and opens nothing: no socket, no session, no port (``openral validate``
builds it). An observer that needs one opens it in ``start()`` (:class:`StartableObserver`), which
the runner calls once when it activates, before the first tick. Observers subclass
:class:`TickObserver` and override what they need.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from openral_core import ObserverContext, TickResult, WorldState


@runtime_checkable
class TickObserver(Protocol):
    """Receives every tick and the world state the skill saw (``None`` when none was built)."""

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Take note of one tick; must not block."""

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        """An episode began: the ticks that follow belong to it, under ``task``."""
        return

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        """The episode ended; ``keep=False`` means it is to be thrown away (a re-recorded take)."""
        return

    def close(self) -> None:
        """Flush and release; called once when the runner deactivates."""


class ObserverPlugin(Protocol):
    """What an ``openral.observers`` entry point names: a class (or factory) built from an entry's ``params``.

    ``from_config`` validates ``params`` with the observer's own model and reads what it needs of
    the loop from ``context`` (names, cameras, rate, where relative paths start). It opens nothing:
    ``openral validate`` builds observers and closes them again.
    """

    def from_config(self, params: Mapping[str, Any], context: ObserverContext) -> TickObserver:
        """The observer for one entry.

        Raises:
            ROSConfigError: A wrong parameter, naming ``context.option`` when the entry stands for one.
        """
        ...


@runtime_checkable
class StartableObserver(Protocol):
    """An observer that opens what it needs (a server's port, a Zenoh session) when the runner starts.

    ``start`` is called once at activation, before the first tick, and must be idempotent; a
    failure there rolls the start-up back. ``close`` still ends every observer, started or not.
    """

    def start(self) -> None:
        """Open what building the observer deliberately left closed."""


@dataclass(frozen=True)
class Thumbnail:
    """One small JPEG of a camera frame, encoded once for every viewer (dashboards, Foxglove, bags)."""

    sensor_id: str
    stamp_ns: int
    width: int
    height: int
    jpeg: bytes
    frame_id: str | None = None


@runtime_checkable
class ThumbnailSubscriber(Protocol):
    """An observer that also takes the camera thumbnails (called on the thumbnail worker thread)."""

    def on_thumbnail(self, thumb: Thumbnail) -> None:
        """Take one thumbnail; must not block for long."""


@runtime_checkable
class ThumbnailSource(Protocol):
    """An observer that makes camera thumbnails; the runner subscribes every :class:`ThumbnailSubscriber` to it."""

    def subscribe(self, sink: Callable[[Thumbnail], None]) -> None:
        """Also hand every thumbnail to ``sink``; subscribing twice has no effect."""
