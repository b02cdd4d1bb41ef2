"""rSkill manifests (``rskill.yaml``) and the licence gate every deployment passes before loading a skill.

A manifest names a skill plugin, its licence, the robots it was made for and default parameters.
Loading one checks the licence against the deployment's policy: by default only the open licences in
:data:`OPEN_LICENSES` pass; anything else, notably non-commercial and proprietary licences, passes only
when the deployment lists it in ``vla.accept_licenses``. Putting the gate in the loader means no code
path can load a skill's manifest without deciding on its licence.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from importlib import resources
from pathlib import Path
from typing import Any, Final, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

from openral_core.actions import ControlMode
from openral_core.config import load_model_yaml
from openral_core.errors import ROSConfigError, ROSLicenseError
from openral_core.perception import ModelInputSize
from openral_core.skills import RSkillInfo

OPEN_LICENSES: frozenset[str] = frozenset(
    {
        "Apache-2.0",
        "MIT",
        "MIT-0",
        "BSD-2-Clause",
        "BSD-3-Clause",
        "ISC",
        "Zlib",
        "BSL-1.0",
        "MPL-2.0",
        "Unlicense",
        "CC0-1.0",
        "CC-BY-4.0",
    }
)
"""SPDX ids accepted when a deployment does not set ``vla.accept_licenses``: permissive licences
that allow commercial use without obligations beyond attribution (and MPL-2.0's file-level copyleft)."""

NO_LICENSE: Final = "NOASSERTION"
"""SPDX's word for a package or model that declares no licence: never accepted unless a deployment lists it."""

# SPDX ids are matched case-insensitively (SPDX specification, annex on license expressions).
_SPDX_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9.+-]*$"
_ID_PATTERN = r"^[a-z][a-z0-9_]*$"


class DetectorContract(BaseModel):
    """What a ``kind: detector`` rSkill detects and how it runs."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    engine: Literal["rtdetr", "zeroshot_hf"] = Field(
        default="rtdetr", description="rtdetr: a model with the RT-DETR signature; zeroshot_hf: a hub zero-shot model."
    )
    runtime: Literal["onnx", "tensorrt", "pytorch"] = Field(default="onnx", description="What runs the model.")
    model: str | None = Field(default=None, description="The model file, relative to the manifest.")
    labels: list[str] = Field(min_length=1, description="Class names, in the model's class order.")
    input_size: ModelInputSize = Field(default=(640, 640), description="The model's (height, width).")
    score_threshold: float = Field(default=0.5, ge=0, le=1)
    resize: Literal["stretch", "letterbox"] = "stretch"
    mode: Literal["continuous", "on_demand"] = Field(
        default="continuous", description="continuous: every frame it is given; on_demand: when asked."
    )


class RewardContract(BaseModel):
    """How a ``kind: reward`` rSkill's scores read."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    num_bins: int = Field(default=100, ge=2, description="The model's progress resolution.")
    success_threshold: float = Field(default=0.5, ge=0, le=1, description="Success probability that counts.")
    deadline_s: float = Field(default=5.0, gt=0, description="Longest a scoring request may take.")


