"""The reward monitor: recent frames in a ring, scored for task progress and success by a reward sidecar.

:mod:`~openral_perception.reward.frames` is pure Python; :mod:`~openral_perception.reward.client`
talks to the sidecar over Zenoh (the ``remote`` extra) and is imported only by who uses it.
"""

from openral_perception.reward.frames import Frame, RollingFrameBuffer, trend

__all__ = ["Frame", "RollingFrameBuffer", "trend"]
