"""ChunkedExecutor: the tick never waits, rows are indexed by tick, resets, seams, starvation and deadlines."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from openral_core import ExecutorConfig, JointState, PrivilegedState, SeamMode, StarvationFallback, WorldState
from openral_rskill.anchoring import EndEffectorDeltaAnchor, StateOffsetAnchor
from openral_rskill.chunks import ChunkRequest
from openral_rskill.executor import ChunkedExecutor, Outcome

NAMES = ["a", "b"]


def world(tick: int, *, a: float = 0.0, privileged: dict[str, list[float]] | None = None) -> WorldState:
    return WorldState(
        stamp_ns=tick,
        joint_state=JointState(names=NAMES, positions=[a, 0.0]),
        privileged=None if privileged is None else PrivilegedState(values=privileged),
    )


class GatedPolicy:
    """A chunk whose row j for an observation at tick k holds [k * 100 + j, -j]; it waits for the test's go."""

    def __init__(self, rows: int = 8, *, gated: bool = True) -> None:
        self.rows = rows
        self.gate = threading.Semaphore(0)
        self.gated = gated
        self.calls: list[str] = []
        self.inferring = False
        self.overlapped = False

    def infer(self, request: ChunkRequest) -> np.ndarray:
        observed = request.world
        self.inferring = True
        self.calls.append(f"infer@{observed.stamp_ns}")
        if self.gated:
            self.gate.acquire()
        self.inferring = False
        k = observed.stamp_ns
        return np.array([[k * 100 + j, -j] for j in range(self.rows)], dtype=float)

    def reset(self) -> None:
        self.overlapped |= self.inferring
        self.calls.append("reset")


def wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.001)


def executor(policy: GatedPolicy, config: ExecutorConfig | None = None, **kwargs: object) -> ChunkedExecutor:
    options: dict[str, object] = {"action_names": NAMES, "reset": policy.reset}
    options.update(kwargs)
    return ChunkedExecutor(policy.infer, config, **options)  # type: ignore[arg-type]


def test_rows_skipped_equal_the_ticks_that_passed_while_inferring() -> None:
    policy = GatedPolicy()
    ex = executor(policy)
    try:
        for tick in range(5):  # inference under way: nothing to send yet, and the tick does not wait
            assert ex.step(tick, world(tick)).outcome is Outcome.NONE
        policy.gate.release()
        wait_for(lambda: ex.results_waiting == 1)
        decision = ex.step(5, world(5))
        assert decision.outcome is Outcome.ACTION
        assert decision.action is not None
        assert decision.action.first == [5.0, -5.0]  # row 5 of the chunk observed at tick 0
        assert ex.stats.rows_skipped == 5
        assert list(ex.stats.delays_ticks) == [5]
        assert [ex.step(t, world(t)).action.first[0] for t in (6, 7)] == [6.0, 7.0]  # type: ignore[union-attr]
    finally:
        policy.gate.release(10)
        ex.close()


def test_a_chunk_with_too_few_usable_rows_is_discarded_and_counted() -> None:
    policy = GatedPolicy(rows=4)
    ex = executor(policy, ExecutorConfig(min_rows=2))
    try:
        for tick in range(3):
            ex.step(tick, world(tick))
        policy.gate.release()
        wait_for(lambda: ex.results_waiting == 1)
        assert ex.step(3, world(3)).outcome is Outcome.NONE  # 1 usable row of 4: below min_rows
        assert ex.stats.chunks_discarded == 1
        assert ex.stats.chunks_used == 0
    finally:
        policy.gate.release(10)
        ex.close()


def test_a_reset_discards_the_chunk_in_flight_and_never_runs_during_inference() -> None:
    policy = GatedPolicy()
    ex = executor(policy)
    try:
        ex.step(0, world(0))
        wait_for(lambda: policy.inferring)
        ex.reset()
        policy.gate.release()
        wait_for(lambda: "reset" in policy.calls)
        assert not policy.overlapped
        assert policy.calls[:2] == ["infer@0", "reset"]  # the reset waited for the inference
        decision = ex.step(1, world(1))
        assert decision.outcome is Outcome.NONE  # the old epoch's chunk is not used...
        assert ex.stats.results_stale_epoch == 1
        assert ex.in_flight  # ...and a fresh request for this episode is out
    finally:
        policy.gate.release(10)
        ex.close()


