"""Perception events on Zenoh: ``openral/<robot>/perception/<kind>``, one JSON ``PerceptionEvent`` per sample."""

from __future__ import annotations

from typing import Any

from openral_core.perception import PerceptionEvent
from openral_remote.config import ZenohConfig
from openral_remote.keys import segment
from openral_remote.session import open_session


def event_key(robot: str, kind: str) -> str:
    """The key events of ``kind`` are published on (both segments checked, each error naming its field)."""
    return f"openral/{segment(robot, 'robot')}/perception/{segment(kind, 'kind')}"


class ZenohEventSink:
    """Publishes each event on its kind's key; publishers are declared on first use.

    The session is opened by :meth:`open` (the publisher opens its sinks when it starts), so
    building the sink, as ``openral validate`` does, neither listens nor connects. After
    :meth:`close` a late event goes nowhere until :meth:`open` is called again.

    Args:
        zenoh: The session's settings.
        robot: The robot segment of the keys.
    """

    def __init__(self, zenoh: ZenohConfig, robot: str) -> None:
        self.robot = robot
        self.zenoh = zenoh
        self._session: Any = None
        self._publishers: dict[str, Any] = {}
        self._closed = False

    def open(self) -> None:
        """Open the session (listen, connect), also after :meth:`close`. Idempotent.

        Raises:
            ROSConfigError: An endpoint cannot be listened on.
        """
        self._closed = False
        if self._session is None:
            self._session = open_session(self.zenoh)

    def publish(self, event: PerceptionEvent) -> None:
        if self._closed:  # a late event after close goes nowhere
            return
        if self._session is None:
            self.open()
        publisher = self._publishers.get(event.kind)
        if publisher is None:
            publisher = self._publishers[event.kind] = self._session.declare_publisher(
                event_key(self.robot, event.kind)
            )
        publisher.put(event.model_dump_json().encode("utf-8"))

    def close(self) -> None:
        """Undeclare the publishers and close the session. Idempotent."""
        self._closed = True
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers = {}
        if self._session is not None:
            self._session.close()
            self._session = None
