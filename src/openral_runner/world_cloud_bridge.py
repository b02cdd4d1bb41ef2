"""The world-cloud picture at its specification path; it lives in :mod:`openral_perception.world_cloud`."""

from openral_observability.semconv import SPAN_WORLD_CLOUD
from openral_perception.world_cloud import (
    WORLD_CLOUD_TOPIC_DEFAULT,
    WorldCloudBridge,
    crop_points_to_box,
    distance_to_rgb,
    encode_world_cloud_png,
    world_cloud_span_attributes,
)

__all__ = [
    "SPAN_WORLD_CLOUD",
    "WORLD_CLOUD_TOPIC_DEFAULT",
    "WorldCloudBridge",
    "crop_points_to_box",
    "distance_to_rgb",
    "encode_world_cloud_png",
    "world_cloud_span_attributes",
]
