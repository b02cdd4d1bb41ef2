"""RSkillBase: lifecycle transitions, error latch and recovery, step latency bookkeeping."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable

import numpy as np
import pytest
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter
from pydantic import BaseModel, ConfigDict

import openral_rskill.base as base_module
from openral_core import (
    Action,
    ControlMode,
    ROSConfigError,
    ROSEStopRequested,
    ROSSkillError,
    ROSStopRequested,
    RSkillInfo,
    RSkillState,
    WorldState,
)
from openral_observability import semconv
from openral_rskill import RSkillBase, rSkillBase, validate_params
from openral_rskill.base import ChunkingSkillBase
from openral_rskill.chunks import ChunkRequest

S = RSkillState
WS = WorldState(stamp_ns=0)


class Probe(RSkillBase):
    """Records every hook call; a hook or step fails when its name is in ``fail``."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[str] = []
        self.fail: dict[str, Exception] = {}
        self.step_cost_ns = 0

    @property
    def info(self) -> RSkillInfo:
        return RSkillInfo(skill_id="probe")

    def _hook(self, name: str) -> None:
        self.calls.append(name)
        if name in self.fail:
            raise self.fail[name]

    def _on_configure(self) -> None:
        self._hook("configure")

    def _on_activate(self) -> None:
        self._hook("activate")

    def _on_deactivate(self) -> None:
        self._hook("deactivate")

    def _on_shutdown(self) -> None:
        self._hook("shutdown")

    def _on_reset(self) -> None:
        self._hook("reset")

    def _step_impl(self, world_state: WorldState) -> Action:
        self._hook("step")
        _FakeClock.now += self.step_cost_ns
        return Action(joint_names=["j"], targets=[[0.0]], skill_id="probe")


class _FakeClock:
    now = 0

    @classmethod
    def read(cls) -> int:
        return cls.now


def drive_to(state: RSkillState) -> Probe:
    """A probe in ``state``, reached through the public lifecycle (ERROR via a failing step)."""
    skill = Probe()
    if state is S.UNCONFIGURED:
        return skill
    if state is S.FINALIZED:
        skill.shutdown()
        return skill
    skill.configure()
    if state is S.INACTIVE:
        return skill
    skill.activate()
    if state is S.ERROR:
        skill.fail["step"] = RuntimeError("boom")
        with pytest.raises(ROSSkillError):
            skill.step(WS)
        del skill.fail["step"]
    skill.calls.clear()
    return skill


OPS: dict[str, Callable[[Probe], object]] = {
    "configure": lambda s: s.configure(),
    "activate": lambda s: s.activate(),
    "deactivate": lambda s: s.deactivate(),
    "reset": lambda s: s.reset(),
    "recover": lambda s: s.recover(),
    "step": lambda s: s.step(WS),
}

# state -> op -> resulting state; ops missing from a row are invalid in that state.
VALID: dict[RSkillState, dict[str, RSkillState]] = {
    S.UNCONFIGURED: {"configure": S.INACTIVE},
    S.INACTIVE: {"activate": S.ACTIVE, "reset": S.INACTIVE},
    S.ACTIVE: {"deactivate": S.INACTIVE, "reset": S.ACTIVE, "step": S.ACTIVE},
    S.ERROR: {"recover": S.INACTIVE},
    S.FINALIZED: {},
}
TABLE = [(state, op) for state in VALID for op in OPS]


@pytest.mark.parametrize(("state", "op"), TABLE, ids=[f"{s.value}-{o}" for s, o in TABLE])
def test_transition_table(state: RSkillState, op: str) -> None:
    skill = drive_to(state)
    assert skill.state is state
    expected = VALID[state].get(op)
    if expected is not None:
        OPS[op](skill)
        assert skill.state is expected
        return
    calls_before = list(skill.calls)
    with pytest.raises(ROSSkillError) as info:
        OPS[op](skill)
    assert skill.state is state, "an invalid transition must not change the state"
    assert skill.calls == calls_before, "an invalid transition must not run a hook"
    message = str(info.value)
    assert "probe" in message
    if state is S.ERROR:
        assert "error latch" in message
        assert "recover()" in message
    else:
        assert state.value.upper() in message
        allowed = [s for s, ops in VALID.items() if op in ops]
        for s in allowed:
            assert s.value.upper() in message


@pytest.mark.parametrize("state", list(S))
def test_shutdown_from_any_state_finalizes_and_is_idempotent(state: RSkillState) -> None:
    skill = drive_to(state)
    skill.shutdown()
    assert skill.state is S.FINALIZED
    calls = list(skill.calls)
    skill.shutdown()
    assert skill.state is S.FINALIZED
    assert skill.calls == calls


@pytest.mark.parametrize(
    ("state", "hooks"),
    [
        (S.UNCONFIGURED, []),
        (S.INACTIVE, ["shutdown"]),
        (S.ACTIVE, ["deactivate", "shutdown"]),
        (S.ERROR, ["deactivate", "shutdown"]),  # the step failed while active: release both
        (S.FINALIZED, []),
    ],
)
def test_shutdown_releases_exactly_what_is_held(state: RSkillState, hooks: list[str]) -> None:
    skill = drive_to(state)
    skill.calls.clear()
    skill.shutdown()
    assert skill.calls == hooks


