"""Perception events on Zenoh: one JSON event per sample on its kind's key; building opens nothing."""

from __future__ import annotations

import threading

import pytest

from openral_core import PerceptionEvent, ROSConfigError

pytest.importorskip("zenoh", reason="needs the 'remote' extra")

from openral_perception.sinks.zenoh import ZenohEventSink, event_key
from openral_remote.config import ZenohConfig
from openral_remote.session import open_session
from openral_remote.testing import free_endpoint

EVENT = PerceptionEvent(
    kind="motion",
    sensor_id="front",
    stamp_ns=1,
    width=64,
    height=48,
    summary="motion",
    metadata={"kind": "motion", "changed_fraction": 0.5, "box": {"x0": 0, "y0": 0, "x1": 8, "y1": 8}},
)


def test_keys_are_per_robot_and_kind_and_refuse_wildcards():
    assert event_key("so101", "scene_change") == "openral/so101/perception/scene_change"
    with pytest.raises(ROSConfigError, match="key expression"):
        event_key("so101", "**")


def test_events_arrive_on_their_kinds_key_and_a_closed_sink_reopens():
    endpoint = free_endpoint()
    sink = ZenohEventSink(ZenohConfig(listen=[endpoint]), "so101")
    received: list[PerceptionEvent] = []
    arrived = threading.Condition()

    def on_sample(sample) -> None:
        with arrived:
            received.append(PerceptionEvent.model_validate_json(sample.payload.to_bytes()))
            arrived.notify_all()

    sink.open()  # listens from here on, not when built
    session = open_session(ZenohConfig(connect=[endpoint]))
    subscriber = session.declare_subscriber("openral/so101/perception/motion", on_sample)
    try:
        with arrived:
            for _ in range(100):  # the subscription reaches the sink's session after a moment
                sink.publish(EVENT)
                if arrived.wait_for(lambda: received, timeout=0.1):
                    break
        assert received[0] == EVENT
        sink.close()
        sink.publish(EVENT)  # a late event after close goes nowhere, and opens nothing
        assert sink._session is None
        sink.open()
        count = len(received)
        with arrived:
            for _ in range(100):
                sink.publish(EVENT)
                if arrived.wait_for(lambda: len(received) > count, timeout=0.1):
                    break
        assert len(received) > count
    finally:
        sink.close()
        subscriber.undeclare()
        session.close()