class RSkillManifest(BaseModel):
    """``rskill.yaml``: what a skill is and where it may run.

    Attributes:
        name: Human-readable name of this rSkill (a packaged skill, possibly with weights).
        version: Version of the rSkill.
        kind: ``policy`` (acts), ``detector`` (finds objects in camera frames) or ``reward``
            (scores task progress).
        skill: A policy's plugin id in the ``openral.skills`` entry-point group.
        license: SPDX licence id of the skill and its weights (``LicenseRef-...`` for others).
        control_mode: What its actions command.
        chunk_size: Steps per inference (1 for a skill that emits one command per tick).
        robots: Robot ids it is compatible with; empty means any robot.
        weights_uri: Where its weights live, when it has any.
        params: Default ``vla.params`` for the skill; the deployment's values override them.
        detector: A detector's contract.
        reward: A reward model's contract.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    version: str = "0.0.0"
    kind: Literal["policy", "detector", "reward"] = "policy"
    skill: str | None = Field(default=None, pattern=_ID_PATTERN)
    license: str = Field(pattern=_SPDX_PATTERN)
    description: str = ""
    control_mode: ControlMode = ControlMode.JOINT_POSITION
    chunk_size: int = Field(default=1, ge=1)
    robots: list[str] = Field(default_factory=list)
    weights_uri: str | None = None
    params: dict[str, Any] = Field(default_factory=dict)
    detector: DetectorContract | None = None
    reward: RewardContract | None = None

    _source: str | None = PrivateAttr(default=None)

    @model_validator(mode="after")
    def _kind_has_its_block(self) -> Self:
        needs = {"policy": "skill", "detector": "detector", "reward": "reward"}[self.kind]
        if getattr(self, needs) is None:
            raise ValueError(f"a {self.kind} manifest needs '{needs}'")
        stray = [name for name in ("skill", "detector", "reward") if name != needs and getattr(self, name) is not None]
        if stray:
            raise ValueError(f"a {self.kind} manifest has no {', '.join(stray)}")
        return self

    @property
    def path(self) -> Path | None:
        """The manifest's file, when it was loaded from one."""
        return None if self._source is None else Path(self._source)

    @classmethod
    def from_yaml(
        cls, path: str | Path, *, accept_licenses: Collection[str] | None = None, field: str | None = "vla.manifest"
    ) -> Self:
        """Load and validate ``path``, then check its licence (see :meth:`check_license`).

        Raises:
            ROSConfigError: Missing file, bad YAML, or a bad field (named, with allowed keys).
            ROSLicenseError: The licence is not accepted.
        """
        path = Path(path)
        manifest = load_model_yaml(cls, path, field=field)
        manifest._source = str(path)
        manifest.check_license(accept_licenses)
        return manifest

    @property
    def source(self) -> str:
        """Where the manifest came from (its path), or its name when built in code."""
        return self._source or f"rSkill '{self.name}'"

    def check_license(self, accept_licenses: Collection[str] | None = None) -> None:
        """Raise unless the licence is accepted (see :func:`check_license`).

        Raises:
            ROSLicenseError: Naming the licence, the manifest, and how to accept it.
        """
        check_license(self.license, self.source, accept_licenses)

    def check_compatible(self, robot_id: str) -> None:
        """Raise unless the manifest lists no robots or lists ``robot_id``.

        Raises:
            ROSConfigError: The skill was not made for this robot.
        """
        if self.robots and robot_id not in self.robots:
            raise ROSConfigError(
                f"{self.source} supports robots {', '.join(self.robots)}, not '{robot_id}'",
                field="robot",
                hint="pick a skill made for this robot, or add the robot to the manifest's robots after testing it",
            )

    def merged_params(self, overrides: Mapping[str, Any]) -> dict[str, Any]:
        """The skill's parameters: the manifest's defaults, replaced key by key by the deployment's ``vla.params``."""
        return {**self.params, **overrides}

    def to_info(self) -> RSkillInfo:
        """The manifest's identity as the :class:`RSkillInfo` the runner reports."""
        if self.skill is None:
            raise ROSConfigError(f"{self.source} is a {self.kind} manifest, not a policy", field="kind")
        return RSkillInfo(
            skill_id=self.skill,
            name=self.name,
            version=self.version,
            license=self.license,
            control_mode=self.control_mode,
            chunk_size=self.chunk_size,
            description=self.description,
        )


rSkill = RSkillManifest  # noqa: N816 (the spec's name)
"""The spec's name for :class:`RSkillManifest`."""


def builtin_manifest(name: str) -> Path:
    """Path of a manifest shipped with openral (``manifests/<name>.rskill.yaml``).

    Raises:
        ROSConfigError: No such built-in manifest (the error lists the ones that exist).
    """
    folder = resources.files("openral_rskill") / "manifests"
    known = sorted(p.name.removesuffix(".rskill.yaml") for p in folder.iterdir() if p.name.endswith(".rskill.yaml"))
    if name not in known:
        raise ROSConfigError(f"no built-in rSkill manifest '{name}'; built-in: {', '.join(known)}")
    return Path(str(folder / f"{name}.rskill.yaml"))


def check_license(
    license_id: str,
    source: str,
    accept_licenses: Collection[str] | None = None,
    *,
    field: str = "vla.accept_licenses",
) -> None:
    """Raise unless ``license_id`` (an SPDX id) is accepted: the one licence gate of every skill and model.

    Args:
        license_id: The licence; ``NOASSERTION`` (SPDX's word) for one that declares none.
        source: What carries it, as the error names it (a manifest's path, a package).
        accept_licenses: SPDX ids the deployment accepts; ``None`` means :data:`OPEN_LICENSES`.
            An explicit list replaces the default list rather than extending it, so a deployment
            can also narrow what it accepts.
        field: Where the deployment lists what it accepts.

    Raises:
        ROSLicenseError: Naming the licence, its source, and how to accept it.
    """
    accepted = OPEN_LICENSES if accept_licenses is None else accept_licenses
    if license_id.casefold() in {lic.casefold() for lic in accepted}:
        return
    why = "it is not on the built-in open-licence list" if accept_licenses is None else "it is not listed"
    if license_id.casefold() == NO_LICENSE.casefold():
        why = "it declares no licence, so whether it may be used at all is a decision for whoever operates the robot"
    elif _non_commercial(license_id):
        why += "; it forbids commercial use, so accepting it is a decision for whoever operates the robot"
    raise ROSLicenseError(
        f"licence '{license_id}' of {source} is not accepted: {why}",
        field=field,
        hint=(
            f"to accept it, add '{license_id}' to {field} in the deployment; "
            "that list replaces the default open list, so also list any other licence you accept"
        ),
    )


def _non_commercial(license_id: str) -> bool:
    parts = license_id.upper().split("-")
    return "NC" in parts or "NONCOMMERCIAL" in parts
