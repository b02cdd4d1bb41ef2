"""The tick sampler: trace a ratio of runner ticks, each tick whole, under a kept root."""

from __future__ import annotations

from typing import Any

from opentelemetry import trace

from openral_core import ROSDependencyMissing
from openral_observability.semconv import SPAN_TICK
from openral_observability.telemetry_config import OTEL_EXTRA


def tick_sampler(ratio: float) -> Any:
    """A sampler that traces ``ratio`` of the ticks, each tick whole, independently of its parent.

    * ``rskill.tick`` spans: every ``1/ratio``-th tick is recorded (a deterministic credit
      counter, so ``0.1`` traces exactly one tick in ten), whether or not the enclosing span
      (``cli.command``) is, and whatever the trace id: all ticks of one deployment share the
      ``cli.command`` trace, so a trace-id ratio would keep all of them or none.
    * Any other span with a parent follows the parent: a traced tick is traced with all its
      phase spans, an untraced tick costs only non-recording spans.
    * Other root spans (``cli.command``) are recorded unless ``ratio`` is 0, so traced ticks
      always have their parent.

    A ratio of 1 records everything, like the SDK's default, with a cheaper decision per span.

    Raises:
        ROSDependencyMissing: The ``otel`` extra is not installed.
    """
    try:
        from opentelemetry.sdk.trace.sampling import Decision, Sampler, SamplingResult  # noqa: PLC0415
    except ImportError as exc:
        raise ROSDependencyMissing(exc.name or "opentelemetry.sdk", extra=OTEL_EXTRA, needed_for="sampling") from exc

    record = SamplingResult(Decision.RECORD_AND_SAMPLE)
    drop = SamplingResult(Decision.DROP)

    class TickSampler(Sampler):
        def __init__(self) -> None:
            self._credit = 1.0 - ratio if ratio > 0.0 else 0.0  # the first tick is traced unless ratio is 0

        def should_sample(  # noqa: PLR0917  (the SDK's signature)
            self,
            parent_context: Any,
            trace_id: int,
            name: str,
            kind: Any = None,
            attributes: Any = None,
            links: Any = None,
            trace_state: Any = None,
        ) -> Any:
            parent = trace.get_current_span(parent_context).get_span_context()
            if name == SPAN_TICK:
                self._credit += ratio
                if self._credit >= 1.0:
                    self._credit -= 1.0
                    sampled = True
                else:
                    sampled = False
            elif parent.is_valid:
                sampled = parent.trace_flags.sampled
            else:
                sampled = ratio > 0.0
            state = parent.trace_state if parent.is_valid else None
            if not sampled:
                return SamplingResult(Decision.DROP, None, state) if state else drop
            if not state and not attributes:
                return record
            # The SDK takes the span's start attributes from the sampling result.
            return SamplingResult(Decision.RECORD_AND_SAMPLE, attributes, state)

        def get_description(self) -> str:
            return f"OpenRALTickSampler{{{ratio}}}"

    return TickSampler()
