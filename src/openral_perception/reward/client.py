"""The reward monitor's client: a reward model in a sidecar scores a clip of frames for a task, over Zenoh.

The sidecar (any process, any machine, with the model's weights) serves the queryable
``openral/<robot>/reward/<model>/score``: a message of the wire codec with ``frames`` (a
``(T, H, W, 3)`` uint8 BGR clip) and ``task`` in, ``progress`` and ``success`` (``(T,)``
float, each in ``[0, 1]``) out. Each request has a deadline; a late or missing answer is an
error of that request alone, and the next one starts clean.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np

from openral_core import ROSConfigError, ROSUnavailable
from openral_perception.reward.frames import Frame, trend
from openral_remote.codec import decode, encode
from openral_remote.config import ZenohConfig
from openral_remote.keys import segment
from openral_remote.session import open_session, request
from openral_rskill.manifest import RSkillManifest


def reward_key(robot: str, model_id: str) -> str:
    """The key a reward sidecar of ``model_id`` serves for ``robot``.

    Raises:
        ROSConfigError: A segment that cannot be part of a key expression, naming it.
    """
    return f"openral/{segment(robot, 'robot')}/reward/{segment(model_id, 'model_id')}/score"


def clip_array(frames: Sequence[Frame]) -> np.ndarray:
    """A clip as one ``(T, H, W, 3)`` uint8 array.

    Raises:
        ROSConfigError: No frames, or frames of different sizes.
    """
    if not frames:
        raise ROSConfigError("an empty clip cannot be scored", field="frames")
    sizes = {(frame.width, frame.height) for frame in frames}
    if len(sizes) != 1:
        raise ROSConfigError(f"a clip's frames must share one size, got {sorted(sizes)}", field="frames")
    width, height = sizes.pop()
    return np.frombuffer(b"".join(frame.bgr for frame in frames), dtype=np.uint8).reshape(len(frames), height, width, 3)


class RewardMonitor:
    """Scores clips with a reward sidecar and sums up where the task stands.

    Args:
        model_id: The reward model (the key's segment).
        robot: The robot (the key's segment).
        zenoh: The session's settings (the sidecar's endpoint in ``connect``).
        deadline_s: Longest a request waits for its answer.
        num_bins: The model's progress resolution (progress is quantised to it).
        success_threshold: A success probability at or above it counts as success.
        stalled_slope: Progress trends at or below this (per frame) count as stalled.
    """

    def __init__(
        self,
        *,
        model_id: str,
        robot: str,
        zenoh: ZenohConfig,
        deadline_s: float = 5.0,
        num_bins: int = 100,
        success_threshold: float = 0.5,
        stalled_slope: float = 0.001,
    ) -> None:
        self.key = reward_key(robot, model_id)
        self.model_id = model_id
        self.deadline_s = deadline_s
        self.num_bins = num_bins
        self.success_threshold = success_threshold
        self.stalled_slope = stalled_slope
        self._session: Any = open_session(zenoh)

    def score(self, frames: Sequence[Frame], task: str) -> tuple[list[float], list[float]]:
        """``(progress, success)`` for each frame of the clip.

        Raises:
            ROSConfigError: An empty clip or task, or frames of different sizes.
            RemoteTimeout: No answer before the deadline.
            PeerError: The sidecar answered with an error.
            NoReply: No sidecar serves the key.
            ROSUnavailable: A malformed reply.
        """
        if not task.strip():
            raise ROSConfigError("a clip is scored for a task; the task is empty", field="task")
        clip = clip_array(frames)
        session = self._session
        if session is None:
            raise ROSUnavailable("the reward monitor is closed")
        payload = encode({"frames": clip, "task": task, "num_bins": self.num_bins})
        fields = decode(request(session, self.key, payload, timeout_s=self.deadline_s))
        progress, success = fields.get("progress"), fields.get("success")
        if not (isinstance(progress, np.ndarray) and isinstance(success, np.ndarray)):
            raise ROSUnavailable(f"{self.key}: the reply has no progress and success arrays")
        if progress.shape != (len(frames),) or success.shape != (len(frames),):
            raise ROSUnavailable(f"{self.key}: {progress.shape} scores for a clip of {len(frames)} frames")
        return np.clip(progress, 0, 1).tolist(), np.clip(success, 0, 1).tolist()

    def assess(self, frames: Sequence[Frame], task: str) -> dict[str, Any]:
        """Where the task stands: progress and success now, their trends, stalled, succeeded."""
        progress, success = self.score(frames, task)
        progress_trend, success_trend = trend(progress), trend(success)
        return {
            "progress_now": progress[-1],
            "success_now": success[-1],
            "progress_trend": progress_trend,
            "success_trend": success_trend,
            "stalled": len(progress) >= 2
            and progress_trend <= self.stalled_slope
            and success[-1] < self.success_threshold,
            "succeeded": success[-1] >= self.success_threshold,
            "frames_seen": len(frames),
        }

    def close(self) -> None:
        """Close the session. Idempotent."""
        if self._session is not None:
            self._session.close()
            self._session = None


def sidecar_reply(progress: Sequence[float], success: Sequence[float]) -> bytes:
    """A reward sidecar's answer (what a sidecar written in Python sends back)."""
    return encode(
        {"progress": np.asarray(progress, dtype=np.float64), "success": np.asarray(success, dtype=np.float64)}
    )


def sidecar_request(message: bytes) -> tuple[np.ndarray, str]:
    """``(frames, task)`` of a request, for a sidecar written in Python."""
    fields = decode(message)
    frames, task = fields.get("frames"), fields.get("task")
    if not isinstance(frames, np.ndarray) or frames.ndim != 4 or not isinstance(task, str):
        raise ValueError(f"not a reward request: {json.dumps(sorted(fields))}")
    return frames, task


def build_reward_monitor(manifest: RSkillManifest, *, robot: str, zenoh: ZenohConfig) -> RewardMonitor:
    """The monitor of a ``kind: reward`` rSkill manifest (its name is the sidecar's model key).

    Raises:
        ROSConfigError: Not a reward manifest.
    """
    contract = manifest.reward
    if manifest.kind != "reward" or contract is None:
        raise ROSConfigError(
            f"{manifest.source} is a {manifest.kind} manifest, not a reward model", field="kind", hint="kind: reward"
        )
    return RewardMonitor(
        model_id=manifest.name,
        robot=robot,
        zenoh=zenoh,
        deadline_s=contract.deadline_s,
        num_bins=contract.num_bins,
        success_threshold=contract.success_threshold,
    )
