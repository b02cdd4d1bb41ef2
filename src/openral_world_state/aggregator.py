"""``WorldStateAggregator``: a tick's frames, read verdicts and joint state, turned into one ``WorldState``."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from opentelemetry.trace import INVALID_SPAN, Span
from opentelemetry.util.types import Attributes

from openral_core import (
    ComponentDiagnostics,
    JointState,
    ROSConfigError,
    ROSError,
    ROSPerceptionStale,
    SensorFrame,
    SensorReaderConfig,
    WorldState,
)
from openral_observability import metrics, semconv

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
    """Turns the frames and verdicts a runner read this tick, and the freshest joint state, into one ``WorldState``.

    The aggregator holds no frames: the latest-frame slots are the one mailbox, and the runner
    hands :meth:`snapshot` what it read from them this tick together with each failed read's
    exception, the reader's verdict. A sensor whose read raised ``ROSPerceptionStale`` is stale
    (with the age the reader measured); another ``ROSError`` sets the sensor's error for this
    snapshot. A sensor read without complaint is judged by its frame's age. The joint state is
    kept across ticks (:meth:`update_joint_state`), thread-safe, newest capture wins.

    Freshness is measured from each sample's *capture* stamp (``SensorFrame.stamp_ns``,
    ``JointState.stamp_ns``) to ``clock()``, never from when it arrived: a sample is stale when it
    is missing, older than its ``max_age_ms``, or stamped further than ``max_age_ms`` in the future
    (a backend stamping on another clock is never "fresh forever"). A component with an error set
    (:meth:`set_error`) is unhealthy until :meth:`clear_error`.

    Transitions are reported as events on the span the caller passes (the runner's
    ``world_state.snapshot`` span, timed by the runner):

    - ``openral.event.staleness_latched`` (component, age when known) the first snapshot a
      component is stale after having been fresh. Every component starts out fresh, so a
      sensor that has not delivered by the first snapshot latches once then.
    - ``openral.event.error_latched`` (component, message) the first snapshot that sees an
      error; the same or a changed error emits nothing until it is cleared.
    - Recovery emits no event; the up-down counter ``openral.world_state.components_stale``
      goes +1 when a component becomes unhealthy (stale or in error) and -1 when it is healthy again.

    Each component's age is in its ``ComponentDiagnostics``; the runner records it on the
    ``openral.world_state.staleness_ms`` histogram.

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
        self._lock = threading.Lock()
        self._joint_state: JointState | None = None
        self._errors: dict[str, str] = {}

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

    def snapshot(
        self,
        frames: Mapping[str, SensorFrame] | None = None,
        *,
        failures: Mapping[str, ROSError] | None = None,
        task: str | None = None,
        span: Span = INVALID_SPAN,
    ) -> WorldState:
        """A ``WorldState`` of ``frames`` and the joint state, with diagnostics for every declared component.

        Args:
            frames: The latest frame of each sensor that has delivered one (the objects themselves
                reach ``image_frames``, in a new dict: never copied pixels).
            failures: This tick's failed reads by sensor: ``ROSPerceptionStale`` makes the sensor
                stale, any other ``ROSError`` its error for this snapshot.
            task: The instruction the skill is given.
            span: Where transition events go (the caller's ``world_state.snapshot`` span).

        ``image_frames`` is ``None`` when no sensors are declared. ``stamp_ns`` is ``clock()`` read
        after the samples were taken, so ages are never negative on a shared clock.

        Raises:
            ROSConfigError: ``frames`` or ``failures`` name an undeclared sensor.
        """
        if frames and not self._sensor_ids.issuperset(frames):
            raise self._undeclared(frames)
        if failures and not self._sensor_ids.issuperset(failures):
            raise self._undeclared(failures)
        with self._lock:
            joint_state = self._joint_state
            errors = dict(self._errors) if self._errors else None
        now_ns = self._clock()
        diagnostics: dict[str, ComponentDiagnostics] = {}
        for component in self._components:
            failure = None
            if component.name == JOINT_STATE_COMPONENT:
                stamp_ns = None if joint_state is None else joint_state.stamp_ns
            else:
                frame = frames.get(component.name) if frames else None
                stamp_ns = None if frame is None else frame.stamp_ns
                failure = failures.get(component.name) if failures else None
            diagnostics[component.name] = self._diagnose(
                component, stamp_ns, now_ns, errors, failure=failure, span=span
            )
        # Plain (validated) construction: pydantic-core checks these flat fields faster than
        # ``model_construct`` builds them, and nested model instances pass through unvalidated and uncopied.
        return WorldState(
            stamp_ns=now_ns,
            joint_state=joint_state,
            image_frames=(dict(frames) if frames else {}) if self._has_sensors else None,
            diagnostics=diagnostics,
            task=task,
        )

    def _diagnose(
        self,
        component: _Component,
        stamp_ns: int | None,
        now_ns: int,
        errors: dict[str, str] | None,
        *,
        failure: ROSError | None,
        span: Span,
    ) -> ComponentDiagnostics:
        limit = component.max_age_ms
        if stamp_ns is None:
            age_ms: float | None = None
            stale = True
        else:
            age_ms = (now_ns - stamp_ns) / 1e6
            stale = age_ms > limit or age_ms < -limit
        error = errors.get(component.name) if errors else None
        if isinstance(failure, ROSPerceptionStale):
            stale = True  # the reader's verdict, with the age it measured when it has one
            age_ms = failure.age_ms if failure.age_ms is not None else age_ms
        elif failure is not None:
            error = str(failure)

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

    def _undeclared(self, names: Mapping[str, object]) -> ROSConfigError:
        unknown = sorted(set(names) - self._sensor_ids)[0]
        return self._unknown(unknown, declared=sorted(self._sensor_ids), what="sensor")

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
