"""Zenoh sessions from a :class:`~openral_remote.config.ZenohConfig`, and requests with a deadline.

Zenoh's errors are translated here, once (as httpx maps its transport's exceptions). A request
has one answer, or fails with one of three :class:`~openral_core.errors.ROSUnavailable`:

* :class:`RemoteTimeout` (also a ``TimeoutError``): no answer before the deadline. Zenoh reports
  it as a reply error whose payload is the text ``Timeout``;
* :class:`PeerError`: the peer answered with an error (its text in :attr:`PeerError.text`);
* :class:`NoReply`: nobody answered: nothing serves the key.

An answer carries who gave it (:attr:`Answer.replier`, the replying session's Zenoh id), so a
client can act only on the peer it trusts. A session with a ``tls`` block has its files checked
(:func:`openral_remote.tls.check_tls`) before Zenoh sees them.

Opening a session changes nothing else in the process (allocator tuning is
:func:`openral_remote.allocator.keep_message_memory`, called by the entry points that want it).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any, NamedTuple

from openral_core import ROSConfigError, ROSDependencyMissing, ROSRuntimeError, ROSUnavailable
from openral_remote.config import ZenohConfig
from openral_remote.tls import check_tls

try:
    import zenoh
except ImportError as exc:
    raise ROSDependencyMissing("zenoh", extra="remote", needed_for="remote inference over Zenoh") from exc

_ZENOH_TIMEOUT = "timeout"
"""What Zenoh's own reply error says at a query's deadline (compared ignoring case and surrounding spaces)."""


class RemoteTimeout(ROSUnavailable, TimeoutError):
    """The peer did not answer before the request's deadline."""


class PeerError(ROSUnavailable):
    """The peer answered the request with an error.

    Attributes:
        key: The key asked.
        text: What the peer said (decoded as UTF-8, undecodable bytes replaced).
    """

    def __init__(self, key: str, text: str) -> None:
        super().__init__(f"{key}: the peer answered with an error: {text}")
        self.key = key
        self.text = text


class NoReply(ROSUnavailable):
    """Nobody answered the request: nothing serves the key (or what did is gone)."""


class Answer(NamedTuple):
    """A request's answer and who gave it.

    Attributes:
        payload: The reply's bytes.
        replier: The Zenoh id (hex) of the session that replied; ``None`` if Zenoh did not say.
    """

    payload: bytes
    replier: str | None


def zenoh_config(config: ZenohConfig) -> Any:
    """The ``zenoh.Config`` of ``config`` (its TLS files checked first).

    Raises:
        ROSConfigError: A TLS file is wrong (naming it), or Zenoh refused a setting.
    """
    if config.tls is not None:
        check_tls(config.tls)
    settings = zenoh.Config()
    for path, value in config.settings().items():
        try:
            settings.insert_json5(path, json.dumps(value))
        except Exception as exc:  # zenoh raises its own ZError for a bad value
            raise ROSConfigError(f"zenoh refused {path}={value!r}: {exc}", field="zenoh") from exc
    return settings


def open_session(config: ZenohConfig) -> Any:
    """An open Zenoh session.

    Raises:
        ROSConfigError: Zenoh refused the settings, or cannot listen on an endpoint (in use, not local).
        ROSRuntimeError: The session could not be opened for another reason.
    """
    settings = zenoh_config(config)
    try:
        return zenoh.open(settings)
    except Exception as exc:
        text = str(exc)
        if config.listen and ("listen" in text.lower() or "bind" in text.lower() or "address" in text.lower()):
            raise ROSConfigError(
                f"cannot listen on {config.listen}: {text}", field="listen", hint="pick a free port or a local address"
            ) from exc
        raise ROSRuntimeError(f"cannot open a Zenoh session ({config.mode}, connect {config.connect}): {text}") from exc


