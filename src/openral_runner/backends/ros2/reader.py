"""``Ros2ImageSensorReader``: frames from a ``sensor_msgs/Image`` topic through ``rclpy``.

For cameras whose vendor driver publishes on ROS 2 (RealSense, Orbbec, ros2_control camera
plugins). A dedicated node spins on a background thread; each message's buffer becomes a
frame without copying, stamped from its header.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

from openral_core import ROSDependencyMissing, ROSRuntimeError, SensorReaderConfig
from openral_runner.backends.ros2.convert import image_to_frame, ros_stamp_to_monotonic_ns, stamp_to_ns
from openral_runner.backends.ros2.params import Ros2ImageParams
from openral_runner.frame_slot import LatestFrameSlot, SlotReader
from openral_runner.sensor_reader import validate_backend_params

try:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, qos_profile_sensor_data
    from sensor_msgs.msg import Image
except ImportError as exc:  # pragma: no cover - exercised only without ROS 2
    raise ROSDependencyMissing(
        "rclpy",
        extra=None,
        needed_for="the ros2_image backend",
        install="source a ROS 2 distribution first (e.g. source /opt/ros/jazzy/setup.bash); rclpy is not on PyPI",
    ) from exc


class Ros2ImageSensorReader(SlotReader):
    """Subscribes to one image topic; serves the latest message as a frame.

    Args:
        sensor_id: Reader id.
        topic: The ``sensor_msgs/Image`` topic.
        default_max_age_ms: Staleness limit when ``read_latest`` is given none.
        qos: ``sensor_data`` (best effort, depth 1) or ``reliable`` (depth 1).
        node_name: Node name; ``openral_<sensor_id>`` by default.
    """

    def __init__(
        self,
        *,
        sensor_id: str,
        topic: str,
        default_max_age_ms: float = 100.0,
        qos: str = "sensor_data",
        node_name: str | None = None,
    ) -> None:
        self.sensor_id = sensor_id
        self.topic = topic
        self.qos = qos
        self.node_name = node_name or f"openral_{sensor_id}"
        self._slot = LatestFrameSlot(sensor_id, default_max_age_ms=default_max_age_ms)
        self._node: Any = None
        self._executor: Any = None
        self._thread: threading.Thread | None = None
        self._owns_context = False
        self._seq = 0

    @classmethod
    def from_config(
        cls, config: SensorReaderConfig, *, hal: Any, robot: Any, base_dir: Path | None = None
    ) -> Ros2ImageSensorReader:
        """Plugin constructor; ``backend_params`` are validated as :class:`Ros2ImageParams`."""
        params = validate_backend_params(Ros2ImageParams, config, backend="ros2_image")
        return cls(
            sensor_id=config.sensor_id,
            topic=params.topic,
            default_max_age_ms=config.max_age_ms,
            qos=params.qos,
            node_name=params.node_name,
        )

    def open(self) -> None:
        """Create the node and subscription and start spinning. Idempotent."""
        if self._slot.is_open:
            return
        if not rclpy.ok():
            rclpy.init()
            self._owns_context = True
        try:
            self._node = rclpy.create_node(self.node_name)
            profile = qos_profile_sensor_data if self.qos == "sensor_data" else QoSProfile(depth=1)
            self._node.create_subscription(Image, self.topic, self._on_image, profile)
            self._executor = SingleThreadedExecutor()
            self._executor.add_node(self._node)
        except Exception as exc:
            self._teardown()
            raise ROSRuntimeError(f"sensor '{self.sensor_id}': cannot subscribe to {self.topic}: {exc}") from exc
        self._slot.open()
        self._thread = threading.Thread(target=self._spin, name=f"ros2-{self.sensor_id}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop spinning and destroy the node. Idempotent."""
        self._slot.close()
        if self._executor is not None:
            self._executor.shutdown(timeout_sec=1.0)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._teardown()

    def _spin(self) -> None:
        executor = self._executor
        try:
            while self._slot.is_open and rclpy.ok():
                executor.spin_once(timeout_sec=0.1)
        except Exception as exc:
            self._slot.fail(ROSRuntimeError(f"sensor '{self.sensor_id}': ROS 2 executor stopped: {exc}"))

    def _on_image(self, msg: Any) -> None:
        ros_now_ns = self._node.get_clock().now().nanoseconds
        stamp_ns = ros_stamp_to_monotonic_ns(
            stamp_to_ns(msg.header.stamp), ros_now_ns=ros_now_ns, monotonic_now_ns=time.monotonic_ns()
        )
        self._seq += 1
        try:
            frame = image_to_frame(msg, sensor_id=self.sensor_id, stamp_ns=stamp_ns, seq=self._seq)
        except Exception as exc:
            self._slot.fail(ROSRuntimeError(str(exc)))
            return
        self._slot.publish(frame)

    def _teardown(self) -> None:
        if self._node is not None:
            self._node.destroy_node()
            self._node = None
        self._executor = None
        if self._owns_context and rclpy.ok():
            rclpy.shutdown()
        self._owns_context = False
