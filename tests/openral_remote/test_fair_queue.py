"""The server's queue and episode table, without Zenoh: turns, latest wins, bounds, batches, idle clients."""

import threading
import time

import pytest

from openral_remote.admission import ServeLimits
from openral_remote.episodes import EpisodeTable
from openral_remote.fair_queue import INFER, RESET, FairQueue, Job
from openral_remote.testing import ChunkSkill


def _job(client: str, kind: str = INFER, *, established: bool = False) -> Job:
    return Job(query=None, kind=kind, client=client, established=established)


def _never_active() -> int:
    return 0


def test_clients_are_served_in_turn_whatever_their_rate():
    queue = FairQueue(max_pending=16)
    queue.put(_job("busy", RESET))
    queue.put(_job("busy", RESET))
    queue.put(_job("busy"))
    queue.put(_job("quiet"))
    order = [queue.take(1, 0.0, _never_active)[0] for _ in range(4)]
    assert [(j.client, j.kind) for j in order] == [
        ("busy", RESET),
        ("quiet", INFER),
        ("busy", RESET),
        ("busy", INFER),
    ]


def test_the_latest_inference_of_a_client_supersedes_its_waiting_one():
    queue = FairQueue(max_pending=16)
    first = _job("a")
    queue.put(first)
    admission = queue.put(_job("a"))
    assert admission.superseded == [first]
    assert len(queue) == 1


def test_a_full_queue_refuses_newcomers_and_makes_room_for_a_robot_under_way():
    queue = FairQueue(max_pending=2)
    queue.put(_job("x1"))
    older = _job("x2")
    queue.put(older)
    assert not queue.put(_job("x3")).accepted  # a newcomer: refused at once
    robot = queue.put(_job("robot", established=True))
    assert robot.accepted
    assert robot.displaced == [older]  # the newest newcomer's request made room
    assert {job.client for job in queue.drain()} == {"x1", "robot"}


def test_a_batch_gathers_one_inference_per_client_and_stops_at_a_reset():
    queue = FairQueue(max_pending=16)
    for client in ("a", "b", "c"):
        queue.put(_job(client))
    queue.put(_job("d", RESET))
    batch = queue.take(8, 0.0, _never_active)
    assert [job.client for job in batch] == ["a", "b", "c"]
    assert [job.kind for job in queue.take(8, 0.0, _never_active)] == [RESET]


def test_a_short_batch_waits_for_active_clients_but_never_past_the_wait():
    queue = FairQueue(max_pending=16)
    queue.put(_job("a"))
    started = time.monotonic()
    batch = queue.take(8, 0.15, lambda: 4)  # four active clients, one waiting: wait for the others
    waited = time.monotonic() - started
    assert [job.client for job in batch] == ["a"]
    assert waited < 10.0  # bounded by the wait (load may stretch it, not to the 30 s a wait-forever would take)
    assert waited >= 0.1


def test_a_batch_fills_as_requests_arrive():
    queue = FairQueue(max_pending=16)
    queue.put(_job("a"))

    def later() -> None:
        queue.put(_job("b"))

    threading.Timer(0.05, later).start()
    batch = queue.take(2, 30.0, lambda: 2)  # returns once b arrives, long before the wait
    assert sorted(job.client for job in batch) == ["a", "b"]


def test_a_lone_robot_does_not_wait_for_a_batch():
    queue = FairQueue(max_pending=16)
    queue.put(_job("a"))
    started = time.monotonic()
    queue.take(8, 30.0, lambda: 1)
    assert time.monotonic() - started < 10.0  # every active client is in: no 30 s wait


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_full_table_takes_a_new_client_only_in_the_place_of_an_idle_one():
    clock = _Clock()
    made: list[ChunkSkill] = []

    def factory() -> ChunkSkill:
        made.append(ChunkSkill(["a"], latch=True))
        return made[-1]

    primary = ChunkSkill(["a"], latch=True)
    primary.configure()
    primary.activate()
    table = EpisodeTable(primary, factory=factory, limits=ServeLimits(max_clients=2, client_idle_s=5.0), clock=clock)
    assert table.admit("r1")
    assert table.admit("r2")
    first, second = table.skill_of(table.episode("r1")), table.skill_of(table.episode("r2"))
    assert first is primary
    assert second is made[0]
    clock.now += 3.0
    assert table.admit("r1")  # r1 is seen again
    assert not table.admit("r3")  # nobody idle long enough: refused
    clock.now += 3.0  # r2 silent 6 s, r1 3 s
    assert table.admit("r3")
    table.skill_of(table.episode("r3"))
    assert made[0].state.value == "finalized"  # r2's instance was released
    assert table.established("r1") is False


def test_a_shared_skill_is_one_instance_and_a_lone_unshareable_one_serves_one_client():
    shared = ChunkSkill(["a"])
    table = EpisodeTable(shared, factory=None, limits=ServeLimits(max_clients=3))
    assert all(table.admit(c) for c in ("a", "b", "c"))
    assert table.skill_of(table.episode("b")) is shared
    lone = ChunkSkill(["a"], latch=True)
    table = EpisodeTable(lone, factory=None, limits=ServeLimits(max_clients=3))
    assert table.admit("a")
    assert not table.admit("b")


@pytest.mark.parametrize("pending", [1, 3])
def test_drain_hands_back_every_waiting_job_and_closes(pending):
    queue = FairQueue(max_pending=8)
    for i in range(pending):
        queue.put(_job(f"c{i}"))
    assert len(queue.drain()) == pending
    assert queue.take(4, 0.0, _never_active) == []
    assert not queue.put(_job("late")).accepted
