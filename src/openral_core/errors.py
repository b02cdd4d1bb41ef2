"""The ``ROS*`` error family: every failure openral raises on purpose.

Each error says what happened, why, and what to do. The CLI maps
:class:`ROSConfigError` to exit code 2 and every other :class:`ROSError` to 1.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from openral_core.results import RunResult, TickResult


def one_line(text: str) -> str:
    """``text`` on one line: line breaks and other control characters are written as escapes.

    Messages echo what a user wrote (a value, a key, a path); a newline or a terminal escape in it
    must neither split an error over several lines nor reach the terminal raw.
    """
    if text.isprintable():
        return text
    return "".join(ch if ch.isprintable() or ch == " " else ascii(ch)[1:-1] for ch in text)


class ROSError(Exception):
    """Base of every openral error."""


class ROSConfigError(ROSError):
    """A configuration, manifest or registry lookup is wrong; fixable by editing input.

    Args:
        message: What is wrong.
        field: Dotted path of the offending field, when there is one.
        hint: What to change to fix it.
    """

    def __init__(self, message: str, *, field: str | None = None, hint: str | None = None) -> None:
        self.field = field
        self.hint = hint
        text = f"{field}: {message}" if field else message
        if hint:
            text = f"{text} ({hint})"
        super().__init__(one_line(text))


class ROSDependencyMissing(ROSConfigError):
    """An optional dependency needed by the selected configuration is not installed.

    Args:
        module: The Python module that failed to import.
        extra: The openral extra that installs it; ``None`` when no extra can (a module from
            outside PyPI), and then ``install`` says what to do.
        needed_for: What the configuration asked for that needs it.
        install: How to install it, when not through an extra.
    """

    def __init__(self, module: str, *, extra: str | None, needed_for: str, install: str | None = None) -> None:
        self.module = module
        self.extra = extra
        self.needed_for = needed_for
        self.install = install
        if install is None and extra is None:
            raise ValueError("ROSDependencyMissing needs an extra or install instructions")
        super().__init__(
            f"{needed_for} needs the Python module '{module}', which is not installed",
            hint=install or f"install the extra: uv sync --extra {extra}  (or pip install 'openral[{extra}]')",
        )

    def __reduce__(self) -> tuple[Any, ...]:
        kwargs = {"extra": self.extra, "needed_for": self.needed_for, "install": self.install}
        return (_rebuild, (type(self), (self.module,), kwargs))


class ROSLicenseError(ROSConfigError):
    """A skill's licence is not accepted by the deployment's licence policy."""


def renamed_field(exc: ROSConfigError, prefixes: tuple[str, ...], prefix: str) -> ROSConfigError:
    """``exc`` naming its field under ``prefix`` where the field starts with one of ``prefixes``; else ``exc`` itself.

    A part names its parameters where it usually sits (a skill's as ``vla.params``); built from
    another block of the file (``takeover.params``), its errors must name that block. Other kinds
    of configuration error (a missing dependency, a refused licence) pass unchanged.
    """
    field = exc.field
    if type(exc) is not ROSConfigError or field is None:
        return exc
    for old in prefixes:
        if field == old or field.startswith(f"{old}."):
            message = str(exc).removeprefix(f"{one_line(field)}: ")
            if exc.hint:
                message = message.removesuffix(f" ({one_line(exc.hint)})")
            return ROSConfigError(message, field=prefix + field.removeprefix(old), hint=exc.hint)
    return exc


class ROSRuntimeError(ROSError):
    """Something failed while running: a device, a pipeline, a bus transaction."""


class ROSHardwareError(ROSRuntimeError):
    """The robot hardware (or its twin) failed a connect, read or write."""


class ROSPerceptionStale(ROSRuntimeError):
    """A sensor has no frame yet, or its freshest frame is older than the allowed age.

    Args:
        sensor_id: The sensor that is stale.
        age_ms: Age of the freshest frame, ``None`` when no frame has arrived yet.
        max_age_ms: The age limit that was exceeded.
    """

    def __init__(self, sensor_id: str, *, age_ms: float | None, max_age_ms: float | None) -> None:
        self.sensor_id = sensor_id
        self.age_ms = age_ms
        self.max_age_ms = max_age_ms
        if age_ms is None:
            text = f"sensor '{sensor_id}' has not delivered a frame yet"
        else:
            text = f"sensor '{sensor_id}' frame is {age_ms:.1f} ms old (limit {max_age_ms} ms)"
        super().__init__(text)

    def __reduce__(self) -> tuple[Any, ...]:
        kwargs = {"age_ms": self.age_ms, "max_age_ms": self.max_age_ms}
        return (_rebuild, (type(self), (self.sensor_id,), kwargs))


class ROSSyncError(ROSRuntimeError):
    """A multi-camera set could not be made with capture stamps within the allowed skew in time.

    Args:
        message: Which sensors lagged and by how much.
        skew_ms: The spread of capture stamps in the best set found.
        lagging: Sensor ids whose frames were too old relative to the newest.
    """

    def __init__(self, message: str, *, skew_ms: float, lagging: tuple[str, ...]) -> None:
        self.skew_ms = skew_ms
        self.lagging = lagging
        super().__init__(message)

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild, (type(self), (str(self),), {"skew_ms": self.skew_ms, "lagging": self.lagging}))


class ROSSafetyViolation(ROSError):
    """The safety client rejected an action; the runner withholds it.

    Args:
        message: Which limit was violated and by how much.
        check_name: Short stable name of the check (``joint_limit``, ``non_finite``, ...).
        severity: ``violation`` for a rejected action, ``critical`` for one that also stops the loop.
    """

    def __init__(self, message: str, *, check_name: str = "unspecified", severity: str = "violation") -> None:
        self.check_name = check_name
        self.severity = severity
        super().__init__(message)


class ROSEStopRequested(ROSError):
    """An emergency stop was requested: the loop stops and ``HAL.estop()`` is called."""


class ROSSkillError(ROSRuntimeError):
    """A skill failed in a lifecycle transition or in ``step``; its error latch is set."""


class ROSUnavailable(ROSRuntimeError):
    """Something a skill depends on (a remote policy server, its link) cannot answer now; it may come back.

    Raised from ``step`` it does not latch the skill's error: the next step may succeed.
    """


class ROSDeadlineMissed(ROSRuntimeError):
    """A tick missed its deadline under the ``raise`` policy.

    The late action was withheld and the robot left holding its last target.

    Args:
        message: Which tick was late and by how much.
        tick_result: The late tick.
        run_result: The partial run up to and including the late tick (set by ``run()``).
    """

    def __init__(
        self,
        message: str,
        *,
        tick_result: TickResult | None = None,
        run_result: RunResult | None = None,
    ) -> None:
        self.tick_result = tick_result
        self.run_result = run_result
        super().__init__(message)


class ROSStopRequested(ROSError):
    """A cooperative stop (signal, caller, or a skill that finished its task) ended the run early.

    Args:
        message: What asked for the stop.
        reason: The stop reason reported in the ``RunResult`` (``signal:SIGTERM``, ...).
    """

    def __init__(self, message: str = "stop requested", *, reason: str = "stop_requested") -> None:
        self.reason = reason
        super().__init__(message)

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild, (type(self), (str(self),), {"reason": self.reason}))


def _rebuild(cls: type[ROSError], args: tuple[Any, ...], kwargs: dict[str, Any]) -> ROSError:
    """Unpickle an error whose constructor takes keyword-only arguments."""
    return cls(*args, **kwargs)