def test_starvation_holds_the_last_target_then_falls_back() -> None:
    policy = GatedPolicy(rows=3)
    ex = executor(policy, ExecutorConfig(max_starved_ticks=2, fallback=StarvationFallback.SKILL, margin_ticks=0))
    try:
        ex.step(0, world(0))
        policy.gate.release()  # the first chunk only: the next request stays stuck
        wait_for(lambda: ex.results_waiting == 1)
        outcomes = [ex.step(t, world(t)) for t in range(1, 8)]
        # Rows 1 and 2 (row 0's tick has passed), then the last target held twice, then the fallback.
        assert [d.outcome for d in outcomes] == [Outcome.ACTION] * 2 + [Outcome.HOLD] * 2 + [Outcome.FALLBACK] * 3
        assert ex.fallback_active  # what a console shows
        assert outcomes[2].action is not None
        assert outcomes[2].action.first == [2.0, -2.0]
        assert ex.stats.starved_ticks == 5
    finally:
        policy.gate.release(10)
        ex.close()


def test_a_hung_policy_never_blocks_the_tick_and_its_late_result_is_dropped() -> None:
    policy = GatedPolicy()
    ex = executor(policy, ExecutorConfig(deadline_ticks=5))
    try:
        ex.step(0, world(0))
        wait_for(lambda: policy.inferring)  # stuck in its inference from here on
        ticking = threading.Thread(target=lambda: [ex.step(tick, world(tick)) for tick in range(1, 40)])
        ticking.start()
        ticking.join(30)  # microseconds a tick; a tick that waits for the policy waits for the gate
        assert not ticking.is_alive(), "a tick waited for the stuck policy"
        assert policy.inferring  # still stuck: the ticks ran past it
        assert ex.stats.results_late == 1  # given up on at its deadline; no request queued behind it
        assert ex.stats.requests == 1
        policy.gate.release(5)
        wait_for(lambda: ex.results_waiting >= 1)
        ex.step(40, world(40))
        assert ex.stats.chunks_used == 0  # the late result was dropped by id when it came
    finally:
        policy.gate.release(10)
        ex.close(timeout_s=1.0)


def test_a_slow_policy_at_30_hz_keeps_every_tick_short() -> None:
    """300 ms inference against 33 ms ticks: the tick stays in microseconds and rows match elapsed ticks."""

    class Slow(GatedPolicy):
        def infer(self, request: ChunkRequest) -> np.ndarray:
            time.sleep(0.3)
            k = request.world.stamp_ns
            return np.array([[k * 100 + j, -j] for j in range(self.rows)], dtype=float)

    policy = Slow(rows=30, gated=False)
    ex = executor(policy)
    period = 1 / 30
    start = time.monotonic()
    longest = 0.0
    try:
        for tick in range(45):
            time.sleep(max(0.0, start + tick * period - time.monotonic()))
            t0 = time.perf_counter()
            decision = ex.step(tick, world(tick))
            longest = max(longest, time.perf_counter() - t0)
            if decision.outcome is Outcome.ACTION:
                assert decision.action is not None
                obs_tick, row = divmod(int(decision.action.first[0]), 100)
                assert obs_tick + row == tick  # each row is sent at exactly the tick it was made for
    finally:
        ex.close()
    assert longest < 0.25  # below one inference (0.3 s): the tick never waited for it, even on a loaded machine
    assert ex.stats.chunks_used >= 1
    assert ex.stats.rows_skipped == sum(ex.stats.delays_ticks)


def test_virtual_latency_makes_a_chunk_usable_exactly_d_ticks_later() -> None:
    policy = GatedPolicy(gated=False)
    ex = executor(policy, virtual_delay=lambda _request: 2)
    assert [ex.step(t, world(t)).outcome for t in (0, 1)] == [Outcome.NONE, Outcome.NONE]
    decision = ex.step(2, world(2))
    assert decision.action is not None
    assert decision.action.first == [2.0, -2.0]
    assert list(ex.stats.delays_ticks) == [2]


