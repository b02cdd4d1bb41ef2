"""Prefix-conditioned LeRobot policies: what each reads of the executor's prefix and past, behind one seam.

A prefix-conditioned policy continues the targets the executor will send while it infers (the
*prefix*: committed rows, known by tick), so its new chunk joins the old one without a jump. It
may be trained so (``act_smooth``: training-time real-time chunking) or guided so at inference (a
flow-matching policy with LeRobot's RTC). What differs between them is registered here by LeRobot
policy type (:data:`PREFIX_CONDITIONING`): how many executed commands it reads and which
committed delays it was trained on (read from its ``config.json``, so known without torch), and
how the prefix is handed to it (batch entries, or keyword arguments of ``predict_action_chunk``).

What is common is done once, for any of them (:func:`committed_rows` here; the units, the
normalisation and the rows put back in front by the skill and the runtime): the prefix held to
the delay as the executor holds it, the delay clipped to the trained range, a one-row prefix when
there is none (an episode's start), and the prefix normalised with the checkpoint's action
statistics after LeRobot's preprocessor, which drops it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Protocol

import numpy as np

from openral_core import ROSConfigError


@dataclass(frozen=True)
class PrefixSpec:
    """What a prefix-conditioned checkpoint reads, from its configuration.

    Attributes:
        past: Executed commands it reads before the observation's tick (0: none).
        min_delay: Committed rows it needs at least (``act_smooth``: 1, the observation's own tick).
        max_delay: Committed rows it was trained on at most; ``None``: any number.
    """

    past: int
    min_delay: int = 1
    max_delay: int | None = None

    def delay(self, asked: int) -> int:
        """The committed rows fed for an inference delay of ``asked`` ticks: within ``min_delay .. max_delay``."""
        fed = max(asked, self.min_delay)
        return fed if self.max_delay is None else min(fed, self.max_delay)


@dataclass(frozen=True)
class PolicyInputs:
    """The prefix as the policy takes it: entries of its batch, and keyword arguments of ``predict_action_chunk``."""

    batch: dict[str, Any] = field(default_factory=dict)
    kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PolicyPrefix:
    """One request's prefix in the policy's units (not normalised): what the runtime hands the policy.

    Attributes:
        committed: ``(d, dims)`` the rows for ticks ``obs_tick .. obs_tick + d - 1``.
        past: ``(n, dims)`` the commands sent before ``obs_tick``, oldest first.
    """

    committed: np.ndarray
    past: np.ndarray


class PrefixConditioning(Protocol):
    """How one policy type reads a prefix."""

    @property
    def batched(self) -> bool:
        """Whether its inputs are batch entries only, so requests with different prefixes share a forward pass."""
        ...

    def spec(self, config: Mapping[str, Any], path: Path) -> PrefixSpec:
        """What the checkpoint with ``config.json`` content ``config`` (in folder ``path``) reads.

        Raises:
            ROSConfigError: The configuration does not say it in a usable form.
        """
        ...

    def inputs(self, policy: Any, committed: Any, past: Any) -> PolicyInputs:
        """The policy's inputs for ``committed`` ``(1, d, dims)`` and ``past`` ``(1, n, dims)`` rows.

        Both are tensors on the policy's device, in the policy's units and normalised as its actions are.
        """
        ...


class CommittedActionPrefix:
    """``act_smooth``: the prefix in the batch (``inference_action`` and its padding mask), built by the policy itself.

    Its configuration names the executed commands it reads (``length_prefix_past``) and the most
    committed rows it was trained on (``length_prefix_future``); it needs at least one.
    """

    @property
    def batched(self) -> bool:
        return True

    def spec(self, config: Mapping[str, Any], path: Path) -> PrefixSpec:
        past = config.get("length_prefix_past", 0)
        future = config.get("length_prefix_future", 1)
        for key, value, least in (("length_prefix_past", past, 0), ("length_prefix_future", future, 1)):
            if not isinstance(value, int) or isinstance(value, bool) or value < least:
                raise ROSConfigError(
                    f"{path / 'config.json'}: {key} is {value!r}, not an integer of at least {least}",
                    field="params.path",
                )
        return PrefixSpec(past=past, min_delay=1, max_delay=future)

    def inputs(self, policy: Any, committed: Any, past: Any) -> PolicyInputs:
        action, is_pad = policy.build_inference_action_prefix(committed, past)
        return PolicyInputs(batch={"inference_action": action, "inference_action_is_pad": is_pad})


PREFIX_CONDITIONING: Final[dict[str, PrefixConditioning]] = {"act_smooth": CommittedActionPrefix()}
"""Prefix-conditioned policy types by LeRobot policy type; another registers its own here."""


def conditioning_for(policy_type: str) -> PrefixConditioning | None:
    """How ``policy_type`` reads a prefix, or ``None`` for a policy that reads none."""
    return PREFIX_CONDITIONING.get(policy_type)


def committed_rows(prefix: np.ndarray, delay: int, spec: PrefixSpec, start: np.ndarray) -> np.ndarray:
    """The committed rows a policy is fed, for ticks ``obs_tick, obs_tick + 1, ...``: ``spec.delay(delay)`` of them.

    Args:
        prefix: The executor's prefix (its rows for those ticks); fewer than ``delay`` rows when
            its buffer runs out first, and it then holds the last: so are they held here.
        delay: The request's inference delay in ticks.
        spec: The policy's trained range (beyond it, the first rows only: the executor skips the rest).
        start: ``(dims,)``: the row that stands for the prefix when there is none.
    """
    fed = spec.delay(delay)
    rows = np.asarray(prefix, dtype=np.float64)
    if len(rows) == 0:
        rows = np.asarray(start, dtype=np.float64).reshape(1, -1)
    if len(rows) < fed:
        rows = np.concatenate([rows, np.repeat(rows[-1:], fed - len(rows), axis=0)])
    return rows[:fed]


__all__ = [
    "PREFIX_CONDITIONING",
    "CommittedActionPrefix",
    "PolicyInputs",
    "PolicyPrefix",
    "PrefixConditioning",
    "PrefixSpec",
    "committed_rows",
    "conditioning_for",
]
