"""Loopback: a policy server in a child process, a client here; killed, hung, superseded, swapped."""

import threading
import time

import numpy as np
import pytest

from openral_core import JointState, WorldState
from openral_remote.client import RemotePolicyClient, RemoteSuperseded, RemoteTimeout, ServerUnavailable
from openral_remote.testing import ChunkSkill, wait_for

pytestmark = pytest.mark.timeout(120)


def _world(q=(0.1, -0.2)) -> WorldState:
    return WorldState(stamp_ns=1, joint_state=JointState(names=["a0", "a1"], positions=list(q)))


def test_a_round_trip_returns_the_chunk_the_policy_computes(server, client):
    server("--chunk-size", "8", "--offset", "0.25")
    remote = client()
    assert remote.meta is not None
    assert remote.meta.chunk_size == 8
    world = _world()
    expected = ChunkSkill(["a0", "a1"], chunk_size=8, offset=0.25).rows(world)
    np.testing.assert_array_equal(remote.infer(world), expected)
    remote.reset(seed=7)  # answered once the server's worker ran it


def test_connect_without_a_server_says_how_to_start_one(keys, client_zenoh):
    remote = RemotePolicyClient(keys, client_zenoh)
    with pytest.raises(ServerUnavailable, match="openral serve"):
        remote.connect(timeout_s=0.3)


def test_a_killed_server_is_known_down_without_a_request_and_a_request_fails_fast(server, client):
    process = server()
    remote = client(deadline_ms=30_000)  # a request sent anyway could wait this long for a reply
    remote.infer(_world())
    process.kill()
    assert wait_for(lambda: not remote.available(), timeout_s=3.0)  # liveliness, not a failed request
    assert remote.changes == ["down"]
    started = time.perf_counter()
    with pytest.raises(ServerUnavailable, match="is down"):  # refused here, never sent
        remote.infer(_world())
    assert time.perf_counter() - started < 5.0


def test_a_hung_server_costs_the_deadline_and_is_counted_late(server, client):
    server("--delay-ms", "10000")
    remote = client(deadline_ms=200)
    started = time.perf_counter()
    with pytest.raises(RemoteTimeout) as caught:
        remote.infer(_world())
    elapsed = time.perf_counter() - started
    assert isinstance(caught.value, TimeoutError)  # what the executor counts as late
    assert 0.15 < elapsed < 5.0  # the deadline, not the 10 s inference
    assert remote.available()  # hung is not dead: the token is still there


class _HeldSkill(ChunkSkill):
    """Its inferences wait until ``release`` is set: one request stays under way as long as a test needs."""

    def __init__(self, action_names: list[str]) -> None:
        super().__init__(action_names)
        self.inferring = threading.Event()
        self.release = threading.Event()

    def _chunks_impl(self, requests):
        self.inferring.set()
        assert self.release.wait(60), "the test never released the inference"
        return super()._chunks_impl(requests)


def test_a_request_overtaken_by_a_newer_one_is_answered_at_once(keys, endpoint, client, monkeypatch):
    from openral_remote.config import ZenohConfig  # noqa: PLC0415
    from openral_remote.server import PolicyServer  # noqa: PLC0415
    from openral_remote.testing import chunk_meta  # noqa: PLC0415

    skill = _HeldSkill(["a0", "a1"])
    meta = chunk_meta(skill, rate_hz=10.0, model_hash="model-a")
    with PolicyServer(skill, keys=keys, zenoh=ZenohConfig(listen=[endpoint]), meta=meta) as running:
        queued: list[str] = []
        enqueue = running.service.infer

        def counted(client_id: str, *args: object, **kwargs: object) -> None:
            enqueue(client_id, *args, **kwargs)  # type: ignore[arg-type]
            queued.append(client_id)

        monkeypatch.setattr(running.service, "infer", counted)
        remote = client(deadline_ms=30_000)
        outcomes: dict[str, object] = {}

        def ask(name: str) -> None:
            try:
                outcomes[name] = remote.infer(_world())
            except Exception as exc:
                outcomes[name] = exc

        threads = {name: threading.Thread(target=ask, args=(name,)) for name in ("first", "second", "third")}
        try:
            threads["first"].start()
            assert skill.inferring.wait(20)  # the first is being inferred, held there
            threads["second"].start()
            assert wait_for(lambda: len(queued) == 2)  # the second waits behind it
            threads["third"].start()
            # Answered while the first is still held: not after the inference ahead of it.
            assert wait_for(lambda: "second" in outcomes)
            assert isinstance(outcomes["second"], RemoteSuperseded)
            assert "first" not in outcomes
            assert "third" not in outcomes
        finally:
            skill.release.set()
            for thread in threads.values():
                if thread.ident is not None:  # started
                    thread.join()
    assert isinstance(outcomes["first"], np.ndarray)
    assert isinstance(outcomes["third"], np.ndarray)


