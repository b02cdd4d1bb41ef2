"""How a chunking policy's actions are executed: the executor's settings, and a simulation's virtual latency."""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class SeamMode(StrEnum):
    """How a new chunk meets the rows left of the one it follows."""

    REPLACE = "replace"
    CROSSFADE = "crossfade"
    ENSEMBLE = "ensemble"


class StarvationFallback(StrEnum):
    """What happens once no chunk row has come for ``max_starved_ticks`` ticks in a row."""

    HOLD = "hold"
    SKILL = "skill"
    STOP = "stop"


class FallbackSkill(BaseModel):
    """A local skill that acts while the policy is starved (``fallback: skill``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str = Field(min_length=1)
    params: dict[str, Any] = Field(default_factory=dict)


class ExecutorConfig(BaseModel):
    """Settings of the chunk executor, used for skills whose chunk size is above 1: each option's one definition.

    Rows are indexed by the tick of the observation a chunk was computed from; a new inference
    starts when the rows left fall to the recent p95 latency (in ticks) plus ``margin_ticks``.
    ``ChunkedExecutor`` takes this model whole (``openral_rskill.executor``).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    seam: SeamMode = Field(default=SeamMode.REPLACE, description="How a new chunk meets the rows left of the old.")
    crossfade_rows: int = Field(default=3, ge=1, description="Rows over which a crossfade blends.")
    ensemble_decay: float = Field(default=0.01, ge=0, description="ACT's m: weight exp(-m * i) for the i-th oldest.")
    margin_ticks: int = Field(default=1, ge=0, description="Ask for the next chunk this many ticks early.")
    min_rows: int = Field(default=1, ge=1, description="A chunk with fewer usable rows on arrival is discarded.")
    deadline_ticks: int = Field(default=30, ge=1, description="A result later than this after its request is dropped.")
    max_starved_ticks: int = Field(default=10, ge=0, description="Starved ticks (holding) before the fallback acts.")
    fallback: StarvationFallback = Field(
        default=StarvationFallback.HOLD, description="After max_starved_ticks: hold the last target, skill or stop."
    )
    fallback_skill: FallbackSkill | None = Field(default=None, description="The skill for fallback: skill.")
    executed_rows: int | None = Field(
        default=None, ge=1, description="Use at most this many rows of each chunk (the rest is dropped)."
    )
    warmup_requests: int = Field(
        default=1, ge=0, description="First requests whose latency is not counted (compilation, caches)."
    )
    indexing: Literal["tick", "stale_start"] = Field(
        default="tick",
        description="tick: rows anchored and indexed by tick; stale_start: each chunk runs from its first row "
        "when it arrives, as naive executors do (for comparison only).",
    )


class VirtualLatency(BaseModel):
    """A simulation's inference latency in ticks: a chunk asked for at tick k is usable at tick k + d.

    ``d = ticks``, plus a uniform draw in ``[0, jitter_ticks]`` from a generator seeded with the
    episode's seed, so the same episode always sees the same delays.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    ticks: int = Field(default=0, ge=0, le=1000)
    jitter_ticks: int = Field(default=0, ge=0, le=1000)

    def sampler(self, seed: int) -> Callable[[int], int]:
        """Delay of each request of an episode, by its index in the episode."""
        if self.jitter_ticks == 0:
            return lambda _request: self.ticks
        draws = np.random.default_rng(seed)
        cache: list[int] = []

        def delay(request: int) -> int:
            while len(cache) <= request:
                cache.append(self.ticks + int(draws.integers(0, self.jitter_ticks + 1)))
            return cache[request]

        return delay
