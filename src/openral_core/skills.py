"""Skill identity and lifecycle states."""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field

from openral_core.actions import ControlMode


class RSkillState(StrEnum):
    """Lifecycle state of a skill (ROS 2 managed-node shape)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"
    ERROR = "error"


class RSkillInfo(BaseModel):
    """What a skill is: identity, licence and the action it produces."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    skill_id: str = Field(min_length=1)
    name: str = ""
    version: str = "0.0.0"
    license: str = "Apache-2.0"
    control_mode: ControlMode = ControlMode.JOINT_POSITION
    chunk_size: int = Field(default=1, ge=1)
    description: str = ""
    observation_steps: int = Field(
        default=1,
        ge=1,
        le=64,
        description="Observations one inference reads, the current one included (a Diffusion policy's n_obs_steps); "
        "the chunk executor keeps the earlier ones by tick.",
    )
    past_actions: int = Field(
        default=0,
        ge=0,
        le=1024,
        description="Commands actually sent (after the safety check) before the observation's tick that one "
        "inference reads (a prefix-conditioned policy's executed actions); the chunk executor keeps them by tick.",
    )
    observation: list[str] = Field(
        default_factory=list,
        description="What the skill reads of the world state (joint_state, images.<sensor>, privileged.<name>, "
        "task); empty when it does not say. A remote client sends only these.",
    )
