"""The tick sampler: a ratio of ticks traced whole, under a root that is always kept."""

from __future__ import annotations

from typing import Any

from openral_observability import semconv
from openral_observability.sampling import tick_sampler


def _sampled_run(ratio: float, ticks: int) -> list[Any]:
    """Spans recorded for ``ticks`` ticks (each with one phase child) under a ``cli.command`` root."""
    from opentelemetry.sdk.trace import TracerProvider  # noqa: PLC0415
    from opentelemetry.sdk.trace.export import SimpleSpanProcessor  # noqa: PLC0415
    from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter  # noqa: PLC0415

    exporter = InMemorySpanExporter()
    provider = TracerProvider(sampler=tick_sampler(ratio))
    provider.add_span_processor(SimpleSpanProcessor(exporter))
    tr = provider.get_tracer("test")
    with tr.start_as_current_span(semconv.SPAN_CLI_COMMAND, attributes={semconv.ATTR_CLI_COMMAND: "deploy"}):
        for idx in range(ticks):
            with tr.start_as_current_span(semconv.SPAN_TICK, attributes={semconv.ATTR_TICK_IDX: idx}):
                tr.start_span(semconv.SPAN_HAL_SEND_ACTION).end()
    provider.shutdown()
    return list(exporter.get_finished_spans())


def test_tick_sampler_traces_the_ratio_of_ticks_whole_under_the_kept_root() -> None:
    spans = _sampled_run(0.25, 8)
    (root,) = [s for s in spans if s.name == semconv.SPAN_CLI_COMMAND]
    assert root.attributes[semconv.ATTR_CLI_COMMAND] == "deploy"  # start attributes survive sampling
    ticks = [s for s in spans if s.name == semconv.SPAN_TICK]
    assert [t.attributes[semconv.ATTR_TICK_IDX] for t in ticks] == [0, 4]
    assert all(t.parent.span_id == root.context.span_id for t in ticks)
    children = [s for s in spans if s.name == semconv.SPAN_HAL_SEND_ACTION]
    assert sorted(c.parent.span_id for c in children) == sorted(t.context.span_id for t in ticks)


def test_tick_sampler_at_one_traces_everything_and_at_zero_nothing() -> None:
    assert len(_sampled_run(1.0, 5)) == 1 + 5 * 2
    assert _sampled_run(0.0, 5) == []
