"""A LeRobot checkpoint loaded through LeRobot's own API, and its inference: the one module importing torch.

Loading is LeRobot's, after its installed plugins are imported as its own scripts do (a
``lerobot_policy_*`` package registers its policy type): ``PreTrainedConfig.from_pretrained``, the policy class's
``from_pretrained`` and ``make_pre_post_processors`` with the saved pipelines and statistics, so
the policy runs exactly as ``lerobot-eval`` would run it. openral changes three things only, all
for running offline and on the device asked for: the hub is never contacted
(``HF_HUB_OFFLINE``), the ImageNet backbone download that ACT and Diffusion configurations
trigger is turned off (the checkpoint's own weights replace it anyway), and the processors' device
is the one the deployment names rather than the one the checkpoint was trained on. And the weights
load strictly: a ``model.safetensors`` that lacks some of the policy's tensors, or holds others, is
refused, never run with the rest at its random initialisation.
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # before huggingface_hub is imported: never reach for the hub

from collections.abc import Sequence
from typing import Any, Final

import numpy as np

from openral_core import ROSConfigError, ROSDependencyMissing
from openral_hal.lerobot.plugins import load_lerobot_plugins
from openral_rskill.lerobot.checkpoint import ACTION, STATE, Checkpoint, weights_mismatch
from openral_rskill.lerobot.licence import check_policy_license
from openral_rskill.lerobot.prefix import PolicyInputs, PolicyPrefix, conditioning_for

try:
    import torch
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
except ImportError as exc:
    raise ROSDependencyMissing(
        exc.name or "lerobot",
        extra="lerobot",
        needed_for="LeRobot checkpoints (the lerobot_policy skill)",
        install=None
        if sys.version_info >= (3, 12)
        else f"lerobot 0.6 needs Python 3.12 or newer, and this is {sys.version.split()[0]}: "
        "uv sync --python 3.12 --extra lerobot",
    ) from exc

_FIELD = "params.path"
DRAWS_NOTHING: Final = frozenset({"act"})
"""Policies that draw no random number at inference (ACT's latent is zero outside training): seeds change nothing."""


def resolve_device(asked: str) -> str:
    """The torch device for ``asked`` (``auto``: CUDA, else Apple's MPS, else the CPU).

    Raises:
        ROSConfigError: ``cuda`` or ``mps`` asked for where there is none: never a silent CPU fallback.
    """
    if asked == "auto":
        if torch.cuda.is_available():
            return "cuda"
        if torch.backends.mps.is_available():
            return "mps"
        return "cpu"
    if asked == "cuda" and not torch.cuda.is_available():
        raise ROSConfigError("device cuda asked for, but PyTorch sees no CUDA device", field="params.device")
    if asked == "mps" and not torch.backends.mps.is_available():
        raise ROSConfigError("device mps asked for, but PyTorch sees no MPS device", field="params.device")
    return asked


class LoadedPolicy:
    """A policy with its pre- and post-processors on one device.

    Args:
        checkpoint: The folder, read.
        device: ``cpu``, ``cuda``, ``mps`` or ``auto``.
        threads: PyTorch's CPU threads (``None``: its default).
        accept_licenses: Licences accepted for a policy class from a plugin package (``None``:
            the open ones, :data:`~openral_rskill.manifest.OPEN_LICENSES`).

    Raises:
        ROSConfigError: The device is missing, or LeRobot cannot load the folder.
        ROSLicenseError: The policy's plugin package has a licence not accepted (or declares none).
    """

    def __init__(
        self,
        checkpoint: Checkpoint,
        *,
        device: str,
        threads: int | None = None,
        accept_licenses: Sequence[str] | None = None,
    ) -> None:
        self.checkpoint = checkpoint
        self.device = resolve_device(device)
        if threads is not None:
            torch.set_num_threads(threads)
        path = checkpoint.path
        try:
            load_lerobot_plugins()  # a plugin's policy type is registered only once its package is imported
            checkpoint.check_type(PreTrainedConfig.get_known_choices())
            policy_class = get_policy_class(checkpoint.policy_type)
            check_policy_license(policy_class.__module__, checkpoint.policy_type, accept_licenses)
            config = PreTrainedConfig.from_pretrained(path)
            if getattr(config, "pretrained_backbone_weights", None):
                config.pretrained_backbone_weights = None  # ImageNet weights, overwritten by the checkpoint's
            config.device = self.device
            # strict: LeRobot's default leaves what model.safetensors lacks at its random initialisation
            self.policy: Any = policy_class.from_pretrained(path, config=config, strict=True)
            self.pre, self.post = make_pre_post_processors(
                self.policy.config,
                pretrained_path=str(path),
                preprocessor_overrides={"device_processor": {"device": self.device}},
                postprocessor_overrides={"device_processor": {"device": "cpu"}},
            )
        except ROSConfigError:
            raise
        except Exception as exc:  # LeRobot and draccus raise their own types for a checkpoint they cannot read
            raise weights_mismatch(checkpoint, exc) or ROSConfigError(
                f"LeRobot cannot load {path}: {type(exc).__name__}: {exc}", field=_FIELD
            ) from exc
        self.policy.eval()
        self._draws_nothing = checkpoint.policy_type in DRAWS_NOTHING
        self._noise_shape = _noise_shape(self.policy.config)
        self._conditioning = conditioning_for(checkpoint.policy_type)
        self._actions: Any = None if self._conditioning is None else _action_normaliser(self.pre, checkpoint)

    def action_mean(self) -> np.ndarray:
        """``(dims,)``: the action the checkpoint's statistics centre on (normalised zero), in the policy's units."""
        zero = torch.zeros((1, self.checkpoint.action.shape[0]), dtype=torch.float32, device=self.device)
        with torch.inference_mode():
            mean = self._actions._normalize_action(zero, inverse=True)
        return np.asarray(mean.detach().to("cpu", torch.float64).numpy()).reshape(-1)

    def state_bound(self) -> float | None:
        """The largest magnitude ``observation.state`` had in training (from the saved statistics), if known."""
        for step in getattr(self.pre, "steps", []):
            stats = getattr(step, "stats", None)
            if isinstance(stats, dict) and STATE in stats:
                entry = stats[STATE]
                if "min" in entry and "max" in entry:
                    low, high = _numbers(entry["min"]), _numbers(entry["max"])
                    return float(max(np.abs(low).max(), np.abs(high).max()))
                if "mean" in entry and "std" in entry:
                    mean, std = _numbers(entry["mean"]), _numbers(entry["std"])
                    return float((np.abs(mean) + 3 * std).max())
        return None

    def reset(self, seed: int | None) -> None:
        """A new episode: the policy's queues emptied, and the process's generator seeded when a seed is given.

        A chunk's sampling is seeded per request (:meth:`chunks`); this seeds a single-step policy's.
        """
        self.policy.reset()
        if seed is not None:
            torch.manual_seed(seed)

    def chunk(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        task: str,
        seed: int | None = None,
        prefix: PolicyPrefix | None = None,
    ) -> np.ndarray:
        """``(rows, action_dim)`` of the policy's next chunk, in its own units, for the observations (oldest first).

        One observation: LeRobot's preprocessor batches it. Several (a policy reading
        ``n_obs_steps``): each is preprocessed, then they are stacked on the time axis the policy
        expects, and its queues are emptied first so the stack is what it reads. ``seed``: the
        seed its sampling draws from (``None``: the process's generator as it stands). ``prefix``:
        a prefix-conditioned policy's committed rows and past commands, in its units; its chunk
        then starts at the tick after the last committed row.
        """
        return self.chunks([observations], [task], [seed], None if prefix is None else [prefix])[0]

    def chunks(
        self,
        requests: Sequence[Sequence[dict[str, np.ndarray]]],
        tasks: Sequence[str],
        seeds: Sequence[int | None] | None = None,
        prefixes: Sequence[PolicyPrefix | None] | None = None,
    ) -> list[np.ndarray]:
        """The chunks of several requests (each its observations, oldest first) in one forward pass.

        Each request is preprocessed alone, exactly as :meth:`chunk` does, then the requests are
        concatenated on the batch axis: batched rows equal unbatched ones up to the kernels' float
        rounding. A request's ``seeds`` entry makes its sampling its own: Diffusion's noise is
        drawn per request from its seed and handed in; a policy whose noise cannot be handed in
        runs each seeded request alone, the process's generator seeded for it. A prefix-conditioned
        policy's ``prefixes`` are normalised and added after preprocessing (LeRobot's preprocessor
        drops them); one handed as keyword arguments runs each request alone.
        """
        drawn = [None] * len(requests) if seeds is None or self._draws_nothing else list(seeds)
        given = [None] * len(requests) if prefixes is None else list(prefixes)
        alone_only = self._conditioning is not None and not self._conditioning.batched
        if len(requests) > 1 and (
            (self._noise_shape is None and any(seed is not None for seed in drawn)) or alone_only
        ):
            alone = zip(requests, tasks, drawn, given, strict=True)
            return [
                self.chunks([one], [task], [seed], None if prefix is None else [prefix])[0]
                for one, task, seed, prefix in alone
            ]
        with torch.inference_mode():
            batches, kwargs = [], {}
            for observations, task, prefix in zip(requests, tasks, given, strict=True):
                batch = self._batch(observations, task)
                inputs = self._prefix_inputs(prefix)
                batch.update(inputs.batch)
                kwargs = inputs.kwargs
                batches.append(batch)
            batch = batches[0] if len(batches) == 1 else _concatenate(batches)
            if self._noise_shape is not None and any(seed is not None for seed in drawn):
                actions = self.policy.predict_action_chunk(batch, noise=self._noise(drawn), **kwargs)
            else:
                if drawn[0] is not None:
                    torch.manual_seed(drawn[0])
                actions = self.policy.predict_action_chunk(batch, **kwargs)
            actions = self.post(actions)
            self._synchronize()
        rows = actions.detach().to("cpu", torch.float64).numpy()
        self._check_rows(rows.shape)
        return [np.asarray(rows[i]) for i in range(len(batches))]

    def _prefix_inputs(self, prefix: PolicyPrefix | None) -> PolicyInputs:
        """A prefix-conditioned policy's inputs for ``prefix``, normalised as its actions were in training.

        Raises:
            ROSConfigError: A prefix-conditioned policy asked without a prefix.
        """
        if self._conditioning is None:
            return PolicyInputs()
        if prefix is None:
            raise ROSConfigError(
                f"the {self.checkpoint.policy_type} policy at {self.checkpoint.path} is prefix-conditioned: "
                "each chunk needs the committed rows it continues",
                field=_FIELD,
            )
        committed = self._normalised(prefix.committed)
        past = self._normalised(prefix.past)
        return self._conditioning.inputs(self.policy, committed, past)

    def _normalised(self, rows: np.ndarray) -> Any:
        """``(1, n, dims)`` on the policy's device, normalised with the checkpoint's action statistics."""
        dims = self.checkpoint.action.shape[0]
        tensor = torch.as_tensor(np.asarray(rows, dtype=np.float32).reshape(1, -1, dims), device=self.device)
        return self._actions._normalize_action(tensor, inverse=False)

    def _check_rows(self, shape: tuple[int, ...]) -> None:
        """Refuse a chunk shorter than the configuration declares: the policy class must deliver what config.json says.

        A policy is run as a chunking one by what its ``config.json`` declares (``chunk_size``),
        read before its class is known; its ``predict_action_chunk`` is what proves it.
        """
        expected = self.checkpoint.chunk_size
        if expected > 1 and (len(shape) != 3 or shape[1] < expected):
            raise ROSConfigError(
                f"{self.checkpoint.path / 'config.json'} declares chunks of {expected} rows, but the "
                f"{self.checkpoint.policy_type} policy's predict_action_chunk returned an array of shape {shape}",
                field=_FIELD,
            )

    def _noise(self, seeds: Sequence[int | None]) -> Any:
        """``(requests, *noise_shape)``: each request's noise from its own seed, drawn on the CPU (so on any device)."""
        assert self._noise_shape is not None
        rows = [
            torch.randn(self._noise_shape, generator=None if seed is None else torch.Generator().manual_seed(seed))
            for seed in seeds
        ]
        parameter = next(self.policy.parameters())
        return torch.stack(rows).to(device=parameter.device, dtype=parameter.dtype)

    def _batch(self, observations: Sequence[dict[str, np.ndarray]], task: str) -> dict[str, Any]:
        """One request as the policy reads it: a batch of one, with a time axis when it reads several steps."""
        if len(observations) == 1:
            return dict(self.pre(self._raw(observations[0], task)))
        steps = [self.pre(self._raw(o, task)) for o in observations]
        batch = dict(steps[-1])
        for key in self.checkpoint.inputs:
            batch[key] = torch.stack([s[key] for s in steps], dim=1)
        self.policy.reset()
        return batch

    def select(self, observation: dict[str, np.ndarray], task: str) -> np.ndarray:
        """This tick's action of a single-step policy, in its own units (``select_action``)."""
        with torch.inference_mode():
            action = self.post(self.policy.select_action(self.pre(self._raw(observation, task))))
            self._synchronize()
        return np.asarray(action.detach().to("cpu", torch.float64).numpy()).reshape(-1)

    def _raw(self, observation: dict[str, np.ndarray], task: str) -> dict[str, Any]:
        raw: dict[str, Any] = {key: torch.from_numpy(value) for key, value in observation.items()}
        raw["task"] = task
        return raw

    def _synchronize(self) -> None:
        if self.device == "cuda":
            torch.cuda.synchronize()


def _concatenate(batches: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Batches of one joined on the batch axis: tensors concatenated, lists (the task texts) joined."""
    joined: dict[str, Any] = {}
    for key, first in batches[0].items():
        values = [batch[key] for batch in batches]
        if isinstance(first, torch.Tensor):
            joined[key] = torch.cat(values, dim=0)
        elif isinstance(first, list):
            joined[key] = [item for value in values for item in value]
        else:
            joined[key] = first
    return joined


def _action_normaliser(pre: Any, checkpoint: Checkpoint) -> Any:
    """The preprocessor's step that normalises actions as in training: a prefix is normalised by it.

    Raises:
        ROSConfigError: The saved preprocessor holds no action statistics.
    """
    for step in getattr(pre, "steps", []):
        stats = getattr(step, "_tensor_stats", None)
        if hasattr(step, "_normalize_action") and isinstance(stats, dict) and ACTION in stats:
            return step
    raise ROSConfigError(
        f"{checkpoint.path / 'policy_preprocessor.json'} normalises no action, but the {checkpoint.policy_type} "
        "policy reads its prefix normalised as its actions were in training",
        field=_FIELD,
        hint="use the pretrained_model folder lerobot-train saved, processors and statistics included",
    )


def _noise_shape(config: Any) -> tuple[int, ...] | None:
    """The shape of one request's noise where ``predict_action_chunk`` takes it (Diffusion's), else ``None``."""
    if getattr(config, "type", None) == "diffusion":
        return (int(config.horizon), int(config.action_feature.shape[0]))
    return None


def _numbers(value: Any) -> np.ndarray:
    array = value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)
    return np.asarray(array, dtype=np.float64).reshape(-1)


__all__ = ["LoadedPolicy", "resolve_device"]
