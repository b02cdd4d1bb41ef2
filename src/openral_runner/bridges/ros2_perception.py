"""The ROS 2 event sink at its specification path; it lives in :mod:`openral_perception.sinks.ros2` (needs rclpy)."""

from openral_perception.sinks.ros2 import EVENT_QOS, Ros2EventSink

__all__ = ["EVENT_QOS", "Ros2EventSink"]
