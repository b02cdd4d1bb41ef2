"""The world around the robot as a picture: a point cloud (an occupancy map's voxel centres, a depth camera's
points) cropped to a box around the base and drawn from a chase view, coloured by distance, for a dashboard.

The drawing is pure (numpy and Pillow) and runs anywhere. :class:`WorldCloudBridge` subscribes a
ROS 2 ``PointCloud2`` (octomap_server's ``/octomap_point_cloud_centers`` by default), moves it into
the base frame with TF2, and at most once a period records the picture and its figures as the
attributes of an ``openral.world_cloud`` span; it needs rclpy (a ROS 2 installation).
"""

from __future__ import annotations

import base64
import io
import math
import time
from typing import Any, Final

import numpy as np
from PIL import Image

from openral_observability import semconv, tracer

WORLD_CLOUD_TOPIC_DEFAULT: Final = "/octomap_point_cloud_centers"

_WARM = np.array([230.0, 60.0, 30.0])
_MID = np.array([240.0, 220.0, 60.0])
_COOL = np.array([40.0, 110.0, 230.0])


def crop_points_to_box(points: np.ndarray, *, xy_m: float, z_min: float, z_max: float) -> np.ndarray:
    """The ``(N, 3)`` points within ``|x|, |y| <= xy_m`` and ``z_min <= z <= z_max`` of the base, as float32.

    Non-finite points (a depth camera's holes) are dropped.
    """
    cloud = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    keep = np.isfinite(cloud).all(axis=1)
    keep &= (np.abs(cloud[:, 0]) <= xy_m) & (np.abs(cloud[:, 1]) <= xy_m)
    keep &= (cloud[:, 2] >= z_min) & (cloud[:, 2] <= z_max)
    return cloud[keep]


def distance_to_rgb(dist_m: float, *, range_max_m: float) -> tuple[int, int, int]:
    """Near is warm (red), half the range yellow, the range and beyond cool (blue)."""
    t = min(max(dist_m / range_max_m, 0.0), 1.0) if range_max_m > 0 else 1.0
    colour = _WARM + (_MID - _WARM) * (t / 0.5) if t < 0.5 else _MID + (_COOL - _MID) * ((t - 0.5) / 0.5)
    r, g, b = (round(c) for c in colour)
    return r, g, b


def _colours(distances: np.ndarray, range_max_m: float) -> np.ndarray:
    t = np.clip(distances / range_max_m, 0.0, 1.0)[:, None]
    lower = _WARM + (_MID - _WARM) * (t / 0.5)
    upper = _MID + (_COOL - _MID) * ((t - 0.5) / 0.5)
    return np.asarray(np.where(t < 0.5, lower, upper).round().astype(np.uint8))


