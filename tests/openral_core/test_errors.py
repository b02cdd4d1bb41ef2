"""The ROS* error family: hierarchy, messages that say what to do, attributes, pickling."""

from __future__ import annotations

import pickle

import pytest

from openral_core import (
    ROSConfigError,
    ROSDeadlineMissed,
    ROSDependencyMissing,
    ROSError,
    ROSEStopRequested,
    ROSHardwareError,
    ROSLicenseError,
    ROSPerceptionStale,
    ROSRuntimeError,
    ROSSafetyViolation,
    ROSSkillError,
    ROSStopRequested,
    RunResult,
    TickResult,
)


@pytest.mark.parametrize(
    ("error", "parent"),
    [
        (ROSConfigError, ROSError),
        (ROSDependencyMissing, ROSConfigError),
        (ROSLicenseError, ROSConfigError),
        (ROSRuntimeError, ROSError),
        (ROSHardwareError, ROSRuntimeError),
        (ROSPerceptionStale, ROSRuntimeError),
        (ROSSkillError, ROSRuntimeError),
        (ROSDeadlineMissed, ROSRuntimeError),
        (ROSSafetyViolation, ROSError),
        (ROSEStopRequested, ROSError),
        (ROSStopRequested, ROSError),
    ],
)
def test_hierarchy(error: type[Exception], parent: type[Exception]) -> None:
    assert issubclass(error, parent)


def test_config_errors_and_run_time_errors_are_disjoint() -> None:
    """The CLI maps ROSConfigError to exit 2 and other ROSError to 1: no class may be both."""
    runtime = [ROSRuntimeError, ROSHardwareError, ROSPerceptionStale, ROSSkillError, ROSDeadlineMissed]
    assert not any(issubclass(e, ROSConfigError) for e in runtime)
    assert not issubclass(ROSEStopRequested, ROSSafetyViolation), "an e-stop is never an ordinary violation"


def test_config_error_names_the_field_and_the_fix() -> None:
    error = ROSConfigError("must be above 0", field="sensors[0].fps", hint="use e.g. 30")
    assert str(error) == "sensors[0].fps: must be above 0 (use e.g. 30)"
    assert error.field == "sensors[0].fps"
    assert error.hint == "use e.g. 30"
    assert str(ROSConfigError("plain")) == "plain"


def test_dependency_missing_names_the_module_and_the_extra() -> None:
    error = ROSDependencyMissing("mujoco", extra="twin", needed_for="the MuJoCo twin")
    assert isinstance(error, ROSConfigError)
    text = str(error)
    assert "the MuJoCo twin needs the Python module 'mujoco'" in text
    assert "uv sync --extra twin" in text
    assert "openral[twin]" in text
    assert (error.module, error.extra) == ("mujoco", "twin")


def test_dependency_outside_pypi_says_how_to_get_it_instead_of_an_extra() -> None:
    error = ROSDependencyMissing("rclpy", extra=None, needed_for="the ros2_image backend", install="source ROS 2")
    assert "source ROS 2" in str(error)
    assert "uv sync" not in str(error)
    with pytest.raises(ValueError, match="extra or install"):
        ROSDependencyMissing("rclpy", extra=None, needed_for="x")


def test_perception_stale_says_whether_a_frame_ever_arrived() -> None:
    never = ROSPerceptionStale("front", age_ms=None, max_age_ms=50.0)
    assert str(never) == "sensor 'front' has not delivered a frame yet"
    old = ROSPerceptionStale("front", age_ms=123.456, max_age_ms=50.0)
    assert str(old) == "sensor 'front' frame is 123.5 ms old (limit 50.0 ms)"
    assert (old.sensor_id, old.age_ms, old.max_age_ms) == ("front", 123.456, 50.0)


def test_safety_violation_carries_check_and_severity() -> None:
    error = ROSSafetyViolation("joint 2 beyond limit by 0.1 rad", check_name="joint_limit", severity="critical")
    assert (error.check_name, error.severity) == ("joint_limit", "critical")
    default = ROSSafetyViolation("x")
    assert (default.check_name, default.severity) == ("unspecified", "violation")


def test_deadline_missed_carries_the_partial_run() -> None:
    tick = TickResult(tick_idx=7, deadline_missed=True)
    run = RunResult(rate_hz=30.0, n_ticks=8, stop_reason="deadline")
    error = ROSDeadlineMissed("tick 7 late by 4.0 ms", tick_result=tick, run_result=run)
    assert error.tick_result is tick
    assert error.run_result is run
    assert ROSDeadlineMissed("late").run_result is None


@pytest.mark.parametrize(
    "error",
    [
        ROSConfigError("bad", field="rate_hz", hint="use 30"),
        ROSDependencyMissing("cv2", extra="opencv", needed_for="the OpenCV reader"),
        ROSDependencyMissing("rclpy", extra=None, needed_for="the ROS 2 reader", install="source ROS 2"),
        ROSPerceptionStale("front", age_ms=120.0, max_age_ms=50.0),
        ROSSafetyViolation("over", check_name="joint_limit", severity="critical"),
        ROSDeadlineMissed("late", tick_result=TickResult(tick_idx=1)),
        ROSHardwareError("servo 3 did not answer"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_errors_survive_pickling(error: ROSError) -> None:
    """Errors cross process boundaries (worker processes, multiprocessing pools) by pickle."""
    try:
        back = pickle.loads(pickle.dumps(error))
    except TypeError as exc:
        pytest.fail(
            f"{type(error).__name__} cannot be unpickled ({exc}): its __init__ takes required keyword-only "
            "arguments that BaseException.__reduce__ does not pass; define __reduce__ returning the constructor "
            "arguments"
        )
    assert type(back) is type(error)
    assert str(back) == str(error)
    assert vars(back).keys() == vars(error).keys()


@pytest.mark.parametrize(
    ("message", "field", "hint"),
    [
        ("'a\tb\nc' is not a pattern", "sensors[cam].backend_params.pattern", None),
        ("unknown key", "params.pa\nttern\x1b[31m", "did you mean\r\n'pattern'?"),
        ("value\x00\x07\u2028here", None, None),
    ],
)
def test_config_error_echoing_control_characters_stays_on_one_printable_line(
    message: str, field: str | None, hint: str | None
) -> None:
    text = str(ROSConfigError(message, field=field, hint=hint))
    assert text.isprintable(), repr(text)
    assert "\\n" in text or "\\x00" in text or "\\r" in text
    assert "is not a pattern" in text or "unknown key" in text or "here" in text