def test_hooks_run_once_per_transition() -> None:
    skill = Probe()
    skill.configure()
    skill.activate()
    skill.step(WS)
    skill.reset()
    skill.deactivate()
    skill.reset()
    skill.shutdown()
    assert skill.calls == ["configure", "activate", "step", "reset", "deactivate", "reset", "shutdown"]


@pytest.mark.parametrize(
    ("phase", "state", "resting"),
    [
        ("configure", S.UNCONFIGURED, S.UNCONFIGURED),
        ("activate", S.INACTIVE, S.INACTIVE),
        ("deactivate", S.ACTIVE, S.INACTIVE),
        ("reset", S.ACTIVE, S.INACTIVE),
        ("reset", S.INACTIVE, S.INACTIVE),
        ("step", S.ACTIVE, S.INACTIVE),
    ],
)
def test_failure_latches_chains_and_recovers(phase: str, state: RSkillState, resting: RSkillState) -> None:
    skill = drive_to(state)
    original = ValueError("bad weights")
    skill.fail[phase] = original
    with pytest.raises(ROSSkillError) as info:
        OPS[phase](skill)
    assert info.value.__cause__ is original
    assert "probe" in str(info.value)
    assert phase in str(info.value)
    assert "bad weights" in str(info.value)
    assert skill.state is S.ERROR
    assert skill.last_error is original

    del skill.fail[phase]
    skill.recover()
    assert skill.state is resting
    assert skill.last_error is None


def test_latched_step_fails_fast_without_calling_the_skill() -> None:
    skill = drive_to(S.ERROR)
    for _ in range(3):
        with pytest.raises(ROSSkillError, match="error latch"):
            skill.step(WS)
    assert "step" not in skill.calls


def test_reset_does_not_clear_the_latch() -> None:
    skill = drive_to(S.ERROR)
    with pytest.raises(ROSSkillError, match="error latch"):
        skill.reset()
    assert skill.state is S.ERROR


def test_recover_after_a_step_failure_deactivates_then_allows_a_new_episode() -> None:
    skill = drive_to(S.ERROR)
    skill.recover()
    assert skill.calls == ["deactivate"]
    skill.activate()
    assert isinstance(skill.step(WS), Action)
    assert skill.state is S.ACTIVE


def test_recover_after_a_failed_activate_does_not_deactivate() -> None:
    skill = drive_to(S.INACTIVE)
    skill.fail["activate"] = RuntimeError("no device")
    with pytest.raises(ROSSkillError):
        skill.activate()
    skill.calls.clear()
    skill.recover()
    assert skill.calls == []
    assert skill.state is S.INACTIVE


def test_recover_keeps_the_latch_when_deactivate_fails_then_succeeds_next_time() -> None:
    skill = drive_to(S.ERROR)
    skill.fail["deactivate"] = RuntimeError("stuck")
    with pytest.raises(ROSSkillError, match="recover"):
        skill.recover()
    assert skill.state is S.ERROR
    skill.recover()  # deactivate was attempted once; it is not retried
    assert skill.state is S.INACTIVE


def test_failing_shutdown_still_finalizes_and_raises_chained() -> None:
    skill = drive_to(S.ACTIVE)
    original = OSError("driver gone")
    skill.fail["deactivate"] = original
    with pytest.raises(ROSSkillError, match="deactivate during shutdown") as info:
        skill.shutdown()
    assert info.value.__cause__ is original
    assert skill.calls == ["deactivate", "shutdown"], "shutdown must still run after a failing deactivate"
    assert skill.state is S.FINALIZED
    skill.shutdown()


def test_error_message_survives_an_exception_without_text() -> None:
    skill = drive_to(S.ACTIVE)
    skill.fail["step"] = KeyError()
    with pytest.raises(ROSSkillError, match="failed in step: KeyError"):
        skill.step(WS)


def test_latch_adds_an_event_to_the_current_span() -> None:
    exporter = InMemorySpanExporter()
    provider = TracerProvider()
    provider.add_span_processor(SimpleSpanProcessor(exporter))
    skill = drive_to(S.ACTIVE)
    skill.fail["step"] = RuntimeError("boom")
    with provider.get_tracer("test").start_as_current_span("tick"), pytest.raises(ROSSkillError):
        skill.step(WS)
    (span,) = exporter.get_finished_spans()
    events = [e for e in span.events if e.name == semconv.EVENT_ERROR_LATCHED]
    assert len(events) == 1
    assert events[0].attributes is not None
    assert events[0].attributes[semconv.ATTR_SKILL_ID] == "probe"


def test_keyboard_interrupt_is_not_latched() -> None:
    skill = drive_to(S.ACTIVE)
    skill.fail["step"] = KeyboardInterrupt()  # type: ignore[assignment]
    with pytest.raises(KeyboardInterrupt):
        skill.step(WS)
    assert skill.state is S.ACTIVE


