"""Shared bits for benchmarks: machine load line and a component timer."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from typing import Any


def machine_line() -> str:
    """One line describing the machine and its load right now (benchmarks here are noisy)."""
    load1, load5, _ = os.getloadavg()
    return (
        f"machine: {platform.machine()} {os.cpu_count()} cpu, python {platform.python_version()}, "
        f"load avg {load1:.2f} (1 min) {load5:.2f} (5 min)"
    )


class ComponentTimer:
    """Accumulates the time spent inside wrapped component calls (skill, HAL, safety, world state).

    ``per_tick`` holds one total per tick; a wrapper made with ``starts_tick=True`` (the first
    component each tick calls) opens a new entry.
    """

    def __init__(self) -> None:
        self.total_s = 0.0
        self.per_tick: list[float] = []

    def wrap(self, fn: Callable[..., Any], *, starts_tick: bool = False) -> Callable[..., Any]:
        """``fn`` with its own run time added to ``total_s`` and to the current tick's entry."""
        perf = time.perf_counter
        per_tick = self.per_tick

        def timed(*args: Any, **kwargs: Any) -> Any:
            if starts_tick:
                per_tick.append(0.0)
            start = perf()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = perf() - start
                self.total_s += elapsed
                if per_tick:
                    per_tick[-1] += elapsed

        return timed


def run_deployment(env: Any, base_dir: Any, seconds: float, *, settle_s: float = 1.0) -> tuple[Any, Any]:
    """Build ``env``, start it, let cameras settle, run it for ``seconds`` and close it: ``(RunResult, runner)``."""
    from openral_runner.factory import build_runner  # noqa: PLC0415

    runner, skill = build_runner(env, base_dir=base_dir)
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        time.sleep(settle_s)  # let the cameras start delivering
        result = runner.run(duration_s=seconds)
    finally:
        runner.deactivate()
        skill.shutdown()
    return result, runner