@pytest.mark.parametrize(
    ("seam", "expected"),
    [
        (SeamMode.REPLACE, [0.0, 1.0, 200.0, 201.0]),
        (SeamMode.CROSSFADE, [0.0, 1.0, 0.5 * 2.0 + 0.5 * 200.0, 201.0]),
    ],
)
def test_seams_between_the_old_chunk_and_the_new(seam: SeamMode, expected: list[float]) -> None:
    policy = GatedPolicy(rows=6, gated=False)
    ex = executor(policy, ExecutorConfig(seam=seam, crossfade_rows=1, margin_ticks=3), virtual_delay=lambda _request: 0)
    firsts = [ex.step(t, world(t)).action.first[0] for t in range(4)]  # type: ignore[union-attr]
    # Chunk 0 serves ticks 0 and 1; at tick 2 the rows left (4) reach p95 + margin, and chunk 1,
    # observed at tick 2 with no delay, meets chunk 0's row for tick 2 there.
    assert firsts == pytest.approx(expected)


def test_each_decision_names_the_chunk_its_row_came_from_and_a_held_row_keeps_it() -> None:
    policy = GatedPolicy(rows=3, gated=False)
    # Chunks of 3 rows, the next asked for with one row left (the p95 before any measurement): chunk 1
    # replaces chunk 0 at tick 2; chunk 2 never arrives, so chunk 1's last row is held from tick 5 on.
    ex = executor(policy, ExecutorConfig(margin_ticks=0), virtual_delay=lambda request: 0 if request < 2 else 99)
    decisions = [ex.step(t, world(t)) for t in range(8)]
    assert [d.outcome for d in decisions] == [Outcome.ACTION] * 5 + [Outcome.HOLD] * 3
    assert [d.chunk for d in decisions] == [0, 0, 1, 1, 1, 1, 1, 1]
    assert [d.action.first[0] for d in decisions if d.action is not None] == [0, 1, 200, 201, 202, 202, 202, 202]


def test_a_new_episodes_first_chunk_is_not_held_up_by_a_slow_one_of_the_episode_before() -> None:
    policy = GatedPolicy(rows=3, gated=False)
    # Episode 1: its second request (tick 2) takes 20 ticks, and the episode ends before it is usable.
    ex = executor(policy, ExecutorConfig(margin_ticks=0), virtual_delay=lambda request: 0 if request == 0 else 20)
    assert [ex.step(t, world(t)).outcome for t in range(4)] == [Outcome.ACTION] * 3 + [Outcome.HOLD]
    ex.reset()
    ex.virtual_delay = lambda _request: 0  # episode 2's delays, as a simulation sets them at its reset
    decision = ex.step(4, world(4))
    assert decision.outcome is Outcome.ACTION  # its own chunk, at once: not after episode 1's slow one
    assert decision.action is not None
    assert decision.action.first[0] == 400
    assert ex.stats.results_stale_epoch == 1


def test_ensemble_weights_older_predictions_first() -> None:
    policy = GatedPolicy(rows=4, gated=False)
    ex = executor(
        policy,
        ExecutorConfig(seam=SeamMode.ENSEMBLE, ensemble_decay=0.0, margin_ticks=10),
        virtual_delay=lambda _request: 0,
    )
    values = [ex.step(t, world(t)).action.first[0] for t in range(2)]  # type: ignore[union-attr]
    # A new chunk every tick; with decay 0 each tick's target is the mean of every prediction for it.
    assert values[0] == 0.0
    assert values[1] == pytest.approx((1.0 + 100.0) / 2)


