"""Perception events on ROS 2: ``/openral/perception/<kind>``, one ``std_msgs/String`` of JSON per event.

QoS as for a stream of observations: best effort, volatile, the last 10. Needs rclpy (a sourced
ROS 2 installation); rclpy is not on PyPI.
"""

from __future__ import annotations

from typing import Any

from openral_core import ROSDependencyMissing
from openral_core.perception import PerceptionEvent
from openral_runner.backends.gstreamer.perception_tee import TOPIC_PREFIX

try:
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
except ImportError as exc:  # pragma: no cover - exercised only without ROS 2
    raise ROSDependencyMissing(
        "rclpy",
        extra=None,
        needed_for="perception events on ROS 2",
        install="source a ROS 2 distribution first (e.g. source /opt/ros/jazzy/setup.bash); rclpy is not on PyPI",
    ) from exc

EVENT_QOS = QoSProfile(
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
)


class Ros2EventSink:
    """Publishes each event on ``<topic_prefix>/<kind>`` from its own node (or ``node``, when given)."""

    def __init__(
        self, *, node: Any = None, node_name: str = "openral_perception", topic_prefix: str = TOPIC_PREFIX
    ) -> None:
        if not topic_prefix.startswith("/"):
            raise ValueError(f"topic prefix {topic_prefix!r} must be absolute")
        self._owns_context = False
        if node is None and not rclpy.ok():
            rclpy.init()
            self._owns_context = True
        self._owns_node = node is None
        self.node = node if node is not None else rclpy.create_node(node_name)
        self.topic_prefix = topic_prefix.rstrip("/")
        self._publishers: dict[str, Any] = {}

    def publish(self, event: PerceptionEvent) -> None:
        publisher = self._publishers.get(event.kind)
        if publisher is None:
            topic = f"{self.topic_prefix}/{event.kind}"
            publisher = self._publishers[event.kind] = self.node.create_publisher(String, topic, EVENT_QOS)
        message = String()
        message.data = event.model_dump_json()
        publisher.publish(message)

    def close(self) -> None:
        """Destroy the publishers (and the node and context this sink made). Idempotent."""
        for publisher in self._publishers.values():
            self.node.destroy_publisher(publisher)
        self._publishers = {}
        if self._owns_node and self.node is not None:
            self.node.destroy_node()
            self.node = None
        if self._owns_context and rclpy.ok():
            rclpy.shutdown()
            self._owns_context = False
