"""The reward monitor's frame ring at its specification path; it lives in :mod:`openral_perception.reward.frames`."""

from openral_perception.reward.frames import Frame, RollingFrameBuffer, trend

__all__ = ["Frame", "RollingFrameBuffer", "trend"]