def test_relative_rows_are_anchored_at_the_observation_and_end_effector_moves_at_the_tick_sent() -> None:
    offsets = np.array([[0.1, 0.0], [0.2, 0.0]])
    anchored = StateOffsetAnchor(NAMES).to_targets(offsets, world(0, a=1.0))
    np.testing.assert_allclose(anchored, [[1.1, 0.0], [1.2, 0.0]])

    anchor = EndEffectorDeltaAnchor("ee", scale=0.1, position_dims=(0,), limit=1.0)
    moves = np.array([[1.0, 0.5], [1.0, 0.0]])
    targets = anchor.to_targets(moves, world(0, privileged={"ee": [2.0]}))
    np.testing.assert_allclose(targets, [[2.1, 0.5], [2.2, 0.0]])  # absolute dims (a gripper) kept
    # Sent later from where the arm really is: the move that reaches the target, clipped to the bound.
    np.testing.assert_allclose(anchor.to_command(targets[1], world(3, privileged={"ee": [2.15]})), [0.5, 0.0])
    np.testing.assert_allclose(anchor.to_command(targets[1], world(3, privileged={"ee": [1.0]})), [1.0, 0.0])


def test_each_chunk_request_is_a_span_and_starvation_and_discards_are_counted(telemetry) -> None:
    from openral_observability import semconv  # noqa: PLC0415

    policy = GatedPolicy(rows=3, gated=False)
    delays = [1, 5]
    ex = executor(
        policy,
        ExecutorConfig(min_rows=1, margin_ticks=0),
        virtual_delay=lambda i: delays[i] if i < len(delays) else 0,
    )
    for tick in range(8):
        ex.step(tick, world(tick))
    spans = telemetry.spans(semconv.SPAN_EXECUTOR_CHUNK)
    assert [s.attributes[semconv.ATTR_EXECUTOR_DELAY_TICKS] for s in spans[:2]] == [1, 5]
    used, discarded = spans[:2]
    assert used.attributes[semconv.ATTR_EXECUTOR_OBS_TICK] == 0
    assert used.attributes[semconv.ATTR_EXECUTOR_ROWS_SKIPPED] == 1
    assert used.attributes[semconv.ATTR_EXECUTOR_ROWS_USED] == 2
    # Observed at tick 2, usable at 7: all 3 rows are for past ticks.
    assert discarded.attributes[semconv.ATTR_EXECUTOR_DISCARDED] == "too_few_rows"
    assert telemetry.metric(semconv.METRIC_EXECUTOR_DISCARDED, **{semconv.ATTR_EXECUTOR_DISCARDED: "too_few_rows"}) == 1
    assert telemetry.metric(semconv.METRIC_EXECUTOR_STARVED_TICKS) == ex.stats.starved_ticks > 0


def test_rows_that_cannot_be_anchored_start_stale_with_a_warning() -> None:
    from structlog.testing import capture_logs  # noqa: PLC0415

    from openral_rskill.anchoring import UnanchoredRows  # noqa: PLC0415

    policy = GatedPolicy(gated=False)
    with capture_logs() as logs:
        ex = executor(policy, virtual_delay=lambda _request: 2, anchor=UnanchoredRows())
    assert any("stale start" in entry["event"] for entry in logs)
    decisions = [ex.step(t, world(t)) for t in range(3)]
    assert decisions[2].action is not None
    assert decisions[2].action.first == [0.0, 0.0]  # row 0 of the chunk observed at tick 0, two ticks late
    assert ex.stats.rows_skipped == 0


def test_a_request_span_is_a_child_of_the_asking_tick_and_inference_runs_under_it(telemetry) -> None:
    from opentelemetry import trace  # noqa: PLC0415

    from openral_observability import semconv, tracer  # noqa: PLC0415

    seen: list[int] = []

    def infer(request: ChunkRequest) -> np.ndarray:
        seen.append(trace.get_current_span().get_span_context().span_id)
        return np.zeros((4, 2))

    ex = ChunkedExecutor(infer, action_names=NAMES)
    try:
        with tracer().start_as_current_span("tick") as tick:
            ex.step(0, world(0))
        wait_for(lambda: ex.results_waiting == 1)
        ex.step(1, world(1))
    finally:
        ex.close()
    (span,) = telemetry.spans(semconv.SPAN_EXECUTOR_CHUNK)
    assert span.parent is not None
    assert span.parent.span_id == tick.get_span_context().span_id
    assert seen == [span.context.span_id]  # a remote client injects this span as the server's parent
    assert span.attributes[semconv.ATTR_EXECUTOR_READY_TICK] == 1


