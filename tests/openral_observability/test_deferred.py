"""Deferred spans: recorded as data on the tick thread, with a context made on first use."""

from __future__ import annotations

from opentelemetry import trace

from openral_observability.deferred import DeferredSpan


def test_deferred_span_keeps_shared_attributes_and_freezes_at_end() -> None:
    shared = {"k": "v"}
    sink: list[DeferredSpan] = []
    span = DeferredSpan(sink, "phase", None, shared, span_context=trace.SpanContext(1, 2, is_remote=False))
    span.set_attribute("extra", 1)
    span.add_event("e", {"a": 1})
    assert span.is_recording()
    span.end()
    span.end()  # a second end is ignored, as the SDK does
    span.set_attribute("late", 2)
    assert shared == {"k": "v"}
    assert span.attributes == {"k": "v", "extra": 1}
    assert sink == [span]
    assert not span.is_recording()
    assert span.start_ns <= span.events[0][2] <= span.end_ns  # type: ignore[index]


def test_a_phase_context_is_made_on_first_use_in_its_parents_trace() -> None:
    parent = trace.SpanContext(0xABC, 0x1, is_remote=False, trace_flags=trace.TraceFlags(1))
    ids = iter([0x10, 0x11])
    span = DeferredSpan([], "phase", parent, new_id=lambda: next(ids))
    first = span.get_span_context()
    assert span.get_span_context() is first  # fixed once made
    assert (first.trace_id, first.span_id, first.trace_flags) == (0xABC, 0x10, parent.trace_flags)
