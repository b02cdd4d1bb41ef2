"""Perception events on ROS 2: ``/openral/perception/<kind>``, one ``std_msgs/String`` of JSON per event.

QoS as for a stream of observations: best effort, volatile, the last 10. Needs rclpy (a sourced
ROS 2 installation); rclpy is not on PyPI.
"""

from __future__ import annotations

from typing import Any

from openral_core import ROSDependencyMissing
from openral_core.perception import PerceptionEvent
from openral_perception.publisher import TOPIC_PREFIX

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
    """Publishes each event on ``<topic_prefix>/<kind>`` from its own node (or ``node``, when given).

    The node (and, when no ROS context is up, the context) is made by :meth:`open`, on the first
    event at the latest; :meth:`close` destroys what this sink made, and :meth:`open` makes it again.
    """

    def __init__(
        self, *, node: Any = None, node_name: str = "openral_perception", topic_prefix: str = TOPIC_PREFIX
    ) -> None:
        if not topic_prefix.startswith("/"):
            raise ValueError(f"topic prefix {topic_prefix!r} must be absolute")
        self._given_node = node
        self.node_name = node_name
        self.node: Any = None
        self.topic_prefix = topic_prefix.rstrip("/")
        self._owns_context = False
        self._publishers: dict[str, Any] = {}

    def open(self) -> None:
        """Make the node (and the ROS context if none is up). Idempotent."""
        if self.node is not None:
            return
        if self._given_node is not None:
            self.node = self._given_node
            return
        if not rclpy.ok():
            rclpy.init()
            self._owns_context = True
        self.node = rclpy.create_node(self.node_name)

    def publish(self, event: PerceptionEvent) -> None:
        self.open()
        publisher = self._publishers.get(event.kind)
        if publisher is None:
            topic = f"{self.topic_prefix}/{event.kind}"
            publisher = self._publishers[event.kind] = self.node.create_publisher(String, topic, EVENT_QOS)
        message = String()
        message.data = event.model_dump_json()
        publisher.publish(message)

    def close(self) -> None:
        """Destroy the publishers (and the node and context this sink made). Idempotent."""
        if self.node is not None:
            for publisher in self._publishers.values():
                self.node.destroy_publisher(publisher)
            if self._given_node is None:
                self.node.destroy_node()
        self._publishers = {}
        self.node = None
        if self._owns_context and rclpy.ok():
            rclpy.shutdown()
        self._owns_context = False
