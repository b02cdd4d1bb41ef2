"""A LeRobot checkpoint folder, read without LeRobot: what the policy is, reads and predicts.

``lerobot-train`` writes ``pretrained_model/`` with the policy's ``config.json``, its weights
(``model.safetensors``) and the saved pre- and post-processor pipelines with their
normalisation statistics. The configuration is plain JSON, so everything a deployment is checked
against (features, shapes, chunk sizes) is known before PyTorch is imported: ``openral validate``
refuses a mismatch in a fraction of a second.

Whether LeRobot knows the policy type is not known from the JSON: a type may be built in or
registered by an installed plugin package (``lerobot_policy_*``), and only importing LeRobot and
its plugins tells (:meth:`Checkpoint.check_type`, when the policy loads). How the policy acts is
read from what its configuration declares, so a plugin's type needs no list here: a
``chunk_size`` makes it a chunking policy of that many rows.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from openral_core import ROSConfigError
from openral_core.config_files import load_json_file, resolve_user_path
from openral_rskill.lerobot.prefix import PrefixSpec, conditioning_for

REQUIRED_FILES: Final = (
    "config.json",
    "model.safetensors",
    "policy_preprocessor.json",
    "policy_postprocessor.json",
)
"""What ``PreTrainedPolicy.save_pretrained`` and the processors' ``save_pretrained`` leave in the folder."""

WINDOW_TYPES: Final = frozenset({"diffusion"})
"""Policies whose ``predict_action_chunk`` returns the ``n_action_steps`` window of a longer horizon."""

PLUGIN_PREFIX: Final = "lerobot_policy_"
"""What LeRobot's plugin discovery imports: every installed distribution whose name starts so."""

_HUB_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")
_KEY_LINE = re.compile(r"(Missing|Unexpected) key\(s\) in state_dict: ([^\n]*)")
_QUOTED = re.compile(r'"([^"]+)"')
_NAMES_SHOWN = 4
_FIELD: Final = "params.path"

STATE: Final = "observation.state"
ENVIRONMENT_STATE: Final = "observation.environment_state"
IMAGE_PREFIX: Final = "observation.images."
ACTION: Final = "action"


@dataclass(frozen=True)
class Feature:
    """One input or output of the policy as its configuration declares it."""

    key: str
    kind: str
    """LeRobot's ``FeatureType``: ``STATE``, ``ENV``, ``VISUAL``, ``ACTION``, ``LANGUAGE``."""
    shape: tuple[int, ...]


@dataclass(frozen=True)
class Checkpoint:
    """A local ``pretrained_model/`` folder and what its ``config.json`` says.

    Attributes:
        path: The folder.
        policy_type: LeRobot's policy type (``act``, ``diffusion``, ...), or a plugin's.
        inputs: The input features by key.
        action: The action feature.
        chunk_size: Rows ``predict_action_chunk`` returns: the ``chunk_size`` the configuration
            declares (ACT, SmolVLA, pi0 and any plugin policy built like them), Diffusion's
            ``n_action_steps``, and 1 for a policy declaring no chunk (run step by step through
            its own ``select_action``).
        n_action_steps: Rows LeRobot executes of each chunk before asking again.
        observation_steps: Observations one inference reads (``n_obs_steps``).
        trained_device: The device the checkpoint was trained on.
        prefix: What a prefix-conditioned policy reads (:mod:`openral_rskill.lerobot.prefix`);
            ``None`` for a policy that reads no prefix.
    """

    path: Path
    policy_type: str
    inputs: dict[str, Feature]
    action: Feature
    chunk_size: int
    n_action_steps: int
    observation_steps: int
    trained_device: str
    prefix: PrefixSpec | None = None

    @classmethod
    def read(cls, value: str, base_dir: Path | None = None, *, field: str = _FIELD) -> Checkpoint:
        """The checkpoint in folder ``value``; refused in one line when it is not a complete local one.

        Raises:
            ROSConfigError: Not a folder (a hub id cannot be fetched here), a file missing, or a
                configuration this skill cannot run.
        """
        path = resolve_user_path(value, base_dir, field=field)
        if not os.path.isdir(path):  # os.path: False for any path that cannot be one (a name too long)
            if not os.path.lexists(path) and _HUB_ID.match(value):
                raise ROSConfigError(
                    f"{value!r} is not a local folder; it looks like a Hugging Face Hub id, and openral never "
                    "downloads models",
                    field=field,
                    hint=f"download it first (huggingface-cli download {value} --local-dir DIR) and give DIR",
                )
            raise ROSConfigError(
                f"{path} is not a folder",
                field=field,
                hint="give a checkpoint folder as lerobot-train writes it (…/checkpoints/<step>/pretrained_model)",
            )
        missing = [name for name in REQUIRED_FILES if not (path / name).is_file()]
        if missing:
            raise ROSConfigError(
                f"{path} is not a LeRobot checkpoint: it has no {', '.join(missing)}",
                field=field,
                hint="point at the pretrained_model folder lerobot-train writes (weights and processors saved)",
            )
        config = _json_object(path / "config.json", field)
        return cls._from_config(path, config, field)

    @classmethod
    def _from_config(cls, path: Path, config: dict[str, Any], field: str) -> Checkpoint:
        policy_type = config.get("type")
        if not isinstance(policy_type, str) or not policy_type:
            raise ROSConfigError(f"{path / 'config.json'} names no policy type", field=field)
        inputs = _features(config.get("input_features"), path, field)
        outputs = _features(config.get("output_features"), path, field)
        action = outputs.get(ACTION)
        if action is None or len(action.shape) != 1:
            raise ROSConfigError(f"{path / 'config.json'} declares no 1-d 'action' output", field=field)
        n_action_steps = _positive(config, "n_action_steps", path, field, default=1)
        if policy_type in WINDOW_TYPES:
            chunk_size = n_action_steps  # predict_action_chunk returns the executed window of the horizon
        else:
            chunk_size = _positive(config, "chunk_size", path, field, default=1)
        conditioning = conditioning_for(policy_type)
        return cls(
            path=path,
            policy_type=policy_type,
            inputs=inputs,
            action=action,
            chunk_size=chunk_size,
            n_action_steps=min(n_action_steps, chunk_size),
            observation_steps=_positive(config, "n_obs_steps", path, field, default=1),
            trained_device=str(config.get("device") or "cpu"),
            prefix=None if conditioning is None else conditioning.spec(config, path),
        )

    def check_type(self, known: Iterable[str]) -> None:
        """Refuse a policy type neither LeRobot nor an installed plugin registers, naming the ones known.

        ``known``: the types registered once LeRobot's plugins are imported.

        Raises:
            ROSConfigError: ``policy_type`` is not among ``known``.
        """
        names = sorted(known)
        if self.policy_type not in names:
            close = difflib.get_close_matches(self.policy_type, names, n=1)
            suggestion = f"did you mean {close[0]!r}? " if close else ""
            raise ROSConfigError(
                f"{self.path / 'config.json'} names policy type {self.policy_type!r}, which neither LeRobot nor an "
                f"installed plugin registers ({suggestion}known: {', '.join(names)})",
                field=_FIELD,
                hint=f"a plugin's policy type needs its package installed: pip install {PLUGIN_PREFIX}<name> "
                f"(LeRobot imports every installed {PLUGIN_PREFIX}* package)",
            )

    @property
    def cameras(self) -> list[str]:
        """The camera names the policy reads (``observation.images.<name>``)."""
        return [key.removeprefix(IMAGE_PREFIX) for key in self.inputs if key.startswith(IMAGE_PREFIX)]