def alive_behind(config: ZenohConfig, key: str, *, timeout_s: float) -> bool:
    """Whether a liveliness token on ``key`` is live at, or behind, any endpoint ``config`` connects to.

    A peer session hears the tokens of the peers it links to directly. Another peer that also
    dials the router or peer at ``config``'s endpoint is not one of them until gossip links the
    two, if ever (neither may listen). A client session asks the router or peer it dials, which
    answers for everything linked to it, so each endpoint is asked through one. An endpoint that
    cannot be reached hides nothing there is to see. The asking session declares nothing and
    only hears replies, so it takes no ``allow`` list (which would silence the peers it asks).
    """
    for endpoint in config.connect:
        asking = config.model_copy(
            update={"mode": "client", "connect": [endpoint], "listen": [], "id": None, "allow": []}
        )
        try:
            session = open_session(asking)
        except ROSRuntimeError:
            continue
        try:
            if any(reply.ok is not None for reply in session.liveliness().get(key, timeout=timeout_s)):
                return True
        finally:
            session.close()
    return False


def request(
    session: Any, key: str, payload: bytes | None = None, *, timeout_s: float, attachment: bytes | None = None
) -> bytes:
    """The payload of :func:`ask`."""
    return ask(session, key, payload, timeout_s=timeout_s, attachment=attachment).payload


def ask(
    session: Any, key: str, payload: bytes | None = None, *, timeout_s: float, attachment: bytes | None = None
) -> Answer:
    """Ask ``key`` once and return the first answer, with who gave it.

    Args:
        session: An open Zenoh session.
        key: The key expression asked (a queryable's).
        payload: The request's body, if any.
        timeout_s: The deadline, from now.
        attachment: Bytes sent beside the payload (trace context, a client's id).

    Raises:
        RemoteTimeout: No answer before the deadline.
        PeerError: The peer answered with an error.
        NoReply: Nobody answered.
    """
    return first_answer(session.get(key, payload=payload, attachment=attachment, timeout=timeout_s), key)


class Querier:
    """Requests to one key with one deadline, over a Zenoh querier (the key is resolved once, not per request).

    Args:
        session: An open Zenoh session.
        key: The key expression asked.
        timeout_s: Each request's deadline.
    """

    def __init__(self, session: Any, key: str, *, timeout_s: float) -> None:
        self.key = key
        self._querier: Any = session.declare_querier(key, timeout=timeout_s)

    def request(self, payload: Any = None, *, attachment: bytes | None = None) -> bytes:
        """The payload of :meth:`ask`."""
        return self.ask(payload, attachment=attachment).payload

    def ask(self, payload: Any = None, *, attachment: bytes | None = None) -> Answer:
        """Ask once; ``payload`` may be ``bytes`` or a ``zenoh.ZBytes`` (shared memory). As :func:`ask`."""
        return first_answer(self._querier.get(payload=payload, attachment=attachment), self.key)

    def close(self) -> None:
        """Undeclare the querier."""
        self._querier.undeclare()


def answer(replies: Iterable[Any], key: str) -> bytes:
    """The payload of :func:`first_answer`."""
    return first_answer(replies, key).payload


def first_answer(replies: Iterable[Any], key: str) -> Answer:
    """The first of ``replies`` (what a Zenoh ``get`` yields) and its replier, or its error translated.

    Raises:
        RemoteTimeout: Zenoh's deadline passed first.
        PeerError: The peer answered with an error.
        NoReply: There was no reply.
    """
    for reply in replies:
        ok = reply.ok
        if ok is not None:
            return Answer(bytes(ok.payload.to_bytes()), _replier(reply))
        text = reply.err.payload.to_bytes().decode("utf-8", "replace")
        if text.strip().lower() == _ZENOH_TIMEOUT:
            raise RemoteTimeout(f"{key}: no answer before the deadline")
        raise PeerError(key, text)
    raise NoReply(f"nobody answered on {key}")


def _replier(reply: Any) -> str | None:
    replier = reply.replier_id
    return None if replier is None else str(replier.zid)


__all__ = [
    "Answer",
    "NoReply",
    "PeerError",
    "Querier",
    "RemoteTimeout",
    "alive_behind",
    "answer",
    "ask",
    "first_answer",
    "open_session",
    "request",
    "zenoh_config",
]
