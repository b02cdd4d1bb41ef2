"""The world-state stage: the latest joint state and sensor frames, snapshotted once per tick."""

from openral_world_state.aggregator import JOINT_STATE_COMPONENT, WorldStateAggregator

__all__ = ["JOINT_STATE_COMPONENT", "WorldStateAggregator"]
