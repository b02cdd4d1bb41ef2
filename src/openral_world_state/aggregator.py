"""``WorldStateAggregator``: the latest joint state and frames, turned into one ``WorldState`` per tick."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from opentelemetry import trace
from opentelemetry.util.types import Attributes

from openral_core import (
    ComponentDiagnostics,
    JointState,
    ROSConfigError,
    SensorFrame,
    SensorReaderConfig,
    WorldState,
)
from openral_observability import metrics, semconv
from openral_observability.deferred import TickTelemetry
from openral_observability.tracing import tracer

JOINT_STATE_COMPONENT = "joint_state"
"""Component name of the robot's joint state in ``WorldState.diagnostics``."""


@dataclass(slots=True)
class _Component:
    """One declared component, its limits and the health it had at the previous snapshot."""

    name: str
    max_age_ms: float
    required: bool
    attributes: Attributes
    stale_latched: bool = False
    error_latched: bool = False
    unhealthy: bool = False


class WorldStateAggregator:
    """Holds the freshest joint state and the latest frame of each declared sensor.

    Capture threads call :meth:`update_frame`, the tick thread calls :meth:`update_joint_state`
    and :meth:`snapshot`; all methods are thread-safe and hold one lock only long enough to
    swap or copy references, so a snapshot never waits on a capture and never copies pixels.

    Freshness is measured from each sample's *capture* stamp (``SensorFrame.stamp_ns``,
    ``JointState.stamp_ns``) to ``clock()``, never from when it arrived here: a sample is
    stale when it is missing, older than its ``max_age_ms``, or stamped further than
    ``max_age_ms`` in the future (a backend stamping on another clock is never "fresh forever").
    A component with an error set (:meth:`set_error`) is unhealthy until :meth:`clear_error` or,
    for a sensor, until its next frame arrives. A sensor whose reader judged its latest frame stale
    (:meth:`mark_stale`) is stale in the next snapshot whatever frame is held: the world state's
    diagnostics are the one verdict on every component.

    Telemetry, emitted inside the ``world_state.snapshot`` span, only on transitions:

    - ``openral.event.staleness_latched`` (component, age when known) the first snapshot a
      component is stale after having been fresh. Every component starts out fresh, so a
      sensor that has not delivered by the first snapshot latches once then.
    - ``openral.event.error_latched`` (component, message) the first snapshot that sees an
      error set; setting it again, or changing its text, emits nothing until it is cleared.
    - Recovery emits no event; the up-down counter ``openral.world_state.components_stale``
      goes +1 when a component becomes unhealthy (stale or in error) and -1 when it is healthy again.

    Every snapshot records each component's age on the ``openral.world_state.staleness_ms``
    histogram.

    Args:
        joint_max_age_ms: Largest joint-state age that counts as fresh.
        joint_required: Whether a stale joint state makes the tick's action withheld.
        sensors: The deployment's sensors; ``sensor_id``, ``max_age_ms`` and ``required`` are used.
        clock: Nanosecond clock shared with the capture stamps (``time.monotonic_ns``).

    Raises:
        ROSConfigError: A sensor id is repeated or is ``joint_state``, or ``joint_max_age_ms`` is not positive.
    """

    def __init__(
        self,
        *,
        joint_max_age_ms: float = 100.0,
        joint_required: bool = True,
        sensors: Sequence[SensorReaderConfig] = (),
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not joint_max_age_ms > 0:
            raise ROSConfigError(
                f"must be above 0 ms, got {joint_max_age_ms}", field="joint_max_age_ms", hint="use e.g. 100"
            )
        components = [_component(JOINT_STATE_COMPONENT, joint_max_age_ms, joint_required)]
        for index, sensor in enumerate(sensors):
            if any(c.name == sensor.sensor_id for c in components):
                raise ROSConfigError(
                    f"sensor id '{sensor.sensor_id}' is already used by another component",
                    field=f"sensors[{index}].sensor_id",
                    hint=f"give each sensor its own id, other than '{JOINT_STATE_COMPONENT}'",
                )
            components.append(_component(sensor.sensor_id, sensor.max_age_ms, sensor.required))
        self._components: tuple[_Component, ...] = tuple(components)
        self._sensor_ids = frozenset(c.name for c in components[1:])
        self._has_sensors = bool(self._sensor_ids)
        self._clock = clock
        self._tracer = tracer()  # the API's proxy tracer follows a provider installed later
        self._lock = threading.Lock()
        self._snapshot_lock = threading.Lock()
        self._joint_state: JointState | None = None
        self._frames: dict[str, SensorFrame] = {}
        self._errors: dict[str, str] = {}
        self._marked_stale: dict[str, float | None] = {}

    def is_required(self, component: str) -> bool:
        """Whether a stale ``component`` withholds the tick's action."""
        for declared in self._components:
            if declared.name == component:
                return declared.required
        raise self._unknown(component, declared=list(self.components), what="component")

    @property
    def components(self) -> tuple[str, ...]:
        """Declared component names: ``joint_state`` first, then the sensors in declaration order."""
        return tuple(c.name for c in self._components)

    def update_joint_state(self, js: JointState) -> None:
        """Keep ``js`` as the current joint state unless the one held was captured later."""
        with self._lock:
            held = self._joint_state
            if held is None or js.stamp_ns >= held.stamp_ns:
                self._joint_state = js

    def update_frame(self, frame: SensorFrame) -> None:
        """Keep ``frame`` (the object itself) as its sensor's latest, unless the one held was captured later.

        Raises:
            ROSConfigError: ``frame.sensor_id`` is not a declared sensor.
        """
        sensor_id = frame.sensor_id
        if sensor_id not in self._sensor_ids:
            raise self._unknown(sensor_id, declared=sorted(self._sensor_ids), what="sensor")
        with self._lock:
            held = self._frames.get(sensor_id)
            if held is None or frame.stamp_ns >= held.stamp_ns:
                self._frames[sensor_id] = frame
            if self._errors:
                self._errors.pop(sensor_id, None)

    def mark_stale(self, sensor_id: str, age_ms: float | None = None) -> None:
        """Have the next snapshot report ``sensor_id`` stale (its reader said so), with ``age_ms`` when known.

        Raises:
            ROSConfigError: ``sensor_id`` is not a declared sensor.
        """
        if sensor_id not in self._sensor_ids:
            raise self._unknown(sensor_id, declared=sorted(self._sensor_ids), what="sensor")
        with self._lock:
            self._marked_stale[sensor_id] = age_ms

    def set_error(self, component: str, message: str) -> None:
        """Mark ``component`` unhealthy with ``message`` until :meth:`clear_error`.

        Raises:
            ROSConfigError: ``component`` is not declared.
        """
        self._check_component(component)
        with self._lock:
            self._errors[component] = message

    def clear_error(self, component: str) -> None:
        """Remove the error set on ``component``; a no-op when none is set.

        Raises:
            ROSConfigError: ``component`` is not declared.
        """
        self._check_component(component)
        with self._lock:
            self._errors.pop(component, None)

    def snapshot(self, *, task: str | None = None, telemetry: TickTelemetry | None = None) -> WorldState:
        """A ``WorldState`` of the latest samples with diagnostics for every declared component.

        ``image_frames`` holds the very frame objects passed to :meth:`update_frame` (no copy),
        only for sensors that delivered one; it is ``None`` when no sensors are declared.
        ``stamp_ns`` is ``clock()`` read after the samples were taken, so ages are never
        negative for samples stamped on the same clock.

        With ``telemetry`` (a runner's tick), the ``world_state.snapshot`` span and the staleness
        samples are recorded into it and exported off the calling thread; without it the span is
        started here, under the current span.
        """
        # The span is started without becoming current: nothing nests under it, and this is
        # several times cheaper than ``start_as_current_span`` on the tick path. Inside a trace
        # the sampler dropped (an unsampled tick) it could not be recorded: the enclosing
        # non-recording span stands in, saving the span id and sampler call.
        with self._snapshot_lock:
            span: Any
            if telemetry is not None:
                span = telemetry.start_span(semconv.SPAN_WORLD_STATE_SNAPSHOT)
            else:
                current = trace.get_current_span()
                if current.is_recording() or not current.get_span_context().is_valid:
                    span = self._tracer.start_span(semconv.SPAN_WORLD_STATE_SNAPSHOT)
                else:
                    span = current
            try:
                with self._lock:
                    joint_state = self._joint_state
                    frames = dict(self._frames)
                    errors = dict(self._errors) if self._errors else None
                    marked = self._marked_stale
                    if marked:
                        self._marked_stale = {}
                    now_ns = self._clock()
                diagnostics: dict[str, ComponentDiagnostics] = {}
                for component in self._components:
                    if component.name == JOINT_STATE_COMPONENT:
                        stamp_ns = None if joint_state is None else joint_state.stamp_ns
                    else:
                        frame = frames.get(component.name)
                        stamp_ns = None if frame is None else frame.stamp_ns
                    diagnostics[component.name] = self._diagnose(
                        component, stamp_ns, now_ns, errors, span, telemetry=telemetry, marked=marked
                    )
                # Plain (validated) construction: pydantic-core checks these flat fields faster than
                # ``model_construct`` builds them, and nested model instances pass through unvalidated and uncopied.
                return WorldState(
                    stamp_ns=now_ns,
                    joint_state=joint_state,
                    image_frames=frames if self._has_sensors else None,
                    diagnostics=diagnostics,
                    task=task,
                )
            finally:
                span.end()

    def _diagnose(
        self,
        component: _Component,
        stamp_ns: int | None,
        now_ns: int,
        errors: dict[str, str] | None,
        span: Any,
        *,
        telemetry: TickTelemetry | None,
        marked: dict[str, float | None],
    ) -> ComponentDiagnostics:
        limit = component.max_age_ms
        if stamp_ns is None:
            age_ms: float | None = None
            stale = True
        else:
            age_ms = (now_ns - stamp_ns) / 1e6
            stale = age_ms > limit or age_ms < -limit
            if telemetry is None:
                metrics.record_histogram_ms(semconv.METRIC_WORLD_STATE_STALENESS, age_ms, component.attributes)
            else:
                telemetry.record_ms(semconv.METRIC_WORLD_STATE_STALENESS, age_ms, component.attributes)
        if marked and component.name in marked:
            stale = True
            age_ms = marked[component.name] if marked[component.name] is not None else age_ms
        error = errors.get(component.name) if errors else None

        if stale and not component.stale_latched:
            attributes = dict(component.attributes or {})
            if age_ms is not None:
                attributes[semconv.ATTR_SENSOR_AGE_MS] = age_ms
            span.add_event(semconv.EVENT_STALENESS_LATCHED, attributes)
        component.stale_latched = stale
        if error is not None and not component.error_latched:
            span.add_event(
                semconv.EVENT_ERROR_LATCHED, {**(component.attributes or {}), semconv.ATTR_EXCEPTION_MESSAGE: error}
            )
        component.error_latched = error is not None
        unhealthy = stale or error is not None
        if unhealthy != component.unhealthy:
            metrics.up_down_counter(semconv.METRIC_WORLD_STATE_COMPONENTS_STALE).add(
                1 if unhealthy else -1, component.attributes
            )
            component.unhealthy = unhealthy

        return ComponentDiagnostics(
            component=component.name,
            age_ms=age_ms,
            max_age_ms=limit,
            stale=stale,
            required=component.required,
            error=error,
        )

    def _check_component(self, component: str) -> None:
        if component != JOINT_STATE_COMPONENT and component not in self._sensor_ids:
            raise self._unknown(component, declared=list(self.components), what="component")

    @staticmethod
    def _unknown(name: str, *, declared: list[str], what: str) -> ROSConfigError:
        return ROSConfigError(
            f"unknown {what} '{name}'; declared: {', '.join(declared) or 'none'}",
            hint="declare it in the deployment's sensors",
        )


def _component(name: str, max_age_ms: float, required: bool) -> _Component:
    return _Component(name=name, max_age_ms=max_age_ms, required=required, attributes={semconv.ATTR_COMPONENT: name})
