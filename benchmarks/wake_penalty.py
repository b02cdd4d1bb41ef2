"""Wake penalty: what the first Python code after a periodic sleep costs, against the same code warm.

A control loop at 30 or 100 Hz sleeps for most of each period. When it wakes, the code it runs
first finds the CPU caches cold and pays to refill them; the same code run again right after is
several times faster. Which code pays depends only on the order, so per-component timings of a
loop (a runner's "own overhead" against its components) shift with it.

For each rate, the same small workload runs twice right after each wake (first, then again), with
the plain ``time.sleep`` of a LeRobot-style loop and with the runner's sleep (``sleep_until``,
whose last millisecond is busy-waited). Medians in µs.

Run:  uv run python benchmarks/wake_penalty.py [--seconds 3]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from _common import machine_line
from openral_runner.clock import sleep_until


class _Joint:
    def __init__(self, name: str, position: float) -> None:
        self.name = name
        self.position = position


def _workload(joints: list[_Joint]) -> dict[str, float]:
    """Attribute reads, a dict and a list built, float arithmetic: the shape of a tick's bookkeeping."""
    targets = {j.name: j.position * 0.5 + 0.1 for j in joints}
    order = sorted(targets)
    return {name: targets[name] for name in order}


def _measure(period_s: float, seconds: float, wait: Callable[[float], None]) -> tuple[float, float]:
    joints = [_Joint(f"j{i}", i * 0.1) for i in range(6)]
    first, again = [], []
    t0 = time.perf_counter()
    for k in range(1, int(seconds / period_s)):
        wait(t0 + k * period_s)
        a = time.perf_counter()
        _workload(joints)
        b = time.perf_counter()
        _workload(joints)
        c = time.perf_counter()
        first.append(b - a)
        again.append(c - b)
    return float(np.median(first)) * 1e6, float(np.median(again)) * 1e6


def _plain_sleep(deadline_s: float) -> None:
    time.sleep(max(0.0, deadline_s - time.perf_counter()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=3.0, help="run time per rate and sleep")
    parser.add_argument("--rates", default="30,100,1000", help="comma-separated rates in Hz")
    args = parser.parse_args()
    print(machine_line())
    for rate in (float(r) for r in args.rates.split(",")):
        for label, wait in (("time.sleep", _plain_sleep), ("sleep_until", sleep_until)):
            first, again = _measure(1.0 / rate, args.seconds, wait)
            print(
                f"{rate:>6g} Hz  {label:<11}  first after wake {first:6.2f} µs  again {again:6.2f} µs  "
                f"ratio {first / max(again, 1e-9):5.1f}x"
            )
    print(machine_line())


if __name__ == "__main__":
    main()
