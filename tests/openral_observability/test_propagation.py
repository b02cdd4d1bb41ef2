"""W3C Trace Context across carriers and processes."""

from __future__ import annotations

import os
import subprocess
import sys
from typing import Any

from opentelemetry import trace
from opentelemetry.trace import NonRecordingSpan, SpanContext, TraceFlags, TraceState

from openral_observability import current_traceparent, traceparent
from openral_observability.propagation import (
    ENV_TRACEPARENT,
    ENV_TRACESTATE,
    attached,
    context_from_env,
    extract,
    inject,
    inject_env,
    parent_from_env,
)

TRACE_ID = 0x0AF7651916CD43DD8448EB211C80319C
SPAN_ID = 0xB7AD6B7169203331
PARENT = f"00-{TRACE_ID:032x}-{SPAN_ID:016x}-01"


def _remote(state: TraceState | None = None) -> Any:
    ctx = SpanContext(TRACE_ID, SPAN_ID, is_remote=False, trace_flags=TraceFlags(1), trace_state=state)
    return trace.set_span_in_context(NonRecordingSpan(ctx))


def _parent_of(ctx: Any) -> SpanContext:
    return trace.get_current_span(ctx).get_span_context()


def test_current_traceparent_is_none_outside_a_span(telemetry: Any) -> None:
    assert current_traceparent() is None


def test_current_traceparent_names_the_current_span(telemetry: Any) -> None:
    with trace.get_tracer("t").start_as_current_span("work") as span:
        assert current_traceparent() == traceparent(span)
        ctx = span.get_span_context()
        assert current_traceparent() == f"00-{ctx.trace_id:032x}-{ctx.span_id:016x}-{int(ctx.trace_flags):02x}"


def test_inject_extract_round_trip_continues_the_trace(telemetry: Any) -> None:
    tracer = trace.get_tracer("t")
    with tracer.start_as_current_span("sender") as sender:
        carrier = inject({})
    assert set(carrier) == {"traceparent"}
    ctx = extract(carrier)
    parent = _parent_of(ctx)
    assert parent.is_remote
    assert (parent.trace_id, parent.span_id) == (sender.get_span_context().trace_id, sender.get_span_context().span_id)
    with attached(ctx), tracer.start_as_current_span("receiver"):
        pass
    (receiver,) = telemetry.spans("receiver")
    assert receiver.parent.span_id == sender.get_span_context().span_id
    assert receiver.context.trace_id == sender.get_span_context().trace_id


def test_tracestate_travels_and_keys_match_in_any_case() -> None:
    carrier = inject({}, _remote(TraceState([("vendor", "abc")])))
    assert carrier == {"traceparent": PARENT, "tracestate": "vendor=abc"}
    ctx = extract({"TraceParent": PARENT, "TRACESTATE": "vendor=abc"})
    parent = _parent_of(ctx)
    assert parent.trace_id == TRACE_ID
    assert parent.trace_state.get("vendor") == "abc"


def test_nothing_is_injected_without_a_span_and_garbage_is_not_extracted() -> None:
    assert inject({}) == {}
    assert not _parent_of(extract({"traceparent": "00-zz-yy-01"})).is_valid
    assert not _parent_of(extract({})).is_valid


def test_env_round_trip() -> None:
    env = inject_env({"PATH": "/bin", ENV_TRACESTATE: "stale=1"}, _remote())
    assert env == {"PATH": "/bin", ENV_TRACEPARENT: PARENT}
    env = inject_env({}, _remote(TraceState([("k", "v")])))
    assert env == {ENV_TRACEPARENT: PARENT, ENV_TRACESTATE: "k=v"}
    parent = _parent_of(context_from_env(env))
    assert (parent.trace_id, parent.span_id, parent.is_remote) == (TRACE_ID, SPAN_ID, True)
    assert parent.trace_state.get("k") == "v"


def test_inject_env_without_a_span_leaves_inherited_variables() -> None:
    env = {ENV_TRACEPARENT: PARENT}
    assert inject_env(env) == {ENV_TRACEPARENT: PARENT}
    assert not _parent_of(context_from_env({})).is_valid
    assert not _parent_of(context_from_env({ENV_TRACEPARENT: "nonsense"})).is_valid


def test_parent_from_env_makes_new_spans_children(telemetry: Any) -> None:
    with parent_from_env({ENV_TRACEPARENT: PARENT}), trace.get_tracer("t").start_as_current_span("child"):
        pass
    (child,) = telemetry.spans("child")
    assert child.parent.span_id == SPAN_ID
    assert child.context.trace_id == TRACE_ID
    # Outside the block the previous (empty) context is back.
    assert not trace.get_current_span().get_span_context().is_valid


def test_a_child_process_continues_the_trace(telemetry: Any) -> None:
    code = (
        "from opentelemetry import trace\n"
        "from openral_observability.propagation import context_from_env\n"
        "c = trace.get_current_span(context_from_env()).get_span_context()\n"
        "print(f'{c.trace_id:032x} {c.span_id:016x}')\n"
    )
    with trace.get_tracer("t").start_as_current_span("parent") as parent:
        env = inject_env(dict(os.environ))
        proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    ctx = parent.get_span_context()
    assert proc.stdout.split() == [f"{ctx.trace_id:032x}", f"{ctx.span_id:016x}"]
