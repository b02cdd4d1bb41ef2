"""Sessions and requests: each outcome of a Zenoh request is one exception, and opening a session tunes nothing."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from openral_core import ROSUnavailable
from openral_remote import allocator
from openral_remote.config import ZenohConfig
from openral_remote.keys import segment
from openral_remote.session import NoReply, PeerError, Querier, RemoteTimeout, open_session, request

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def mallopt_calls(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[tuple[int, int]]]:
    """Every ``mallopt`` call the allocator makes, recorded instead of made (and the once-per-process memo reset)."""
    calls: list[tuple[int, int]] = []

    def record(param: int, value: int) -> int:
        calls.append((param, value))
        return 1

    monkeypatch.setattr(allocator, "_mallopt", lambda: record)
    allocator.keep_message_memory.cache_clear()
    yield calls
    allocator.keep_message_memory.cache_clear()


@pytest.fixture
def session() -> Iterator[Any]:
    opened = open_session(ZenohConfig())  # no endpoints, no scouting: this process only
    yield opened
    opened.close()


Handler = Callable[[Any], bool]
"""Answers a query, or not: returns whether it did (an answered query is finalised at once, as a server does)."""


@pytest.fixture
def serve(session: Any) -> Iterator[Callable[[str, Handler], None]]:
    """Declare a queryable on the session that runs ``handler`` for each query (unanswered ones dropped at the end)."""
    declared: list[Any] = []
    held: list[Any] = []
    lock = threading.Lock()

    def start(key: str, handler: Handler) -> None:
        def on_query(query: Any) -> None:
            if handler(query):
                query.drop()
                return
            with lock:
                held.append(query)

        declared.append(session.declare_queryable(key, on_query, complete=True))

    yield start
    for queryable in declared:
        queryable.undeclare()
    for query in held:
        query.drop()


def test_opening_a_session_leaves_the_process_allocator_alone(mallopt_calls: list[tuple[int, int]]) -> None:
    open_session(ZenohConfig()).close()
    assert mallopt_calls == []


def test_keeping_message_memory_is_an_explicit_call_made_once_per_process(
    mallopt_calls: list[tuple[int, int]],
) -> None:
    assert allocator.keep_message_memory()
    assert allocator.keep_message_memory()
    assert mallopt_calls == [(-3, allocator.MMAP_THRESHOLD_BYTES), (-1, allocator.TRIM_THRESHOLD_BYTES)]


def test_without_glibc_nothing_is_tuned(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(allocator, "_mallopt", lambda: None)
    allocator.keep_message_memory.cache_clear()
    try:
        assert not allocator.keep_message_memory()
    finally:
        allocator.keep_message_memory.cache_clear()


def test_an_answer_is_its_payload_and_the_attachment_reaches_the_peer(session: Any, serve: Any) -> None:
    def echo(query: Any) -> bool:
        body = query.payload.to_bytes() + b"|" + query.attachment.to_bytes()
        query.reply(query.key_expr, body)
        return True

    serve("test/echo", echo)
    assert request(session, "test/echo", b"ping", timeout_s=5.0, attachment=b"trace") == b"ping|trace"
    querier = Querier(session, "test/echo", timeout_s=5.0)
    try:
        assert querier.request(b"pong", attachment=b"id") == b"pong|id"
    finally:
        querier.close()


def test_an_error_answer_is_a_peer_error_carrying_its_text_even_when_it_mentions_a_timeout(
    session: Any, serve: Any
) -> None:
    serve("test/fails", lambda query: query.reply_err(b"TimeoutError: the policy's own") or True)
    with pytest.raises(PeerError) as caught:
        request(session, "test/fails", timeout_s=5.0)
    assert caught.value.text == "TimeoutError: the policy's own"
    assert caught.value.key == "test/fails"
    assert not isinstance(caught.value, TimeoutError)  # the peer answered: not late


def test_no_answer_by_the_deadline_is_a_remote_timeout(session: Any, serve: Any) -> None:
    serve("test/hangs", lambda _query: False)  # held, never answered
    with pytest.raises(RemoteTimeout) as caught:
        request(session, "test/hangs", timeout_s=0.2)
    assert isinstance(caught.value, TimeoutError)  # what the chunk executor counts as late
    assert isinstance(caught.value, ROSUnavailable)
    querier = Querier(session, "test/hangs", timeout_s=0.2)
    try:
        with pytest.raises(RemoteTimeout):
            querier.request(b"")
    finally:
        querier.close()


def test_a_key_nobody_serves_gets_no_reply(session: Any) -> None:
    with pytest.raises(NoReply, match="nobody answered on test/nobody"):
        request(session, "test/nobody", timeout_s=2.0)


def test_a_key_segment_is_checked_in_one_place() -> None:
    assert segment("so101_follower-2.a", "robot") == "so101_follower-2.a"
    for bad in ("", "a/b", "a*", "$x", "a b"):
        with pytest.raises(Exception, match="cannot be part of a key expression"):
            segment(bad, "robot")
