"""``backend_params`` of the ``ros2_image`` backend, validated without ROS 2."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class Ros2ImageParams(BaseModel):
    """``backend_params`` of the ``ros2_image`` backend."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    topic: str = Field(min_length=1, description="sensor_msgs/Image topic to subscribe to")
    qos: Literal["sensor_data", "reliable"] = "sensor_data"
    node_name: str | None = None
