"""Fakes for perception tests: a sink that keeps the events it is given."""

from __future__ import annotations

import threading

from openral_core.perception import PerceptionEvent


class RecordingEventSink:
    """A perception :class:`~openral_perception.publisher.EventSink` that keeps what it is given.

    ``arrived`` is set by the first event (wait on it instead of sleeping).
    """

    def __init__(self) -> None:
        self.events: list[PerceptionEvent] = []
        self.closed = False
        self.arrived = threading.Event()

    def publish(self, event: PerceptionEvent) -> None:
        self.events.append(event)
        self.arrived.set()

    def close(self) -> None:
        self.closed = True
