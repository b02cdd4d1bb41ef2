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
    """Accumulates the time spent inside wrapped component calls (skill, HAL, safety, world state)."""

    def __init__(self) -> None:
        self.total_s = 0.0

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` with its own run time added to ``total_s``."""
        perf = time.perf_counter

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = perf()
            try:
                return fn(*args, **kwargs)
            finally:
                self.total_s += perf() - start

        return timed
