"""``ChunkRequest``: what a chunking skill is asked with, so a chunk stays one array from the model to the executor.

The chunk executor asks on its worker thread, never on the tick. Besides the observation it
knows two things by tick that a policy may use:

* **History**: the observations of the ticks before, for a policy that reads several (a
  Diffusion policy's ``n_obs_steps``). The skill says how many in ``RSkillInfo.observation_steps``.
* **Prefix**: the targets the executor will send while this inference runs, for the ticks from
  the observation's until the chunk can arrive (its recent p95 latency, or a simulation's virtual
  delay). Prefix-conditioned policies (real-time chunking) keep their new chunk continuous with
  them; the rows of the new chunk for those ticks are skipped when it arrives.
* **Past**: the commands actually sent before the observation's tick, after the safety check (a
  clamp included), for a policy that reads executed actions. The skill says how many in
  ``RSkillInfo.past_actions`` (none by default: nothing is kept).

A sampling policy (Diffusion, flow matching) draws a request's noise from :meth:`ChunkRequest.draw_seed`:
the episode's seed mixed with the observation's tick. A chunk is then a function of its request,
so a robot's run depends on its own seed alone, whatever else the process (a policy server
shared by several robots) drew before it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

import numpy as np

from openral_core import WorldState

_WORD: Final = 1 << 64


@dataclass(frozen=True)
class ChunkRequest:
    """One inference a chunking skill is asked for.

    Attributes:
        world: The observation of tick ``obs_tick``: row 0 of the chunk is for that tick.
        obs_tick: The tick the observation belongs to.
        history: Earlier observations, oldest first, one per tick (at most
            ``observation_steps - 1``; fewer at the start of an episode).
        prefix: ``(ticks, dims)`` absolute targets the executor will send at ticks
            ``obs_tick, obs_tick + 1, ...`` while this inference runs; empty when it has none.
            Fewer rows than ``inference_delay`` when the buffer runs out first: the executor
            then holds the last one.
        inference_delay: Ticks expected to pass before the chunk can be used (the executor's
            recent p95 inference latency, or a simulation's exact virtual delay); rows ``0 ..
            inference_delay - 1`` of the new chunk are for ticks already gone by then.
        past: ``(n, dims)`` the last commands sent before ``obs_tick``, oldest first (at most
            ``past_actions``; fewer at the start of an episode, none after a reset).
        past_ticks: The tick each row of ``past`` was sent on (a withheld tick leaves a gap).
        seed: The episode's seed when the caller knows it (a policy server: the asking robot's);
            ``None``: the skill's own (:attr:`~openral_rskill.base.RSkillBase.episode_seed`).
    """

    world: WorldState
    obs_tick: int = 0
    history: tuple[WorldState, ...] = ()
    prefix: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    inference_delay: int = 0
    past: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    past_ticks: tuple[int, ...] = ()
    seed: int | None = None

    def draw_seed(self, episode_seed: int | None) -> int | None:
        """The seed of this request's random draws (``None``: unseeded), from its episode's seed and tick.

        Args:
            episode_seed: The skill's episode seed, used when the request carries none.
        """
        seed = self.seed if self.seed is not None else episode_seed
        if seed is None:
            return None
        entropy = [seed % _WORD, self.obs_tick % _WORD]
        return int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0] >> 1)  # 63 bits: any generator's

    def observations(self, steps: int) -> tuple[WorldState, ...]:
        """The last ``steps`` observations, oldest first and the current one last.

        At an episode's start the oldest known one is repeated, as LeRobot's observation queues do after a reset.
        """
        known = (*self.history, self.world)[-steps:]
        return (known[0],) * (steps - len(known)) + known


__all__ = ["ChunkRequest"]
