"""What a served policy is: enough for a robot to check it can run it, and to notice when it changed."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from openral_core import ControlMode, ROSConfigError
from openral_remote.codec import SCHEMA_VERSION
from openral_rskill.anchoring import AnchorSpec
from openral_rskill.base import RSkillBase


class PolicyMeta(BaseModel):
    """A policy server's answer on its ``meta`` key."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: int = SCHEMA_VERSION
    policy: str
    robot: str
    skill_id: str
    skill_version: str = "0.0.0"
    chunk_size: int = Field(ge=1)
    action_names: list[str]
    control_mode: ControlMode
    anchor: AnchorSpec
    dt_s: float = Field(gt=0, description="The policy's step: one chunk row per tick of this period.")
    observation: list[str] = Field(default_factory=list, description="World-state fields it reads (empty: all).")
    observation_steps: int = Field(
        default=1, ge=1, le=64, description="Observations one inference reads: a request carries the earlier ones."
    )
    model_hash: str = Field(description="SHA-256 of the skill, its parameters and the files they name.")
    warmup_ms: float = Field(default=0.0, ge=0, description="How long the warm-up inference took.")

    def to_bytes(self) -> bytes:
        return self.model_dump_json().encode("utf-8")

    @classmethod
    def from_bytes(cls, data: bytes) -> PolicyMeta:
        """Parse a server's meta.

        Raises:
            ValueError: Not policy meta; or meta with fields this openral does not know, which a
                newer server sends (they change what a request must carry: the robot's openral
                is upgraded with the server's, never guessed across).
        """
        try:
            fields = json.loads(data)
        except ValueError as exc:
            raise ValueError(f"not JSON: {exc}") from None
        unknown = sorted(set(fields) - set(cls.model_fields)) if isinstance(fields, dict) else []
        if unknown:
            raise ValueError(
                f"the server's meta has fields this openral does not know ({', '.join(unknown[:8])}): "
                "the server runs a newer openral; upgrade the robot's to the server's"
            )
        return cls.model_validate(fields)

    def differences(self, other: PolicyMeta) -> list[str]:
        """The fields in which ``other`` differs from this (empty: the same policy)."""
        mine, theirs = self.model_dump(exclude={"warmup_ms"}), other.model_dump(exclude={"warmup_ms"})
        return [name for name in mine if mine[name] != theirs[name]]


def describe(
    skill: RSkillBase, *, policy: str, robot: str, action_names: list[str], rate_hz: float, model_hash: str
) -> PolicyMeta:
    """The meta of ``skill`` served as ``policy`` for ``robot`` at ``rate_hz``.

    Raises:
        ROSConfigError: The skill's rows cannot be described (an anchor of its own kind).
    """
    info = skill.info
    try:
        anchor = AnchorSpec.of(skill.action_anchor())
    except TypeError as exc:
        raise ROSConfigError(f"{info.skill_id} cannot be served: {exc}", field="--skill") from None
    return PolicyMeta(
        policy=policy,
        robot=robot,
        skill_id=info.skill_id,
        skill_version=info.version,
        chunk_size=info.chunk_size,
        action_names=list(action_names),
        control_mode=info.control_mode,
        anchor=anchor,
        dt_s=1.0 / rate_hz,
        observation=list(info.observation),
        observation_steps=info.observation_steps,
        model_hash=model_hash,
    )


def model_hash(skill_id: str, params: Mapping[str, Any], base_dir: Path | None = None) -> str:
    """A digest of what decides a policy's output: the skill, its parameters and every file a parameter names.

    A parameter whose text is the path of an existing file (a model, its weights) contributes that
    file's bytes, and one naming a folder (a LeRobot checkpoint: configuration, weights,
    processors) the bytes of every file directly in it, so a retrained model under the same name
    has another hash.
    """
    digest = hashlib.sha256()
    digest.update(skill_id.encode("utf-8"))
    digest.update(json.dumps(params, sort_keys=True, default=str).encode("utf-8"))
    for value in _texts(params):
        path = Path(value).expanduser()
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        for file in _files_named(path) if len(value) < 4096 else []:
            digest.update(file.name.encode("utf-8"))
            with file.open("rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
    return digest.hexdigest()


def _files_named(path: Path) -> list[Path]:
    """The file ``path`` names, or the files directly in the folder it names (sorted); none otherwise."""
    try:
        if path.is_file():
            return [path]
        if path.is_dir():
            return sorted(child for child in path.iterdir() if child.is_file())
    except OSError:  # a name too long to be a path, a folder that cannot be read
        pass
    return []


def _texts(value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, Mapping):
        return [text for key in sorted(value) for text in _texts(value[key])]
    if isinstance(value, list | tuple):
        return [text for item in value for text in _texts(item)]
    return []
