"""``PolicyServer``: one policy served over Zenoh request/reply to many robots, for computers that cannot run it.

* ``<prefix>/infer``: a chunk request (:mod:`openral_remote.observation`: the observation, the
  earlier ones the policy reads, the executor's prefix, the robot's episode seed) in,
  ``{"chunk": rows}`` out. Requests are checked from their header before anything is decoded
  (:mod:`openral_remote.admission`), then wait in a fair queue (:mod:`openral_remote.fair_queue`):
  latest wins per client (a request overtaken by a newer one of the same client is answered
  ``superseded`` at once), clients are served in turn, and the queue is bounded. One worker
  thread infers; with ``max_batch`` above 1 and a skill that batches, concurrent clients'
  requests go through the policy as one batch. All of that is :class:`~openral_remote.service.PolicyService`,
  shared with the other transports; this module is Zenoh's.
* ``<prefix>/reset``: a new episode **of the sender** (``{"seed": n}``, the client's id in the
  attachment): each client has an episode of its own (:mod:`openral_remote.episodes`).
* ``<prefix>/meta``: :class:`openral_remote.meta.PolicyMeta`, answered on Zenoh's thread.
* ``<prefix>/alive``: a liveliness token, declared only once the policy is configured and warm,
  and withdrawn first on the way out; a SIGKILLed server's token is withdrawn by Zenoh itself.

The request's attachment carries the client's id, its sequence number and the W3C
``traceparent``: the server's inference span is a child of the robot's request span, one trace
across both machines, and records the batch it ran in. Replies are finalised (the ``Query``
dropped) as soon as they are answered, so a client never waits out its timeout on a request the
server is done with.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import structlog

from openral_core import ROSConfigError
from openral_remote.admission import ImagesRead, RequestBounds, ServeLimits, admit, check_seed
from openral_remote.codec import WireFormatError, decode, encode
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta
from openral_remote.observation import request_from_fields
from openral_remote.service import (
    ERROR_BUSY,
    ERROR_FULL,
    ERROR_SHUTTING_DOWN,
    ERROR_SUPERSEDED,
    MAX_CLIENT_ID,
    Answer,
    PolicyService,
    ServiceTransport,
)
from openral_remote.service import ServiceStats as ServerStats
from openral_remote.session import alive_behind, open_session
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

ALIVE_CHECK_TIMEOUT_S = 1.0
"""How long the start-up check waits for a live server's token (peers answer at once when connected)."""


def attachment_fields(attachment: Any) -> dict[str, Any]:
    """The JSON object in a request's attachment (empty when there is none or it is not one)."""
    if attachment is None:
        return {}
    try:
        value = json.loads(attachment.to_bytes())
    except (ValueError, UnicodeDecodeError):
        return {}
    return value if isinstance(value, dict) else {}


