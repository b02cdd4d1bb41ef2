"""A test skill that replays recorded actions: episode seed ``k`` gets the rows recorded for seed ``k``, from its tick.

Served by ``openral serve`` in a child process, registered there through a ``.dist-info`` folder
on ``PYTHONPATH`` (``test_vla_eval_libero.register``): it is never part of the installed package.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Self

import numpy as np

from openral_core import Action, ControlMode, RobotManifest, RSkillInfo, WorldState
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

SKILL_ID = "test_replay"
CHUNK = 8


class ReplaySkill(RSkillBase):
    """``params.actions``: a JSON file ``{"<seed>": [[a0...], ...]}``. Past the last row it repeats the last."""

    INFO = RSkillInfo(
        skill_id=SKILL_ID,
        control_mode=ControlMode.EE_DELTA,
        chunk_size=CHUNK,
        observation=["joint_state"],
        description="Replays recorded actions per episode seed (tests only).",
    )

    def __init__(self, actions: dict[int, np.ndarray]) -> None:
        super().__init__()
        self.actions = actions

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        recorded = json.loads(Path(params["actions"]).read_text())
        return cls({int(seed): np.asarray(rows, dtype=np.float64) for seed, rows in recorded.items()})

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def serves_many_episodes(self) -> bool:
        return True

    def _step_impl(self, world_state: WorldState) -> Action:
        raise NotImplementedError("served as chunks")

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        seed = request.seed if request.seed is not None else self.episode_seed
        if seed is None or seed not in self.actions:
            raise ValueError(f"no actions recorded for episode seed {seed}")
        rows = self.actions[seed]
        ticks = np.minimum(np.arange(request.obs_tick, request.obs_tick + CHUNK), len(rows) - 1)
        return rows[ticks]