def weights_mismatch(checkpoint: Checkpoint, error: BaseException) -> ROSConfigError | None:
    """The error to give for a load that found ``model.safetensors`` not covering the policy, or ``None``.

    ``error`` is what PyTorch (or safetensors) raises for a strict load: its message lists the
    missing and unexpected tensor names, one kind per line. A policy left partly at its random
    initialisation must never act, so either kind refuses the checkpoint.
    """
    found = {kind: _QUOTED.findall(names) for kind, names in _KEY_LINE.findall(str(error))}
    parts = [
        f"{kind.lower()} tensors {_shortened(names)}"
        for kind, names in (("Missing", found.get("Missing", [])), ("Unexpected", found.get("Unexpected", [])))
        if names
    ]
    if not parts:
        return None
    return ROSConfigError(
        f"{checkpoint.path / 'model.safetensors'} does not hold the weights of the {checkpoint.policy_type} policy "
        f"its config.json describes: {'; '.join(parts)}",
        field=_FIELD,
        hint="use the model.safetensors lerobot-train saved beside this config.json",
    )


def _shortened(names: Sequence[str]) -> str:
    shown = ", ".join(sorted(names)[:_NAMES_SHOWN])
    return shown if len(names) <= _NAMES_SHOWN else f"{shown} and {len(names) - _NAMES_SHOWN} more"


def _json_object(path: Path, field: str) -> dict[str, Any]:
    data = load_json_file(path, field=field)
    if not isinstance(data, dict):
        raise ROSConfigError(f"{path} does not hold a JSON object", field=field)
    return data


def _features(raw: Any, path: Path, field: str) -> dict[str, Feature]:
    if not isinstance(raw, dict):
        raise ROSConfigError(f"{path / 'config.json'}: features are not a mapping", field=field)
    features = {}
    for key, spec in raw.items():
        shape = spec.get("shape") if isinstance(spec, dict) else None
        kind = spec.get("type") if isinstance(spec, dict) else None
        if (
            not isinstance(kind, str)
            or not isinstance(shape, list)
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in shape)
        ):
            raise ROSConfigError(f"{path / 'config.json'}: feature {key!r} has no type and shape", field=field)
        features[str(key)] = Feature(str(key), kind, tuple(shape))
    return features


def _positive(config: dict[str, Any], key: str, path: Path, field: str, *, default: int) -> int:
    value = config.get(key, default)
    if value is None:
        return default
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise ROSConfigError(f"{path / 'config.json'}: {key} is {value!r}, not a positive integer", field=field)
    return value


__all__ = [
    "ACTION",
    "ENVIRONMENT_STATE",
    "IMAGE_PREFIX",
    "REQUIRED_FILES",
    "STATE",
    "Checkpoint",
    "Feature",
    "weights_mismatch",
]
