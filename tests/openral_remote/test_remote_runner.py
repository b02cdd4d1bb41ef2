"""A paced simulation driven by a policy served from a child process: the robot side of a server's death."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from openral_core import SimEnvironment, TickResult, WorldState
from openral_observability.observer import TickObserver
from openral_remote.testing import POLICY, ROBOT
from openral_sim.build import build_sim_runner

pytestmark = pytest.mark.timeout(120)

RATE_HZ = 10.0


class Ticks(TickObserver):
    """Keeps the ticks; sets ``reached`` once ``at`` ticks have sent the served policy's (non-zero) action.

    Counting the ticks the policy drove, not the ticks run, keeps the point the same on a slow
    machine, where the server's first chunks may arrive many ticks after the start.
    """

    def __init__(self, at: int) -> None:
        self.ticks: list[TickResult] = []
        self.at = at
        self.driven = 0
        self.reached = threading.Event()

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        self.ticks.append(tick)
        if tick.sent_action is not None and any(tick.sent_action):
            self.driven += 1
            if self.driven >= self.at:
                self.reached.set()

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        return

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        return

    def close(self) -> None:
        return


def _runner(endpoint: str, executor: dict[str, Any], deadline_ms: float = 500.0) -> Any:
    scene = SimEnvironment(
        name="remote",
        env="mock",
        task="reach the target",
        success_key="is_success",
        max_steps=200,
        n_episodes=1,
        rate_hz=RATE_HZ,
        virtual_latency=None,  # real latency: the executor's worker asks the server, as on a robot
        executor=executor,
    )
    params = {"policy": POLICY, "robot": ROBOT, "zenoh": {"connect": [endpoint]}, "deadline_ms": deadline_ms}
    return build_sim_runner(scene, "remote_policy", params)


def _run(runner: Any, max_ticks: int, observer: TickObserver) -> Any:
    runner.observers.append(observer)
    runner.skill.configure()
    runner.skill.activate()
    runner.activate()
    try:
        return runner.run(max_ticks=max_ticks)
    finally:
        runner.deactivate()
        runner.skill.shutdown()


def test_a_killed_server_hands_over_to_the_fallback_within_two_ticks_and_no_tick_waits(server, endpoint):
    process = server("--rate-hz", str(RATE_HZ), "--offset", "0.5")
    runner = _runner(endpoint, {"fallback": "skill", "fallback_skill": {"id": "zero"}, "margin_ticks": 2})
    ticks = Ticks(at=5)
    killed_at: list[int] = []

    def kill_when_reached() -> None:
        ticks.reached.wait(60)
        killed_at.append(len(ticks.ticks))
        process.kill()

    class StopAfterKill(TickObserver):
        """Ends the run 25 ticks after the kill, however many ticks the policy took to start driving."""

        def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
            if killed_at and len(ticks.ticks) >= killed_at[0] + 25:
                runner.request_stop()

    killer = threading.Thread(target=kill_when_reached)
    killer.start()
    runner.observers.append(StopAfterKill())
    result = _run(runner, 190, ticks)
    killer.join()
    kill_tick = killed_at[0]
    sent = [tick.sent_action for tick in ticks.ticks]
    remote_ticks = [i for i, action in enumerate(sent[:kill_tick]) if action is not None and any(action)]
    assert len(remote_ticks) >= 5  # the served policy drove the robot before
    after = sent[kill_tick:]
    first_fallback = next(i for i, action in enumerate(after) if action == [0.0, 0.0])
    assert first_fallback <= 2  # the bound: liveliness (ms on a LAN) plus the tick already running
    assert all(action == [0.0, 0.0] for action in after[first_fallback:])  # never a stale remote row again
    # No tick waited on the network: one that did would wait out the request's 500 ms deadline. A
    # busy machine can stretch a tick past its 100 ms slot, so the bound sits between the two.
    assert max(tick.tick_ms for tick in ticks.ticks) < 250.0
    stats = result.metadata["executor"]
    assert stats["unavailable_ticks"] >= len(after) - first_fallback


def test_a_hung_server_is_counted_late_and_the_starved_robot_falls_back(server, endpoint):
    server("--rate-hz", str(RATE_HZ), "--delay-ms", "5000")
    runner = _runner(
        endpoint, {"fallback": "skill", "fallback_skill": {"id": "zero"}, "max_starved_ticks": 0}, deadline_ms=250
    )
    ticks = Ticks(at=10**9)
    started = time.perf_counter()
    result = _run(runner, 12, ticks)
    assert time.perf_counter() - started < 5.0  # the run never waited for the hung inference
    stats = result.metadata["executor"]
    assert stats["results_late"] >= 1
    assert stats["chunks_used"] == 0
    assert all(tick.sent_action in (None, [0.0, 0.0]) for tick in ticks.ticks)
    assert max(tick.tick_ms for tick in ticks.ticks) < 1e3 / RATE_HZ