def test_a_server_back_with_another_model_is_refused(server, client):
    process = server("--model-hash", "model-a")
    remote = client()
    process.kill()
    assert wait_for(lambda: not remote.available(), timeout_s=3.0)
    server("--model-hash", "model-b")
    assert wait_for(lambda: remote.changes[-1:] == ["refused"], timeout_s=20.0)
    assert not remote.available()
    with pytest.raises(ServerUnavailable):
        remote.infer(_world())


def test_a_server_back_with_the_same_model_is_taken_back(server, client):
    process = server("--model-hash", "model-a")
    remote = client()
    process.kill()
    assert wait_for(lambda: not remote.available(), timeout_s=3.0)
    server("--model-hash", "model-a")
    assert wait_for(remote.available, timeout_s=20.0)
    assert remote.changes == ["down", "up"]
    assert remote.infer(_world()).shape == (10, 2)


def test_accepting_a_new_model_takes_it(server, client):
    process = server("--model-hash", "model-a")
    remote = client(on_model_change="accept")
    process.kill()
    assert wait_for(lambda: not remote.available(), timeout_s=3.0)
    server("--model-hash", "model-b", "--offset", "2.0")
    assert wait_for(remote.available, timeout_s=20.0)
    assert remote.meta is not None
    assert remote.meta.model_hash == "model-b"
    assert remote.infer(_world())[0, 0] == pytest.approx(0.1 + 2.0)


class _CountingSkill(ChunkSkill):
    """Counts its warm-ups: a refused server must not load its model."""

    configured = 0

    def _on_configure(self) -> None:
        type(self).configured += 1
        super()._on_configure()


def test_a_second_server_on_a_live_key_refuses_to_start_before_loading_its_model(server, client, keys, endpoint):
    from openral_core import ROSConfigError  # noqa: PLC0415
    from openral_remote.config import ZenohConfig  # noqa: PLC0415
    from openral_remote.server import PolicyServer  # noqa: PLC0415
    from openral_remote.testing import chunk_meta, free_endpoint  # noqa: PLC0415

    first = server()
    client()  # the first server is up: its token is live
    skill = _CountingSkill(["a0", "a1"])
    meta = chunk_meta(skill, rate_hz=10.0, model_hash="model-b")
    # A peer of the first server, listening for robots of its own: the robots would reach both.
    second_zenoh = ZenohConfig(connect=[endpoint], listen=[free_endpoint()])
    with pytest.raises(ROSConfigError, match="already served") as refused:
        PolicyServer(skill, keys=keys, zenoh=second_zenoh, meta=meta).start()
    assert keys.alive in str(refused.value)
    assert _CountingSkill.configured == 0
    # Once the first server is gone, the same key is free.
    first.stop()
    with PolicyServer(_CountingSkill(["a0", "a1"]), keys=keys, zenoh=second_zenoh, meta=meta) as replacement:
        assert replacement.meta.model_hash == "model-b"
    assert _CountingSkill.configured == 1
