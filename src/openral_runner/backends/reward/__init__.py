"""The reward monitor: recent frames in a ring, scored for task progress and success by a reward sidecar.

``frames`` is pure Python; ``client`` talks to the sidecar over Zenoh (the ``remote`` extra).
"""

from openral_runner.backends.reward.frames import Frame, RollingFrameBuffer, trend

__all__ = ["Frame", "RollingFrameBuffer", "trend"]