def test_a_source_that_is_down_is_not_asked_and_the_fallback_decides_at_once() -> None:
    policy = GatedPolicy(rows=6, gated=False)
    up = [True]
    ex = executor(
        policy,
        ExecutorConfig(fallback=StarvationFallback.SKILL, max_starved_ticks=5),
        virtual_delay=lambda _request: 0,
        available=lambda: up[0],
    )
    assert ex.step(0, world(0)).outcome is Outcome.ACTION
    assert ex.rows_left == 6
    up[0] = False
    asked = len(policy.calls)
    decisions = [ex.step(t, world(t)).outcome for t in range(1, 4)]
    assert decisions == [Outcome.FALLBACK] * 3  # the buffered rows are not played from a dead source
    assert len(policy.calls) == asked
    assert ex.stats.unavailable_ticks == 3
    up[0] = True
    assert ex.step(4, world(4)).outcome is Outcome.ACTION  # a new chunk at once (virtual delay 0)
    assert policy.calls[-1] == "infer@4"


def test_after_the_source_returns_the_fallback_acts_until_a_chunk_arrives() -> None:
    policy = GatedPolicy(rows=3, gated=False)
    up = [True]
    ex = executor(
        policy,
        ExecutorConfig(fallback=StarvationFallback.SKILL, max_starved_ticks=5),
        virtual_delay=lambda request: 0 if request == 0 else 2,
        available=lambda: up[0],
    )
    assert ex.step(0, world(0)).outcome is Outcome.ACTION
    up[0] = False
    assert ex.step(1, world(1)).outcome is Outcome.FALLBACK
    up[0] = True
    # Asked again at tick 2, usable at tick 4: never the stale target of before the outage meanwhile.
    assert [ex.step(t, world(t)).outcome for t in (2, 3)] == [Outcome.FALLBACK, Outcome.FALLBACK]
    assert ex.step(4, world(4)).outcome is Outcome.ACTION
    assert not ex.fallback_active  # a row arrived: the policy acts again


def test_a_policy_that_times_out_is_counted_late_not_failed() -> None:
    def infer(request: ChunkRequest) -> np.ndarray:
        raise TimeoutError("no reply before the deadline")

    ex = ChunkedExecutor(infer, action_names=NAMES, virtual_delay=lambda _request: 0)
    for tick in range(3):
        assert ex.step(tick, world(tick)).outcome is Outcome.NONE
    assert ex.stats.results_late == 3
    assert ex.stats.errors == 0


def _drive(ex: ChunkedExecutor, ticks: int) -> dict[int, list[float]]:
    sent: dict[int, list[float]] = {}
    for tick in range(ticks):
        decision = ex.step(tick, world(tick))
        if decision.action is not None:
            sent[tick] = decision.action.first
    return sent


def test_the_prefix_is_exactly_the_targets_sent_while_the_policy_infers() -> None:
    asked: list[ChunkRequest] = []

    def infer(request: ChunkRequest) -> np.ndarray:
        asked.append(request)
        k = request.obs_tick
        return np.array([[k * 100 + j, -j] for j in range(8)], dtype=float)

    ex = ChunkedExecutor(infer, ExecutorConfig(margin_ticks=1), action_names=NAMES, virtual_delay=lambda _i: 3)
    sent = _drive(ex, 40)
    assert len(asked) >= 5
    assert len(asked[0].prefix) == 0  # nothing buffered yet: nothing runs while the first chunk is computed
    for request in [r for r in asked[1:] if r.obs_tick + r.inference_delay < 40]:  # whose prefix ran in the test
        # The rows buffered for the ticks before the chunk lands (the virtual delay: 3), as they are sent.
        assert request.inference_delay == 3
        assert 1 <= len(request.prefix) <= 3
        for offset, row in enumerate(request.prefix):
            assert sent[request.obs_tick + offset] == row.tolist()
    assert any(len(request.prefix) == 3 for request in asked)


