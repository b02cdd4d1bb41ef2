"""The console's health dict, read from a real ``HardwareRunner`` (on a fake clock) and from duck-typed runners."""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest

from openral_console.status import runner_status, start_jitter_p99_us
from openral_core import ExecutorConfig, StarvationFallback, TickResult, WithheldReason
from openral_hal.testing import RecordingHAL
from openral_rskill.executor import ExecutorStats
from openral_rskill.testing import ScriptedSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock
from openral_world_state import WorldStateAggregator

JOINTS = ["j0", "j1", "j2"]
RATE = 30.0


@pytest.fixture
def runner() -> Iterator[HardwareRunner]:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=[[0.1, 0.0, 0.0]] * 4, raise_on={2: RuntimeError("boom")})
    skill.configure()
    skill.activate()
    built = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=100.0, clock=clock.now_ns),
        rate_hz=RATE,
        clock=clock,
        thumbnail_hz=0.0,
        task="wave hello",
    )
    built.activate()
    yield built
    built.deactivate()


def test_a_hardware_runners_health_names_its_skill_task_withheld_reasons_and_timing(runner: HardwareRunner) -> None:
    runner.run(6)
    status = runner_status(runner)
    assert status["skill_id"] == runner.skill_id
    assert status["task"] == "wave hello"
    assert status["live"]["ticks"] == 6
    assert status["live"]["target_hz"] == RATE
    assert status["live"]["start_jitter_us_p99"] == pytest.approx(0.0, abs=1.0)  # the fake clock is never late
    assert status["withheld"] == {str(WithheldReason.SKILL_ERROR): 4}  # the failure latches
    assert status["withheld_window"] == 6
    assert status["stale_sensors"] == []
    assert status["executor"] is None  # not a chunking skill
    assert status["takeover"] is None  # no takeover on this runner
    json.dumps(status, allow_nan=False)  # plain JSON


def _runner(**attrs: object) -> SimpleNamespace:
    base = {
        "recent_ticks": deque(),
        "rate_hz": 10.0,
        "skill_id": "policy",
        "task": None,
        "executor": None,
        "live_status": lambda: {"ticks": 0.0, "target_hz": 10.0},
    }
    return SimpleNamespace(**{**base, **attrs})


def test_takeover_is_shown_when_the_runner_has_it() -> None:
    takeover = SimpleNamespace(human_in_control=True, skill_id="so101_leader")
    status = runner_status(_runner(takeover=takeover))
    assert status["takeover"] == {"human_in_control": True, "skill_id": "so101_leader"}
    assert runner_status(_runner(takeover=None))["takeover"] is None


def test_a_chunking_skills_executor_shows_delay_starvation_and_fallback() -> None:
    stats = ExecutorStats(requests=5, chunks_used=4, starved_ticks=12, delays_ticks=deque([2, 3, 2]))
    config = ExecutorConfig(max_starved_ticks=3, fallback=StarvationFallback.SKILL)
    executor = SimpleNamespace(stats=stats, config=config, fallback_active=True)
    status = runner_status(_runner(executor=executor))["executor"]
    assert status["chunk_delay_ticks"] == 2
    assert status["chunk_delay_ticks_max"] == 3
    assert status["starved_ticks"] == 12
    assert status["fallback_active"] is True
    executor.fallback_active = False
    assert runner_status(_runner(executor=executor))["executor"]["fallback_active"] is False


def test_stale_sensors_come_from_the_latest_tick_and_a_free_running_sim_has_no_jitter() -> None:
    ticks = deque([TickResult(tick_idx=0, stale_sensors=["cam"]), TickResult(tick_idx=1, stale_sensors=["wrist"])])
    status = runner_status(_runner(recent_ticks=ticks, free_running=True))
    assert status["stale_sensors"] == ["wrist"]
    assert status["live"]["start_jitter_us_p99"] is None


def test_start_jitter_is_recovered_from_start_stamps_on_the_slot_grid() -> None:
    rng = np.random.default_rng(1)
    period_ns = 1e9 / RATE
    t0 = 123_456_789.0
    jitter_ns = rng.uniform(20_000, 400_000, 300)  # 20-400 µs late; slot 17 skipped (a missed slot)
    slots = [k for k in range(301) if k != 17]
    ticks = [
        TickResult(tick_idx=i, start_ns=round(t0 + k * period_ns + j))
        for i, (k, j) in enumerate(zip(slots, jitter_ns, strict=True))
    ]
    expected = np.percentile(jitter_ns - jitter_ns.min(), 99) / 1e3
    assert start_jitter_p99_us(ticks, RATE) == pytest.approx(expected, abs=1.0)
    assert start_jitter_p99_us(ticks[:1], RATE) is None