def test_step_latency_bookkeeping(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(base_module, "perf_counter_ns", _FakeClock.read)
    skill = drive_to(S.ACTIVE)
    assert (skill.step_count, skill.last_step_ms, skill.mean_step_ms, skill.max_step_ms) == (0, 0.0, 0.0, 0.0)
    for cost_ms in (2.0, 6.0, 1.0):
        skill.step_cost_ns = int(cost_ms * 1e6)
        skill.step(WS)
        assert skill.last_step_ms == pytest.approx(cost_ms)
    assert skill.step_count == 3
    assert skill.mean_step_ms == pytest.approx(3.0)
    assert skill.max_step_ms == pytest.approx(6.0)

    skill.fail["step"] = RuntimeError("boom")
    with pytest.raises(ROSSkillError):
        skill.step(WS)
    assert skill.step_count == 3, "a failed step is not a step"

    skill.reset_step_stats()
    assert (skill.step_count, skill.last_step_ms, skill.mean_step_ms, skill.max_step_ms) == (0, 0.0, 0.0, 0.0)


class Lean(RSkillBase):
    """Returns one prebuilt action: any memory growth while stepping is the base's."""

    ACTION = Action(joint_names=["j"], targets=[[0.0]])

    @property
    def info(self) -> RSkillInfo:
        return RSkillInfo(skill_id="lean")

    def _step_impl(self, world_state: WorldState) -> Action:
        return self.ACTION


def test_stepping_does_not_grow_memory() -> None:
    skill = Lean()
    skill.configure()
    skill.activate()
    for _ in range(1_000):
        skill.step(WS)
    tracemalloc.start()
    try:
        first = tracemalloc.take_snapshot()
        for _ in range(20_000):
            skill.step(WS)
        grown = sum(stat.size_diff for stat in tracemalloc.take_snapshot().compare_to(first, "filename"))
    finally:
        tracemalloc.stop()
    assert grown < 20_000 * 8, f"{grown} bytes kept over 20000 steps"


def test_subclass_must_implement_step_and_info() -> None:
    class Incomplete(RSkillBase):
        pass

    with pytest.raises(TypeError, match="_step_impl"):
        Incomplete()  # type: ignore[abstract]


def test_spec_name_is_the_same_class() -> None:
    assert rSkillBase is RSkillBase


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    gain: float = 1.0


def test_validate_params_names_the_bad_key_and_the_allowed_ones() -> None:
    with pytest.raises(ROSConfigError) as info:
        validate_params(_Params, {"gian": 2.0}, skill_id="probe")
    message = str(info.value)
    assert "gian" in message
    assert "allowed keys: gain" in message
    assert "did you mean 'gain'" in message
    assert "skill 'probe'" in message
    assert validate_params(_Params, {"gain": 2.0}, skill_id="probe").gain == 2.0


@pytest.mark.parametrize("request_", [ROSEStopRequested("person in the cell"), ROSStopRequested("task done")])
def test_stop_requests_pass_through_without_latching(request_: Exception) -> None:
    skill = drive_to(S.ACTIVE)
    skill.fail["step"] = request_
    with pytest.raises(type(request_)) as info:
        skill.step(WS)
    assert info.value is request_
    assert skill.state is S.ACTIVE


class Chunker(ChunkingSkillBase):
    """Writes only its chunk: row ``j`` is ``[10 * tick + j, -j]`` for the tick of the observation."""

    def __init__(self) -> None:
        super().__init__()
        self.requests: list[ChunkRequest] = []

    @property
    def info(self) -> RSkillInfo:
        return RSkillInfo(skill_id="chunker", control_mode=ControlMode.EE_DELTA, chunk_size=3)

    @property
    def action_names(self) -> list[str]:
        return ["x", "gripper"]

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        self.requests.append(request)
        tick = request.world.stamp_ns
        return np.array([[10.0 * tick + j, -float(j)] for j in range(3)])


def test_a_chunking_skill_steps_the_first_row_of_its_chunk() -> None:
    skill = Chunker()
    skill.configure()
    skill.activate()
    action = skill.step(WorldState(stamp_ns=4))
    assert action.targets == [[40.0, 0.0]]
    assert action.joint_names == ["x", "gripper"]
    assert (action.control_mode, action.skill_id, action.stamp_ns) == (ControlMode.EE_DELTA, "chunker", 4)
    assert [request.world.stamp_ns for request in skill.requests] == [4]
    chunk = skill.step_chunk(ChunkRequest(WorldState(stamp_ns=5)))
    assert chunk.shape == (3, 2)
    assert skill.step_count == 2


def test_a_chunking_skill_must_name_its_chunk_and_its_columns() -> None:
    class Incomplete(ChunkingSkillBase):
        @property
        def info(self) -> RSkillInfo:
            return RSkillInfo(skill_id="incomplete")

    with pytest.raises(TypeError, match="_chunk_impl") as info:
        Incomplete()  # type: ignore[abstract]
    assert "action_names" in str(info.value)
