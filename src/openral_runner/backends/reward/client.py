"""The reward monitor's client at its specification path; it lives in :mod:`openral_perception.reward.client`."""

from openral_perception.reward.client import (
    RewardMonitor,
    build_reward_monitor,
    clip_array,
    reward_key,
    sidecar_reply,
    sidecar_request,
)

__all__ = [
    "RewardMonitor",
    "build_reward_monitor",
    "clip_array",
    "reward_key",
    "sidecar_reply",
    "sidecar_request",
]
