"""W3C Trace Context propagation: into and out of carrier dicts and across processes by environment.

A ``traceparent`` is ``00-<32 hex trace id>-<16 hex span id>-<2 hex flags>``; ``tracestate``
carries vendor data. In a carrier dict the keys are lower case (``traceparent``,
``tracestate``); in an environment they are ``TRACEPARENT`` and ``TRACESTATE``, so a child
process started with :func:`inject_env` continues the parent's trace through
:func:`context_from_env` or :func:`parent_from_env`.

Only the API's ``TraceContextTextMapPropagator`` is used (not the globally configured
propagator), so the format is the same whatever ``OTEL_PROPAGATORS`` says.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, MutableMapping
from contextlib import contextmanager
from typing import Final

from opentelemetry import context, trace
from opentelemetry.context import Context
from opentelemetry.trace.propagation.tracecontext import TraceContextTextMapPropagator

from openral_observability.tracing import traceparent

ENV_TRACEPARENT: Final = "TRACEPARENT"
ENV_TRACESTATE: Final = "TRACESTATE"
_HEADER_TRACEPARENT: Final = "traceparent"
_HEADER_TRACESTATE: Final = "tracestate"

_PROPAGATOR: Final = TraceContextTextMapPropagator()


def current_traceparent() -> str | None:
    """The ``traceparent`` of the current span, or ``None`` when there is none (or tracing is off)."""
    return traceparent(trace.get_current_span())


def inject(carrier: MutableMapping[str, str], ctx: Context | None = None) -> MutableMapping[str, str]:
    """Write ``traceparent`` (and ``tracestate`` when not empty) of ``ctx`` (default: current) into ``carrier``.

    Nothing is written when the context holds no valid span.

    Returns:
        ``carrier`` itself.
    """
    _PROPAGATOR.inject(carrier, context=ctx)
    return carrier


def extract(carrier: Mapping[str, str], ctx: Context | None = None) -> Context:
    """A context whose parent span is the one named by ``carrier``'s ``traceparent``.

    Keys are matched case-insensitively. A missing or malformed ``traceparent`` gives
    ``ctx`` (default: an empty context) unchanged, so spans started under it become roots.
    """
    lowered = {key.lower(): value for key, value in carrier.items()}
    return _PROPAGATOR.extract(lowered, context=ctx)


def inject_env(env: MutableMapping[str, str], ctx: Context | None = None) -> MutableMapping[str, str]:
    """Set ``TRACEPARENT`` / ``TRACESTATE`` in ``env`` (for a child process) from ``ctx`` (default: current).

    With no valid span nothing is changed, so a variable inherited from this process's own
    parent passes through. A stale ``TRACESTATE`` is removed when a new ``TRACEPARENT`` is set.

    Returns:
        ``env`` itself, e.g. ``subprocess.run(cmd, env=inject_env(dict(os.environ)))``.
    """
    headers: dict[str, str] = {}
    _PROPAGATOR.inject(headers, context=ctx)
    parent = headers.get(_HEADER_TRACEPARENT)
    if parent is None:
        return env
    env[ENV_TRACEPARENT] = parent
    state = headers.get(_HEADER_TRACESTATE)
    if state:
        env[ENV_TRACESTATE] = state
    else:
        env.pop(ENV_TRACESTATE, None)
    return env


def context_from_env(env: Mapping[str, str] = os.environ) -> Context:
    """The context a parent process passed through ``TRACEPARENT`` / ``TRACESTATE``.

    Without a valid ``TRACEPARENT`` this is an empty context: spans started under it are roots.
    """
    headers: dict[str, str] = {}
    parent = env.get(ENV_TRACEPARENT)
    if parent:
        headers[_HEADER_TRACEPARENT] = parent
        state = env.get(ENV_TRACESTATE)
        if state:
            headers[_HEADER_TRACESTATE] = state
    return _PROPAGATOR.extract(headers, context=Context())


@contextmanager
def attached(ctx: Context) -> Iterator[Context]:
    """Make ``ctx`` current for the block: spans started inside are children of its span."""
    token = context.attach(ctx)
    try:
        yield ctx
    finally:
        context.detach(token)


@contextmanager
def parent_from_env(env: Mapping[str, str] = os.environ) -> Iterator[Context]:
    """Run the block under the parent named by ``TRACEPARENT`` (a no-op context when it is unset)."""
    with attached(context_from_env(env)) as ctx:
        yield ctx


__all__ = [
    "ENV_TRACEPARENT",
    "ENV_TRACESTATE",
    "attached",
    "context_from_env",
    "current_traceparent",
    "extract",
    "inject",
    "inject_env",
    "parent_from_env",
]
