"""Cadence benchmark: the runner's absolute schedule vs a LeRobot-style relative-sleep loop.

For each rate, both loops drive the same no-op skill and no-op HAL (the SO-101 manifest's
joints) through the same world-state aggregator and the same null safety client, so the
only difference is scheduling and the runner's own bookkeeping. Reported per loop:

* achieved rate and its error against the target,
* tick-start jitter p50/p99/max in µs (start minus the slot the loop intended),
* missed slots (the runner skips slots after an overrun; the LeRobot loop just drifts),
* overhead per tick in µs: loop time per tick minus the time spent inside the components,
* busy time per tick in µs (slot start to the action sent, components included) and the
  components' share of it.

Read the overhead with the busy time beside it. At 30 and 100 Hz the loop sleeps for most of
each period and wakes with cold caches: whichever code runs first after the wake pays tens of
µs to refill them (``benchmarks/wake_penalty.py`` shows it). In the runner its own code runs
first, so that cost lands in its overhead; in the LeRobot-style loop the HAL read runs first and
the cost lands in the components. Same components, same work: compare the busy times.

Run:  uv run python benchmarks/cadence.py [--seconds 5] [--rates 30,100,1000]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from _common import ComponentTimer, machine_line
from openral_core import Action, SafetyEnvelope
from openral_hal.manifests import load_robot_manifest
from openral_hal.null import NullHAL
from openral_rskill.noop import HoldSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.safety import NullSafetyClient, SafetyClient
from openral_world_state import WorldStateAggregator


@dataclass
class Figures:
    loop: str
    rate_hz: float
    n_ticks: int
    achieved_hz: float
    jitter_p50_us: float
    jitter_p99_us: float
    jitter_max_us: float
    missed_slots: int
    overhead_us: float
    overhead_p50_us: float
    busy_p50_us: float
    components_p50_us: float

    def line(self) -> str:
        error_pct = (self.achieved_hz - self.rate_hz) / self.rate_hz * 100
        return (
            f"{self.loop:<9} {self.rate_hz:>6g} Hz  n={self.n_ticks:<6} achieved {self.achieved_hz:10.4f} Hz "
            f"({error_pct:+.4f}%)  jitter µs p50 {self.jitter_p50_us:8.1f} p99 {self.jitter_p99_us:8.1f} "
            f"max {self.jitter_max_us:9.1f}  missed {self.missed_slots:>5}  "
            f"overhead µs/tick mean {self.overhead_us:6.2f} p50 {self.overhead_p50_us:6.2f}  "
            f"busy p50 {self.busy_p50_us:6.1f} (components {self.components_p50_us:6.1f})"
        )


class _TimedSafety(SafetyClient):
    def __init__(self, timer: ComponentTimer) -> None:
        self.envelope = SafetyEnvelope()
        self._inner = NullSafetyClient()
        self.check_action = timer.wrap(self._inner.check_action)


def _components(timer: ComponentTimer) -> tuple[NullHAL, HoldSkill, WorldStateAggregator, _TimedSafety]:
    robot = load_robot_manifest("so101_follower")
    hal = NullHAL(robot, {})
    hal.read_state = timer.wrap(hal.read_state, starts_tick=True)  # type: ignore[method-assign]
    hal.send_action = timer.wrap(hal.send_action)  # type: ignore[method-assign]
    skill = HoldSkill(robot)
    skill.configure()
    skill.activate()
    skill.step = timer.wrap(skill.step)  # type: ignore[method-assign]
    aggregator = WorldStateAggregator(joint_max_age_ms=1000.0)
    aggregator.snapshot = timer.wrap(aggregator.snapshot)  # type: ignore[method-assign]
    return hal, skill, aggregator, _TimedSafety(timer)


def run_openral(rate_hz: float, seconds: float) -> Figures:
    timer = ComponentTimer()
    hal, skill, aggregator, safety = _components(timer)
    runner = HardwareRunner(
        thumbnail_hz=0.0,
        hal=hal,
        skill=skill,
        aggregator=aggregator,
        safety_client=safety,
        rate_hz=rate_hz,  # type: ignore[arg-type]
    )
    runner.activate()
    try:
        n = int(seconds * rate_hz)
        result = runner.run(n)
    finally:
        runner.deactivate()
    tick_total_s = result.tick_ms_mean * 1e-3 * result.n_ticks
    recent = list(runner.recent_ticks)
    per_tick = np.array([t.tick_ms * 1e-3 for t in recent]) - np.array(timer.per_tick[-len(recent) :])
    return Figures(
        loop="openral",
        rate_hz=rate_hz,
        n_ticks=result.n_ticks,
        achieved_hz=result.effective_rate_hz,
        jitter_p50_us=result.start_jitter_us_p50,
        jitter_p99_us=result.start_jitter_us_p99,
        jitter_max_us=result.start_jitter_us_max,
        missed_slots=result.missed_slots,
        overhead_us=(tick_total_s - timer.total_s) / result.n_ticks * 1e6,
        overhead_p50_us=float(np.median(per_tick)) * 1e6,
        busy_p50_us=float(np.median([t.tick_ms for t in recent])) * 1e3,
        components_p50_us=float(np.median(timer.per_tick[-len(recent) :])) * 1e6,
    )


def run_lerobot_style(rate_hz: float, seconds: float) -> Figures:
    """The record-loop shape: do the work, then ``time.sleep(period - elapsed)`` from this tick's start."""
    timer = ComponentTimer()
    hal, skill, aggregator, safety = _components(timer)
    hal.connect()
    period = 1.0 / rate_hz
    n = int(seconds * rate_hz)
    starts = np.empty(n)
    intended = np.empty(n)
    busy_s = 0.0
    busy = np.empty(n)
    perf = time.perf_counter
    next_intended = perf()
    for i in range(n):
        start = perf()
        starts[i] = start
        intended[i] = next_intended
        aggregator.update_joint_state(hal.read_state())
        action: Action = skill.step(aggregator.snapshot())
        checked = safety.check_action(action)
        hal.send_action(checked or action)
        elapsed = perf() - start
        busy_s += elapsed
        busy[i] = elapsed
        next_intended = start + period
        if period - elapsed > 0:
            time.sleep(period - elapsed)
    hal.disconnect()
    jitter_us = (starts - intended)[1:] * 1e6
    achieved = (n - 1) / (starts[-1] - starts[0])
    return Figures(
        loop="lerobot",
        rate_hz=rate_hz,
        n_ticks=n,
        achieved_hz=achieved,
        jitter_p50_us=float(np.percentile(jitter_us, 50)),
        jitter_p99_us=float(np.percentile(jitter_us, 99)),
        jitter_max_us=float(jitter_us.max()),
        missed_slots=0,
        overhead_us=(busy_s - timer.total_s) / n * 1e6,
        overhead_p50_us=float(np.median(busy - np.array(timer.per_tick))) * 1e6,
        busy_p50_us=float(np.median(busy)) * 1e6,
        components_p50_us=float(np.median(timer.per_tick)) * 1e6,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0, help="run time per loop and rate")
    parser.add_argument("--rates", default="30,100,1000", help="comma-separated rates in Hz")
    args = parser.parse_args()
    print(machine_line())
    for rate in (float(r) for r in args.rates.split(",")):
        ours = run_openral(rate, args.seconds)
        theirs = run_lerobot_style(rate, args.seconds)
        print(ours.line())
        print(theirs.line())
        missed_pct = ours.missed_slots / max(1, ours.n_ticks + ours.missed_slots) * 100
        print(
            f"          ratio lerobot/openral: jitter p99 {theirs.jitter_p99_us / max(ours.jitter_p99_us, 1e-9):.1f}x, "
            f"rate error {abs(theirs.achieved_hz - rate) / max(abs(ours.achieved_hz - rate), 1e-9):.1f}x; "
            f"openral/lerobot: overhead p50 {ours.overhead_p50_us / max(theirs.overhead_p50_us, 1e-9):.2f}x, "
            f"busy p50 {ours.busy_p50_us / max(theirs.busy_p50_us, 1e-9):.2f}x; "
            f"openral missed slots {missed_pct:.3f}%"
        )
    print(machine_line())


if __name__ == "__main__":
    main()
