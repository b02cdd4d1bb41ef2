"""Perception events on ROS 2: written against rclpy, which cannot be installed here (the test then skips)."""

from __future__ import annotations

import importlib
import importlib.util
import threading

import pytest

from openral_core import PerceptionEvent, ROSDependencyMissing


@pytest.mark.skipif(importlib.util.find_spec("rclpy") is not None, reason="rclpy is installed")
def test_without_ros_2_the_sink_says_how_to_get_it():
    with pytest.raises(ROSDependencyMissing, match="ROS 2"):
        importlib.import_module("openral_perception.sinks.ros2")


def test_events_arrive_on_their_kinds_topic():
    pytest.importorskip("rclpy", reason="rclpy needs a ROS 2 installation, which cannot be installed here")
    import rclpy  # noqa: PLC0415
    from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
    from std_msgs.msg import String  # noqa: PLC0415

    from openral_perception.sinks.ros2 import EVENT_QOS, Ros2EventSink  # noqa: PLC0415

    rclpy.init()
    listener = rclpy.create_node("perception_listener")
    received: list[PerceptionEvent] = []
    arrived = threading.Event()

    def on_message(message: String) -> None:
        received.append(PerceptionEvent.model_validate_json(message.data))
        arrived.set()

    listener.create_subscription(String, "/openral/perception/motion", on_message, EVENT_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(listener)
    sink = Ros2EventSink()
    event = PerceptionEvent(
        kind="motion",
        sensor_id="front",
        stamp_ns=1,
        width=64,
        height=48,
        summary="motion",
        metadata={"kind": "motion", "changed_fraction": 0.5, "box": {"x0": 0, "y0": 0, "x1": 8, "y1": 8}},
    )
    try:
        for _ in range(50):  # discovery takes a moment; best effort drops until it is done
            sink.publish(event)
            executor.spin_once(timeout_sec=0.1)
            if arrived.is_set():
                break
        assert received
        assert received[0] == event
    finally:
        sink.close()
        listener.destroy_node()
        rclpy.shutdown()