def test_a_skill_that_continues_its_prefix_meets_the_old_chunk_without_a_jump() -> None:
    def chunk(request: ChunkRequest, *, use_prefix: bool) -> np.ndarray:
        # A policy whose every chunk ramps up by 1 per tick from where it believes it starts.
        start = request.prefix[-1, 0] + 1 - request.inference_delay if use_prefix and len(request.prefix) else 0.0
        return np.array([[start + j, 0.0] for j in range(8)], dtype=float)

    jumps = {}
    for use_prefix in (True, False):
        ex = ChunkedExecutor(
            lambda request, use=use_prefix: chunk(request, use_prefix=use),  # type: ignore[misc]
            action_names=NAMES,
            virtual_delay=lambda _i: 3,
        )
        sent = _drive(ex, 40)
        values = [sent[t][0] for t in sorted(sent)]
        jumps[use_prefix] = max(abs(b - a) for a, b in itertools.pairwise(values))
    assert jumps[True] == 1.0  # continuous: each new chunk picks up where the executed rows will be
    assert jumps[False] > 1.0  # without the prefix every seam jumps back


def test_requests_carry_the_last_commands_sent_by_tick_and_a_reset_forgets_them() -> None:
    asked: list[ChunkRequest] = []

    def infer(request: ChunkRequest) -> np.ndarray:
        asked.append(request)
        return np.array([[request.obs_tick * 100 + j, -j] for j in range(4)], dtype=float)

    ex = ChunkedExecutor(
        infer, ExecutorConfig(margin_ticks=0), action_names=NAMES, past_actions=3, virtual_delay=lambda _i: 1
    )
    for tick in range(12):
        decision = ex.step(tick, world(tick))
        if decision.action is not None and tick != 5:  # tick 5's command withheld: never sent
            ex.sent(tick, [tick + 0.5, -float(tick)])  # what the robot got after the safety check
    assert len(asked) >= 3
    assert len(asked[0].past) == 0
    assert asked[0].past_ticks == ()
    for request in asked:
        expected = [t for t in range(1, request.obs_tick) if t != 5][-3:]  # tick 0 awaited the first chunk
        assert request.past_ticks == tuple(expected)  # the last three sent before the request's tick, oldest first
        assert request.past.tolist() == [[t + 0.5, -float(t)] for t in expected]
        assert request.past.shape == (len(expected), 2)
    assert any(r.obs_tick > 5 and len(r.past) == 3 for r in asked)  # the withheld tick left a gap
    ex.reset()
    ex.step(12, world(12))
    assert asked[-1].obs_tick == 12
    assert len(asked[-1].past) == 0


def test_without_past_actions_no_command_is_kept() -> None:
    asked: list[ChunkRequest] = []

    def infer(request: ChunkRequest) -> np.ndarray:
        asked.append(request)
        return np.zeros((3, 2))

    ex = ChunkedExecutor(infer, action_names=NAMES, virtual_delay=lambda _i: 0)
    for tick in range(8):
        ex.step(tick, world(tick))
        ex.sent(tick, [1.0, 2.0])
    assert len(asked) >= 2
    assert all(r.past.shape == (0, 2) and r.past_ticks == () for r in asked)


def test_requests_carry_the_earlier_ticks_observations_and_a_reset_forgets_them() -> None:
    asked: list[ChunkRequest] = []

    def infer(request: ChunkRequest) -> np.ndarray:
        asked.append(request)
        return np.zeros((4, 2))

    ex = ChunkedExecutor(infer, action_names=NAMES, virtual_delay=lambda _i: 0, observation_steps=3)
    _drive(ex, 12)
    first, later = asked[0], asked[-1]
    assert first.history == ()
    assert [w.stamp_ns for w in first.observations(3)] == [0, 0, 0]  # the first observation repeated
    assert [w.stamp_ns for w in later.observations(3)] == [later.obs_tick - 2, later.obs_tick - 1, later.obs_tick]
    ex.reset()
    ex.step(20, world(20))
    assert asked[-1].history == ()
