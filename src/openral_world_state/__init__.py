"""The world-state stage: one snapshot per tick of the frames and verdicts the runner read, and the joint state."""

from openral_world_state.aggregator import JOINT_STATE_COMPONENT, WorldStateAggregator

__all__ = ["JOINT_STATE_COMPONENT", "WorldStateAggregator"]
