"""The deployment blocks: round trips for every block and the rules each one enforces."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, ValidationError

from openral_core import (
    DeadlineOverrunPolicy,
    FaultPolicy,
    FrameEncoding,
    HalConfig,
    ObserverConfig,
    RealtimeConfig,
    RobotEnvironment,
    SafetyConfig,
    SafetyMode,
    SensorReaderBackend,
    SensorReaderConfig,
    TaskSpec,
    VLASpec,
)

PROPERTY = settings(max_examples=60, deadline=None)
ids = st.from_regex(r"[A-Za-z][A-Za-z0-9_\-]{0,11}", fullmatch=True)
positive = st.floats(min_value=1e-3, max_value=1e6, allow_nan=False)
json_scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**53), 2**53)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8)
)
params = st.dictionaries(st.text(max_size=8), json_scalars | st.lists(json_scalars, max_size=3), max_size=3)
coordinate = st.floats(min_value=-10.0, max_value=10.0)
boxes = st.tuples(coordinate, coordinate, coordinate).map(lambda lo: (lo, (lo[0] + 1.0, lo[1] + 1.0, lo[2] + 1.0)))


@st.composite
def sensor_configs(draw: st.DrawFn, sensor_id: str | None = None) -> SensorReaderConfig:
    tee = draw(st.booleans())
    return SensorReaderConfig(
        sensor_id=sensor_id or draw(ids),
        backend=draw(st.sampled_from(list(SensorReaderBackend))),
        required=draw(st.booleans()),
        max_age_ms=draw(positive),
        fps=draw(st.floats(min_value=1e-3, max_value=1000.0)),
        width=draw(st.none() | st.integers(1, 8192)),
        height=draw(st.none() | st.integers(1, 8192)),
        encoding=draw(st.sampled_from(list(FrameEncoding))),
        backend_params=draw(params),
        publish_to_ros=tee,
        publish_topic=draw(st.text(min_size=1, max_size=12)) if tee else None,
        publish_rate_hz=draw(st.none() | st.floats(min_value=1e-3, max_value=1000.0)),
    )


hal_configs = st.builds(HalConfig, robot_id=ids, adapter=ids, params=params)
task_specs = st.builds(TaskSpec, instruction=st.text(max_size=30), task_id=st.none() | st.text(max_size=8))
vla_specs = st.builds(
    VLASpec,
    id=ids,
    manifest=st.none() | st.text(max_size=12),
    accept_licenses=st.none() | st.lists(st.text(max_size=12), max_size=3),
    params=params,
)


@st.composite
def safety_configs(draw: st.DrawFn) -> SafetyConfig:
    box: dict[str, Any] = {}
    if draw(st.booleans()):
        low, high = draw(boxes)
        box = {"workspace_min": low, "workspace_max": high}
    return SafetyConfig(
        client=draw(st.none() | ids),
        mode=draw(st.sampled_from(list(SafetyMode))),
        max_joint_speed_factor=draw(st.floats(min_value=1e-6, max_value=1.0)),
        **box,
    )


realtime_configs = st.builds(
    RealtimeConfig,
    sched_fifo_priority=st.none() | st.integers(1, 99),
    cpu_affinity=st.none() | st.lists(st.integers(0, 1023), min_size=1, max_size=4),
    switch_interval_s=st.none() | st.floats(min_value=1e-6, max_value=0.1),
    lock_memory=st.booleans(),
)
fault_policies = st.builds(FaultPolicy, max_consecutive_failures=st.integers(1, 1000))


@st.composite
def environments(draw: st.DrawFn) -> RobotEnvironment:
    sensor_ids = draw(st.lists(ids, max_size=3, unique=True))
    return RobotEnvironment(
        name=draw(st.text(min_size=1, max_size=12)),
        hal=draw(hal_configs),
        vla=draw(vla_specs),
        task=draw(task_specs),
        sensors=[draw(sensor_configs(sid)) for sid in sensor_ids],
        rate_hz=draw(st.floats(min_value=1e-3, max_value=10_000)),
        deadline_overrun_policy=draw(st.sampled_from(list(DeadlineOverrunPolicy))),
        latency_budget_ms=draw(st.none() | positive),
        thumbnail_hz=draw(st.floats(min_value=0.0, max_value=100.0)),
        safety=draw(safety_configs()),
        realtime=draw(realtime_configs),
        faults=draw(fault_policies),
    )


@pytest.mark.parametrize(
    ("model", "strategy"),
    [
        (SensorReaderConfig, sensor_configs()),
        (HalConfig, hal_configs),
        (TaskSpec, task_specs),
        (VLASpec, vla_specs),
        (SafetyConfig, safety_configs()),
        (RealtimeConfig, realtime_configs),
        (FaultPolicy, fault_policies),
        (RobotEnvironment, environments()),
    ],
    ids=lambda v: v.__name__ if isinstance(v, type) else "",
)
@PROPERTY
@given(data=st.data())
def test_round_trips(model: type[BaseModel], strategy: st.SearchStrategy[BaseModel], data: st.DataObject) -> None:
    value = data.draw(strategy)
    assert model.model_validate_json(value.model_dump_json()) == value
    assert model.model_validate(value.model_dump()) == value
    assert model.model_validate(value.model_dump(mode="json")) == value


def _env(**overrides: Any) -> RobotEnvironment:
    fields: dict[str, Any] = {"hal": {"robot_id": "so101_follower"}, "vla": {"id": "hello"}}
    fields.update(overrides)
    return RobotEnvironment.model_validate(fields)


# --- SensorReaderConfig ---------------------------------------------------------------------------


def test_ros_tee_needs_a_topic() -> None:
    with pytest.raises(ValidationError, match="publish_to_ros is true but publish_topic is empty"):
        SensorReaderConfig(sensor_id="cam", publish_to_ros=True)
    with pytest.raises(ValidationError, match="publish_to_ros is true but publish_topic is empty"):
        SensorReaderConfig(sensor_id="cam", publish_to_ros=True, publish_topic="")


def test_topic_needs_the_ros_tee() -> None:
    with pytest.raises(ValidationError, match="publish_topic is set but publish_to_ros is false"):
        SensorReaderConfig(sensor_id="cam", publish_topic="/cam/image_raw")


def test_ros_tee_with_topic_is_valid() -> None:
    config = SensorReaderConfig(sensor_id="cam", publish_to_ros=True, publish_topic="/cam/image_raw")
    assert config.publish_topic == "/cam/image_raw"


@pytest.mark.parametrize("sensor_id", ["", "1cam", "front cam", "cam/0"])
def test_sensor_id_must_be_an_identifier(sensor_id: str) -> None:
    with pytest.raises(ValidationError, match="sensor_id"):
        SensorReaderConfig(sensor_id=sensor_id)


@pytest.mark.parametrize(
    "fields", [{"max_age_ms": 0.0}, {"fps": -1.0}, {"width": 0}, {"height": 0}, {"publish_rate_hz": 0.0}]
)
def test_sensor_limits_are_positive(fields: dict[str, Any]) -> None:
    with pytest.raises(ValidationError, match=next(iter(fields))):
        SensorReaderConfig(sensor_id="cam", **fields)


def test_sensor_defaults() -> None:
    config = SensorReaderConfig(sensor_id="cam")
    assert config.required is True
    assert config.max_age_ms == 100.0
    assert config.backend == SensorReaderBackend.OPENCV_THREAD
    assert config.encoding is FrameEncoding.BGR8


# --- RobotEnvironment -----------------------------------------------------------------------------


def test_sensor_ids_are_unique() -> None:
    with pytest.raises(ValidationError, match=r"sensors\[2\]\.sensor_id 'front' is used twice"):
        _env(sensors=[{"sensor_id": "front"}, {"sensor_id": "wrist"}, {"sensor_id": "front"}])


@pytest.mark.parametrize("rate", [0.0, -30.0, 10_001.0])
def test_rate_is_positive_and_bounded(rate: float) -> None:
    with pytest.raises(ValidationError, match="rate_hz"):
        _env(rate_hz=rate)


def test_thumbnail_rate_is_short_for_a_thumbnails_observer() -> None:
    assert _env(thumbnail_hz=0.0).observers == [], "0 adds no observer"
    (entry,) = _env(thumbnail_hz=12.5).observers
    assert (entry.id, entry.params) == ("thumbnails", {"rate_hz": 12.5})
    explicit = ObserverConfig(id="thumbnails", params={"rate_hz": 3.0})
    assert _env(thumbnail_hz=12.5, observers=[explicit]).observers == [explicit], "an explicit entry wins"
    for wrong in (-1.0, float("nan"), 1e300, "fast", True):
        with pytest.raises(ValidationError, match="thumbnail_hz"):
            _env(thumbnail_hz=wrong)


def test_latency_budget_is_positive() -> None:
    with pytest.raises(ValidationError, match="latency_budget_ms"):
        _env(latency_budget_ms=0.0)


def test_period_is_the_inverse_rate() -> None:
    assert _env(rate_hz=50.0).period_s == pytest.approx(0.02)


def test_defaults_fill_every_block() -> None:
    env = _env()
    assert env.task == TaskSpec()
    assert env.safety.client == "envelope"
    assert env.safety.mode is SafetyMode.CLAMP
    assert env.realtime == RealtimeConfig()
    assert env.faults.max_consecutive_failures == 5
    assert env.deadline_overrun_policy is DeadlineOverrunPolicy.WARN
    assert env.sensors == []


def test_blocks_are_frozen() -> None:
    env = _env()
    with pytest.raises(ValidationError, match="frozen"):
        env.rate_hz = 10.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("block", "fields"),
    [
        ("hal", {"robot_id": "so101", "adaptr": "x"}),
        ("vla", {"id": "hello", "parms": {}}),
        ("task", {"instructions": "x"}),
        ("safety", {"clients": "null"}),
        ("realtime", {"priority": 10}),
        ("faults", {"max_failures": 3}),
    ],
)
def test_every_block_forbids_unknown_keys(block: str, fields: dict[str, Any]) -> None:
    base: dict[str, Any] = {"hal": {"robot_id": "so101"}, "vla": {"id": "hello"}, block: fields}
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        RobotEnvironment.model_validate(base)


# --- SafetyConfig / RealtimeConfig / FaultPolicy --------------------------------------------------


def test_safety_client_null_in_yaml_means_the_null_client() -> None:
    assert SafetyConfig(client=None).client == "null"  # type: ignore[arg-type]


def test_safety_workspace_bounds_go_together() -> None:
    try:
        _env(safety={"workspace_min": [0.0, 0.0, 0.0]})
    except ValidationError:
        return
    pytest.fail(
        "SafetyConfig accepted workspace_min without workspace_max: the deployment loads and the mistake "
        "surfaces later when the runner builds the envelope; give SafetyConfig the same _box check as SafetyEnvelope"
    )


def test_safety_workspace_min_must_be_below_max() -> None:
    try:
        _env(safety={"workspace_min": [0.0, 0.0, 1.0], "workspace_max": [1.0, 1.0, 0.5]})
    except ValidationError:
        return
    pytest.fail(
        "SafetyConfig accepted workspace_min.z above workspace_max.z: give SafetyConfig the same _box check "
        "as SafetyEnvelope so the deployment file is rejected with the field named"
    )


@pytest.mark.parametrize(
    ("fields", "field"),
    [
        ({"sched_fifo_priority": 0}, "sched_fifo_priority"),
        ({"sched_fifo_priority": 100}, "sched_fifo_priority"),
        ({"switch_interval_s": 0.0}, "switch_interval_s"),
        ({"switch_interval_s": 0.5}, "switch_interval_s"),
    ],
)
def test_realtime_knob_ranges(fields: dict[str, Any], field: str) -> None:
    with pytest.raises(ValidationError, match=field):
        RealtimeConfig(**fields)


def test_fault_policy_needs_at_least_one_failure() -> None:
    with pytest.raises(ValidationError, match="max_consecutive_failures"):
        FaultPolicy(max_consecutive_failures=0)


@pytest.mark.parametrize("field", ["robot_id", "adapter"])
def test_hal_names_are_identifiers(field: str) -> None:
    fields = {"robot_id": "so101", field: "so 101"}
    with pytest.raises(ValidationError, match=field):
        HalConfig(**fields)
