"""The SDK tracer's pipeline, used directly: span ids, the sampling decision, and the span processors.

A span started through the SDK's ``Tracer.start_span`` costs the calling thread 10–30 µs: the
sampler, span limits, locks and the processors' ``on_start``. A tick of a runner makes half a
dozen spans, which on a 500 Hz tick is more than the whole telemetry budget. Instead, the tick
thread takes ids from the tracer's own id generator and a decision from its own sampler (one per
tick), records its spans as data (:class:`~openral_observability.deferred.DeferredSpan`), and a
worker thread hands each finished span to the tracer's span processors as the SDK's own read-only
span type, as ``Span.end()`` would. Exporters, batching and in-memory test exporters work
unchanged.

Only an SDK tracer has these parts (public attributes of ``opentelemetry.sdk.trace.Tracer``);
:meth:`SdkSpanPipeline.of` says ``None`` for any other tracer, and the caller falls back to the
API's own spans. The SDK module is imported only once such a tracer has been found, so only
``setup()`` or a test can have caused the import.

Differences from spans the SDK starts itself, by design: span processors see deferred spans only
at ``on_end`` (``on_start`` needs a live, mutable span); child spans of a tick follow the tick's
sampling decision (what the SDK's parent-based samplers do) rather than asking the sampler again;
and span limits are applied only when a span exceeds them.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Mapping, Sequence
from functools import lru_cache
from typing import Any, Final, NamedTuple

from opentelemetry.trace import SpanContext, SpanKind, Status, StatusCode, TraceFlags, TraceState
from opentelemetry.util.types import Attributes

RANDOM_TRACE_ID_FLAG: Final = int(getattr(TraceFlags, "RANDOM_TRACE_ID", 0))
"""W3C trace-context level 2 "random trace id" flag (0 where the API predates it)."""
_STATUS: Final = {code.value: code for code in StatusCode}
_UNSET: Final = Status(StatusCode.UNSET)
_MAX_ATTRIBUTES: Final = 128  # the SDK's default span limits
_MAX_EVENTS: Final = 128


class SpanRecord(NamedTuple):
    """One finished span as plain, picklable data (it may be exported by another process)."""

    name: str
    trace_id: int
    span_id: int
    trace_flags: int
    trace_state: str | None
    """The ``tracestate`` header value, ``None`` when empty."""
    parent_span_id: int | None
    parent_is_remote: bool
    start_ns: int
    end_ns: int
    attributes: Mapping[str, Any] | None
    events: Sequence[tuple[str, Attributes, int]]
    """``(name, attributes, timestamp in ns since the epoch)``."""
    status_code: int
    status_description: str | None


def exception_attributes(exception: BaseException, attributes: Attributes = None) -> dict[str, Any]:
    """The attributes of an ``exception`` event, as the SDK's ``Span.record_exception`` writes them."""
    cls = type(exception)
    module = cls.__module__
    out: dict[str, Any] = {
        "exception.type": f"{module}.{cls.__qualname__}" if module and module != "builtins" else cls.__qualname__,
        "exception.message": str(exception),
        "exception.stacktrace": "".join(traceback.format_exception(exception)),
        "exception.escaped": "False",
    }
    if attributes:
        out.update(attributes)
    return out


@lru_cache(maxsize=64)
def _trace_state(header: str) -> TraceState:
    return TraceState.from_header([header])


SDK_RELEASES_READ: Final = ("1.45",)
"""``opentelemetry-sdk`` releases (major.minor) whose tracer attributes and ``ReadableSpan`` constructor
this module was checked against (the lock pins one; a test fails when it moves past these)."""


@lru_cache(maxsize=1)
def sdk_release_supported() -> bool:
    """Whether the installed ``opentelemetry-sdk`` is one of :data:`SDK_RELEASES_READ` (warns once if not)."""
    from importlib import metadata  # noqa: PLC0415

    try:
        release = ".".join(metadata.version("opentelemetry-sdk").split(".")[:2])
    except metadata.PackageNotFoundError:
        return False
    if release in SDK_RELEASES_READ:
        return True
    import warnings  # noqa: PLC0415

    warnings.warn(
        f"opentelemetry-sdk {release} is newer or older than the releases openral's deferred tick spans were "
        f"checked against ({', '.join(SDK_RELEASES_READ)}): recording ticks with live SDK spans instead",
        RuntimeWarning,
        stacklevel=2,
    )
    return False


class SdkSpanPipeline:
    """An SDK tracer's id generator, sampler, resource, scope and span processors.

    Args:
        tracer: An ``opentelemetry.sdk.trace.Tracer`` (checked by :meth:`of`).
    """

    def __init__(self, tracer: Any) -> None:
        from opentelemetry.sdk.trace import Event, ReadableSpan  # noqa: PLC0415  (an SDK tracer exists)
        from opentelemetry.sdk.util.instrumentation import InstrumentationScope  # noqa: PLC0415

        self._event = Event
        self._readable = ReadableSpan
        self._processor = tracer.span_processor
        self._resource = tracer.resource
        info = tracer.instrumentation_info
        self._info = info
        self._scope = InstrumentationScope(info.name, info.version, info.schema_url)
        ids = tracer.id_generator
        self.sampler = tracer.sampler
        self.new_span_id: Callable[[], int] = ids.generate_span_id
        self.new_trace_id: Callable[[], int] = ids.generate_trace_id
        is_random = getattr(ids, "is_trace_id_random", None)
        self.random_trace_id_flag = RANDOM_TRACE_ID_FLAG if is_random is not None and is_random() else 0

    @classmethod
    def of(cls, tracer: Any) -> SdkSpanPipeline | None:
        """The pipeline of ``tracer`` if it is an SDK tracer of a release whose internals were checked.

        ``None`` for the API's no-op tracer, another implementation, or an SDK release outside
        :data:`SDK_RELEASES_READ` (then the caller records live API spans: slower, never wrong).
        """
        parts = ("sampler", "id_generator", "span_processor", "resource", "instrumentation_info")
        if not all(hasattr(tracer, part) for part in parts):
            return None
        if not sdk_release_supported():
            return None
        return cls(tracer)

    def end(self, record: SpanRecord) -> None:
        """Hand one finished span to the span processors, as the SDK's ``Span.end()`` does."""
        flags = TraceFlags(record.trace_flags)
        state = None if record.trace_state is None else _trace_state(record.trace_state)
        context = SpanContext(record.trace_id, record.span_id, is_remote=False, trace_flags=flags, trace_state=state)
        parent = None
        if record.parent_span_id is not None:
            parent = SpanContext(
                record.trace_id, record.parent_span_id, is_remote=record.parent_is_remote, trace_flags=flags
            )
        events: tuple[Any, ...] = ()
        if record.events:
            events = tuple(self._event(name, attrs, at) for name, attrs, at in record.events[-_MAX_EVENTS:])
        attributes = record.attributes
        if attributes is not None and len(attributes) > _MAX_ATTRIBUTES:
            from opentelemetry.attributes import BoundedAttributes  # noqa: PLC0415  (rare)

            attributes = BoundedAttributes(_MAX_ATTRIBUTES, attributes, immutable=True)
        status = _UNSET
        if record.status_code != StatusCode.UNSET.value:
            status = Status(_STATUS[record.status_code], record.status_description)
        self._processor.on_end(
            self._readable(
                name=record.name,
                context=context,
                parent=parent,
                resource=self._resource,
                attributes=attributes,
                events=events,
                kind=SpanKind.INTERNAL,
                instrumentation_info=self._info,
                status=status,
                start_time=record.start_ns,
                end_time=record.end_ns,
                instrumentation_scope=self._scope,
            )
        )