def _chase_view(points: np.ndarray, image_w: int, image_h: int, xy_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates and depth of ``points`` seen from behind and above the base, looking forward and down."""
    eye = np.array([-1.4 * xy_m, 0.0, 1.1 * xy_m])
    target = np.array([0.5 * xy_m, 0.0, 0.0])
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    relative = points.astype(np.float64) - eye
    depth = relative @ forward
    focal = 0.5 * image_h / math.tan(math.radians(25.0))
    u = image_w / 2 + focal * (relative @ right) / np.maximum(depth, 1e-6)
    v = image_h / 2 - focal * (relative @ up) / np.maximum(depth, 1e-6)
    return np.stack([u, v], axis=1), depth


def encode_world_cloud_png(
    points_base: np.ndarray,
    *,
    range_max_m: float = 4.0,
    image_w: int = 480,
    image_h: int = 360,
    xy_m: float = 2.0,
    z_min: float = -0.2,
    z_max: float = 2.0,
) -> str:
    """The cropped cloud drawn from a chase view, as base64 PNG text.

    Points are drawn far to near (near ones on top) as 3×3 squares coloured by their distance
    from the base; the base itself is a white cross.
    """
    cloud = crop_points_to_box(points_base, xy_m=xy_m, z_min=z_min, z_max=z_max)
    canvas = np.full((image_h, image_w, 3), 18, dtype=np.uint8)
    if len(cloud):
        pixels, depth = _chase_view(cloud, image_w, image_h, xy_m)
        visible = (depth > 0) & np.isfinite(pixels).all(axis=1)
        order = np.argsort(-depth[visible])
        uv = pixels[visible][order].round().astype(np.int64)
        colours = _colours(np.linalg.norm(cloud[visible][order], axis=1), range_max_m)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                u, v = uv[:, 0] + du, uv[:, 1] + dv
                inside = (u >= 0) & (u < image_w) & (v >= 0) & (v < image_h)
                canvas[v[inside], u[inside]] = colours[inside]
    origin, _depth = _chase_view(np.zeros((1, 3)), image_w, image_h, xy_m)
    ou, ov = (round(c) for c in origin[0])
    canvas[max(0, ov - 4) : ov + 5, min(max(ou, 0), image_w - 1)] = 255
    canvas[min(max(ov, 0), image_h - 1), max(0, ou - 4) : ou + 5] = 255
    out = io.BytesIO()
    Image.fromarray(canvas).save(out, format="PNG", optimize=False)
    return base64.b64encode(out.getvalue()).decode("ascii")


def world_cloud_span_attributes(
    *,
    points_base: np.ndarray,
    frame_id: str,
    source_node: str,
    range_max_m: float,
    xy_m: float,
    z_min: float,
    z_max: float,
) -> dict[str, Any]:
    """The ``openral.world_cloud.*`` attributes of one picture: what it shows and how it was cut."""
    cloud = crop_points_to_box(points_base, xy_m=xy_m, z_min=z_min, z_max=z_max)
    distances = np.linalg.norm(cloud, axis=1) if len(cloud) else np.zeros(0)
    return {
        semconv.ATTR_WORLD_CLOUD_FRAME_ID: frame_id,
        semconv.ATTR_WORLD_CLOUD_SOURCE_NODE: source_node,
        semconv.ATTR_WORLD_CLOUD_POINTS_TOTAL: int(np.asarray(points_base).reshape(-1, 3).shape[0]),
        semconv.ATTR_WORLD_CLOUD_POINTS_IN_BOX: len(cloud),
        semconv.ATTR_WORLD_CLOUD_NEAREST_M: float(distances.min()) if len(distances) else -1.0,
        semconv.ATTR_WORLD_CLOUD_RANGE_MAX_M: range_max_m,
        semconv.ATTR_WORLD_CLOUD_BOX_XY_M: xy_m,
        semconv.ATTR_WORLD_CLOUD_BOX_Z_M: [z_min, z_max],
        semconv.ATTR_WORLD_CLOUD_PNG_BASE64: encode_world_cloud_png(
            cloud, range_max_m=range_max_m, xy_m=xy_m, z_min=z_min, z_max=z_max
        ),
    }


class WorldCloudBridge:
    """Subscribes a ``PointCloud2`` on ``node`` and records a picture of it at most every ``period_s``.

    Args:
        node: The host ``rclpy.node.Node``.
        topic: The cloud (latched: subscribed TRANSIENT_LOCAL).
        target_frame: The base frame the picture is centred on.
        period_s: At most one picture per period.

    Raises:
        ROSDependencyMissing: rclpy (with tf2_ros and sensor_msgs_py) cannot be imported.
    """

    def __init__(
        self,
        node: Any,
        *,
        topic: str = WORLD_CLOUD_TOPIC_DEFAULT,
        target_frame: str = "base_link",
        period_s: float = 1.0,
        range_max_m: float = 4.0,
        xy_m: float = 2.0,
        z_min: float = -0.2,
        z_max: float = 2.0,
    ) -> None:
        from openral_core import ROSDependencyMissing  # noqa: PLC0415

        try:
            import tf2_ros  # noqa: PLC0415 - ROS 2: a sourced installation, no extra
            from rclpy import qos  # noqa: PLC0415
            from sensor_msgs.msg import PointCloud2  # noqa: PLC0415
            from sensor_msgs_py import point_cloud2  # noqa: PLC0415
        except ImportError as exc:
            raise ROSDependencyMissing(
                "rclpy", extra=None, needed_for="the world-cloud bridge", install="source a ROS 2 installation"
            ) from exc
        self._cloud_msg = PointCloud2
        self._point_cloud2 = point_cloud2
        self.node = node
        self.target_frame = target_frame
        self.period_s = period_s
        self.settings = {"range_max_m": range_max_m, "xy_m": xy_m, "z_min": z_min, "z_max": z_max}
        self._last = -math.inf
        self._buffer = tf2_ros.Buffer()
        self._listener = tf2_ros.TransformListener(self._buffer, node)
        profile = qos.QoSProfile(depth=1, durability=qos.DurabilityPolicy.TRANSIENT_LOCAL)
        self._subscription = node.create_subscription(self._cloud_msg, topic, self._on_cloud, profile)

    def _on_cloud(self, message: Any) -> None:
        now = time.monotonic()
        if now - self._last < self.period_s:
            return
        self._last = now
        points = np.array(
            [(p[0], p[1], p[2]) for p in self._point_cloud2.read_points(message, ("x", "y", "z"), skip_nans=True)],
            dtype=np.float64,
        ).reshape(-1, 3)
        transform = self._buffer.lookup_transform(self.target_frame, message.header.frame_id, message.header.stamp)
        points_base = _apply(transform.transform, points)
        attributes = world_cloud_span_attributes(
            points_base=points_base, frame_id=self.target_frame, source_node=self.node.get_name(), **self.settings
        )
        tracer().start_span(semconv.SPAN_WORLD_CLOUD, attributes=attributes).end()

    def destroy(self) -> None:
        """Release the subscription. Idempotent."""
        if self._subscription is not None:
            self.node.destroy_subscription(self._subscription)
            self._subscription = None


def _apply(transform: Any, points: np.ndarray) -> np.ndarray:
    """Points moved by a ``geometry_msgs/Transform`` (quaternion rotation, then translation)."""
    q = transform.rotation
    x, y, z, w = q.x, q.y, q.z, q.w
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    t = transform.translation
    return np.asarray(points @ rotation.T + np.array([t.x, t.y, t.z]))