class PolicyServer(ServiceTransport):
    """Serves ``skill`` on the keys of ``keys`` until closed (a context manager).

    Args:
        skill: The policy, unconfigured: the server configures, activates and shuts it down.
        keys: Where it is served.
        zenoh: The session's settings (listen endpoints for the robots to connect to).
        meta: What the policy is (published on the ``meta`` key).
        limits: Batching, clients, queue and request limits.
        factory: Makes another unconfigured instance of the skill, for each further client of a
            skill that cannot be shared between episodes; without it such a skill serves one
            client at a time.
    """

    def __init__(
        self,
        skill: RSkillBase,
        *,
        keys: PolicyKeys,
        zenoh: ZenohConfig,
        meta: PolicyMeta,
        limits: ServeLimits | None = None,
        factory: Callable[[], RSkillBase] | None = None,
    ) -> None:
        self.skill = skill
        self.keys = keys
        self.zenoh = zenoh
        self.limits = limits or ServeLimits()
        self.service = PolicyService(skill, meta=meta, limits=self.limits, factory=factory, name=keys.infer)
        self._meta_bytes = meta.to_bytes()
        self._images = ImagesRead.of(meta.observation)
        self._bounds = RequestBounds(
            history=meta.observation_steps - 1, prefix_rows=meta.chunk_size, action_dims=len(meta.action_names)
        )
        self._session: Any = None
        self._declared: list[Any] = []
        self._token: Any = None

    def start(self) -> None:
        """Warm the policy up, declare the keys, then (last) the liveliness token; rolled back on failure.

        Raises:
            ROSConfigError: Another server already holds the key's liveliness token (checked before
                the warm-up and again just before declaring): two servers would answer one robot.
        """
        try:
            self._session = open_session(self.zenoh)
            self._refuse_if_served()
            self.service.start()
            self._meta_bytes = self.service.meta.to_bytes()
            self._refuse_if_served()
            self._declared = [
                self._session.declare_queryable(self.keys.meta, self._on_meta, complete=True),
                self._session.declare_queryable(self.keys.infer, self._on_infer, complete=True),
                self._session.declare_queryable(self.keys.reset, self._on_reset, complete=True),
            ]
            self._token = self._session.liveliness().declare_token(self.keys.alive)
        except BaseException:
            self.close()
            raise
        _log.info(
            "serving",
            key=self.keys.prefix,
            listen=self.zenoh.listen,
            model_hash=self.meta.model_hash[:12],
            max_batch=self.service.batch_limit,
        )

    def close(self) -> None:
        """Withdraw the token first (robots fall back at once), answer what is queued, stop. Idempotent."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        self.service.close()
        for declared in self._declared:
            declared.undeclare()
        self._declared = []
        if self._session is not None:
            self._session.close()
            self._session = None

    def _refuse_if_served(self) -> None:
        """Raise when a server linked to this session, or behind an endpoint it dials, declares the key's token."""
        replies = self._session.liveliness().get(self.keys.alive, timeout=ALIVE_CHECK_TIMEOUT_S)
        if any(reply.ok is not None for reply in replies) or alive_behind(
            self.zenoh, self.keys.alive, timeout_s=ALIVE_CHECK_TIMEOUT_S
        ):
            raise ROSConfigError(
                f"{self.keys.prefix} is already served: another policy server holds its liveliness token "
                f"{self.keys.alive}",
                hint="stop that server first, or serve this policy under another name (--name)",
            )

    # -- Zenoh's threads -------------------------------------------------------------------

    def _on_meta(self, query: Any) -> None:
        query.reply(self.keys.meta, self._meta_bytes)
        query.drop()

    def _on_reset(self, query: Any) -> None:
        client = _client_id(attachment_fields(query.attachment))
        try:
            request = json.loads(_payload(query) or b"{}")
            seed = check_seed(request.get("seed") if isinstance(request, dict) else None)
        except (ValueError, WireFormatError) as exc:
            self.service.stats.errors += 1
            _reply_error(query, f"reset failed: {exc}")
            return

        def done() -> None:
            query.reply(self.keys.reset, b"{}")
            query.drop()

        self.service.reset(client, seed, done=done, error=lambda text: _reply_error(query, text))

    def _on_infer(self, query: Any) -> None:
        attachment = attachment_fields(query.attachment)
        payload = _payload(query)
        try:
            admit(payload, limits=self.limits, images=self._images, bounds=self._bounds)
        except WireFormatError as exc:
            self.service.refuse(lambda text: _reply_error(query, text), f"refused: {exc}")
            return
        dims = len(self.meta.action_names)

        def decoded() -> ChunkRequest:
            return request_from_fields(decode(payload), action_dims=dims)

        def answer(answer: Answer) -> int:
            reply = encode(
                {
                    "chunk": answer.rows,
                    "infer_ms": answer.infer_ms,
                    "queue_ms": answer.queue_ms,
                    "model_hash": self.meta.model_hash,
                }
            )
            query.reply(self.keys.infer, reply)
            query.drop()
            return len(reply)

        self.service.infer(
            _client_id(attachment),
            decoded,
            answer=answer,
            error=lambda text: _reply_error(query, text),
            trace={key: str(attachment[key]) for key in ("traceparent", "tracestate") if key in attachment},
            request_bytes=len(payload),
        )


def _client_id(attachment: dict[str, Any]) -> str:
    """The client's id from its attachment, cut to ``MAX_CLIENT_ID`` characters (a peer chooses it freely)."""
    return str(attachment.get("client", ""))[:MAX_CLIENT_ID]


def _payload(query: Any) -> bytes:
    payload = query.payload
    return b"" if payload is None else bytes(payload.to_bytes())


def _reply_error(query: Any, text: str) -> None:
    try:
        query.reply_err(text.encode("utf-8"))
    finally:
        query.drop()


__all__ = [
    "ERROR_BUSY",
    "ERROR_FULL",
    "ERROR_SHUTTING_DOWN",
    "ERROR_SUPERSEDED",
    "PolicyServer",
    "ServerStats",
    "attachment_fields",
]
