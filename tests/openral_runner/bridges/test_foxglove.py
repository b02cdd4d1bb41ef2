"""Foxglove sink: MCAP channels with one message per tick, a live WebSocket, a tick thread that never blocks."""

from __future__ import annotations

import importlib
import json
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from openral_core import (
    FrameEncoding,
    JointState,
    ROSConfigError,
    ROSDependencyMissing,
    SensorReaderConfig,
    TickResult,
    WorldState,
)
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.frame_slot import frame_from_array
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock, ScriptedReader
from openral_runner.thumbnails import ThumbnailPublisher, encode_thumbnail
from openral_world_state import WorldStateAggregator

EXTRA = "needs the 'foxglove' extra (foxglove-sdk, mcap): uv sync --extra foxglove"

NAMES = ["shoulder_pan", "shoulder_lift", "gripper"]
STEP_NS = 10_000_000  # 100 Hz ticks


def make_tick(i: int, **overrides) -> TickResult:
    fields = {
        "tick_idx": i,
        "tick_ms": 1.0 + i / 100,
        "sensors_ms": 0.1,
        "world_state_ms": 0.2,
        "inference_ms": 0.5 + i / 1000,
        "safety_ms": 0.05,
        "hal_ms": 0.15,
        "action_applied": True,
        "requested_action": [0.1 * i, 0.0, 0.5],
        "sent_action": [0.1 * i, 0.0, 0.5],
    }
    return TickResult(**(fields | overrides))


def make_world(i: int, *, with_frame: bool = True) -> WorldState:
    stamp = 1_000_000_000 + i * STEP_NS
    joints = JointState(names=NAMES, positions=[0.01 * i, -0.02 * i, 0.5], velocities=[1.0, -2.0, 0.0], stamp_ns=stamp)
    frames = None
    if with_frame:
        pixels = np.zeros((48, 64, 3), np.uint8)
        pixels[:, :, 2] = 200
        frames = {"wrist": frame_from_array("wrist", pixels, stamp_ns=stamp, seq=i, encoding=FrameEncoding.BGR8)}
    return WorldState(stamp_ns=stamp, joint_state=joints, image_frames=frames)


@pytest.fixture
def sink_cls() -> Callable[..., object]:
    """``FoxgloveSink``, imported only here: the first two tests run without the extra.

    Called with ``mcap_path``, it attaches an MCAP sink to the view's Foxglove context, closed
    with the view: the test's probe of what the view published.
    """
    pytest.importorskip("foxglove", reason=EXTRA)
    foxglove = importlib.import_module("foxglove")
    sink_type = importlib.import_module("openral_runner.bridges.foxglove").FoxgloveSink

    def make(*, mcap_path: Path | None = None, **kwargs: object) -> object:
        sink = sink_type(**kwargs)
        if mcap_path is not None:
            probe = foxglove.open_mcap(mcap_path, context=sink.context)
            close = sink.close

            def close_with_probe() -> None:
                close()
                probe.close()

            sink.close = close_with_probe
        return sink

    return make


@pytest.fixture
def read_mcap():
    """Read an MCAP file into ``{topic: [(schema, channel, message), ...]}`` with the official reader."""
    reader = pytest.importorskip("mcap.reader", reason=EXTRA)

    def read(path: Path) -> dict[str, list]:
        with path.open("rb") as f:
            mcap = reader.make_reader(f)
            summary = mcap.get_summary()
            assert summary is not None, "MCAP file has no summary: the writer was not closed"
            messages: dict[str, list] = {channel.topic: [] for channel in summary.channels.values()}
            for schema, channel, message in mcap.iter_messages():
                messages[channel.topic].append((schema, channel, message))
        return messages

    return read


def test_importing_observability_loads_no_foxglove() -> None:
    code = "import sys, openral_observability; print(sorted(m for m in ('foxglove', 'mcap') if m in sys.modules))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.strip() == "[]"


def test_missing_foxglove_names_the_extra() -> None:
    code = (
        "import sys\n"
        "sys.modules['foxglove'] = None\n"
        "from openral_core import ROSDependencyMissing\n"
        "try:\n"
        "    import openral_runner.bridges.foxglove\n"
        "except ROSDependencyMissing as exc:\n"
        "    print(exc.extra, '|', exc)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    extra, message = proc.stdout.strip().split(" | ")
    assert extra == "foxglove"
    assert "the Foxglove live view" in message
    assert "uv sync --extra foxglove" in message
    assert issubclass(ROSDependencyMissing, ROSConfigError)


def test_mcap_has_one_joint_state_and_one_timing_message_per_tick(tmp_path: Path, sink_cls, read_mcap) -> None:
    path = tmp_path / "run.mcap"
    n = 20
    sink = sink_cls(mcap_path=path)
    before_ns = time.time_ns()
    for i in range(n):
        extra = {}
        if i == 5:
            extra = {"safety_violations": ["joint 'gripper' clamped"], "sent_action": [0.5, 0.0, 0.4]}
        if i == 7:
            extra = {"action_applied": False, "withheld_reason": "deadline", "deadline_missed": True}
        sink.on_tick(make_tick(i, **extra), make_world(i))
    sink.on_tick(make_tick(n), None)  # a tick without a world: timings only
    for i in (0, 10):  # the runner's thumbnail worker hands over the wrist camera's thumbnails
        frame = make_world(i).image_frames["wrist"]  # type: ignore[index]
        sink.on_thumbnail(encode_thumbnail(frame))
    sink.close()
    sink.close()  # idempotent
    after_ns = time.time_ns()
    assert sink.dropped == 0
    assert sink.publish_errors == 0

    messages = read_mcap(path)
    assert set(messages) == {"/joint_states", "/openral/tick", "/openral/safety", "/camera/wrist/compressed"}

    ticks = [json.loads(m.data) for _, _, m in messages["/openral/tick"]]
    assert [t["tick_idx"] for t in ticks] == list(range(n + 1))
    assert [t["tick_ms"] for t in ticks] == [make_tick(i).tick_ms for i in range(n + 1)]
    assert ticks[7]["withheld_reason"] == "deadline"
    assert ticks[7]["action_applied"] is False
    schema, channel, _ = messages["/openral/tick"][0]
    assert channel.message_encoding == "json"
    assert schema.name == "openral.Tick"

    joints = [json.loads(m.data) for _, _, m in messages["/joint_states"]]
    assert len(joints) == n  # one per tick that saw a joint state
    for i, msg in enumerate(joints):
        assert msg["tick_idx"] == i
        assert msg["name"] == NAMES
        assert msg["position"] == pytest.approx([0.01 * i, -0.02 * i, 0.5])
        assert msg["velocity"] == [1.0, -2.0, 0.0]

    safety = [json.loads(m.data) for _, _, m in messages["/openral/safety"]]
    assert [(e["tick_idx"], e["kind"], e["reason"]) for e in safety] == [
        (5, "safety_violation", "joint 'gripper' clamped"),
        (7, "action_withheld", "deadline"),
    ]

    # Log times are wall-clock nanoseconds, one per tick, non-decreasing; joint stamps keep monotonic spacing.
    log_times = [m.log_time for _, _, m in messages["/openral/tick"]]
    assert before_ns - 1_000_000_000 <= log_times[0] <= log_times[-1] <= after_ns + 1_000_000_000
    assert log_times == sorted(log_times)
    joint_ns = [msg["timestamp"]["sec"] * 1_000_000_000 + msg["timestamp"]["nsec"] for msg in joints]
    assert np.diff(joint_ns).tolist() == [STEP_NS] * (n - 1)

    # Two thumbnails handed over: each is published, or replaced by the newer one before the worker woke.
    images = messages["/camera/wrist/compressed"]
    assert sink.images_published + sink.images_replaced == 2
    assert len(images) == sink.images_published >= 1
    schema, _, message = images[0]
    assert schema.name == "foxglove.CompressedImage"
    assert b"jpeg" in message.data
    assert b"\xff\xd8\xff" in message.data  # the JPEG itself rides in the protobuf bytes field


def test_non_finite_actions_become_null(tmp_path: Path, sink_cls, read_mcap) -> None:
    path = tmp_path / "nan.mcap"
    with sink_cls(mcap_path=path) as sink:
        tick = make_tick(0, requested_action=[float("nan"), float("inf"), 0.5], safety_violations=["NaN in action"])
        sink.on_tick(tick, None)
    payloads = {topic: json.loads(entries[0][2].data) for topic, entries in read_mcap(path).items() if entries}
    assert payloads["/openral/tick"]["requested_action"] == [None, None, 0.5]
    assert payloads["/openral/safety"]["reason"] == "NaN in action"


def test_on_tick_never_blocks_when_the_worker_is_stalled(tmp_path: Path, sink_cls) -> None:
    sink = sink_cls(mcap_path=tmp_path / "stall.mcap", queue_size=16, close_timeout_s=5.0)
    entered = threading.Event()
    release = threading.Event()
    real_publish = sink._publish_tick

    def stalled(item) -> None:
        entered.set()
        release.wait(60)
        real_publish(item)

    sink._publish_tick = stalled
    world = make_world(0)
    sink.on_tick(make_tick(0), world)
    assert entered.wait(5), "worker never picked up the first tick"

    n = 2000
    ticks = [make_tick(i) for i in range(1, n + 1)]
    ticking = threading.Thread(target=lambda: [sink.on_tick(tick, world) for tick in ticks])
    ticking.start()
    ticking.join(30)  # microseconds each; an on_tick that waits for room waits for the release
    assert not ticking.is_alive(), "on_tick blocked on the stalled worker"
    assert sink.ticks_published == 0  # every on_tick returned while tick 0 was still held
    assert sink.dropped == n - 16  # the worker holds tick 0; the queue keeps the newest 16
    release.set()
    sink.close()
    assert sink.ticks_published == 1 + 16


def test_a_port_that_cannot_be_bound_names_the_flag(sink_cls) -> None:
    import socket  # noqa: PLC0415

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        sink = sink_cls(port=taken.getsockname()[1])  # building binds nothing: openral validate builds it
        try:
            assert sink.port is None
            with pytest.raises(ROSConfigError, match="--foxglove"):
                sink.start()
        finally:
            sink.close()


def test_building_binds_nothing_and_start_binds_once(sink_cls) -> None:
    import socket  # noqa: PLC0415

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free = probe.getsockname()[1]
    with sink_cls(port=free) as sink:
        with socket.socket() as other:
            other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
            other.bind(("127.0.0.1", free))  # the port is still free after building the sink
        assert sink.port is None
        sink.start()
        sink.start()  # idempotent
        assert sink.port == free


def test_live_server_streams_ticks_to_a_websocket_client(sink_cls) -> None:
    connect = pytest.importorskip("websockets.sync.client", reason="needs the websockets client (dev group)").connect

    with sink_cls(port=0, host="127.0.0.1") as sink:
        sink.start()
        assert sink.port
        assert sink.port > 0
        assert sink.app_url is not None
        # The SDK server speaks the Foxglove WebSocket protocol under the name foxglove.sdk.v1
        # (same messages as foxglove.websocket.v1); offer both, as the Foxglove app does.
        with connect(
            f"ws://127.0.0.1:{sink.port}",
            subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
            open_timeout=5,
            proxy=None,
        ) as ws:
            channels: dict[str, int] = {}
            deadline = time.monotonic() + 5
            while "/openral/tick" not in channels or "/joint_states" not in channels:
                assert time.monotonic() < deadline, f"channels not advertised, got {sorted(channels)}"
                frame = ws.recv(timeout=5)
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg["op"] == "advertise":
                        channels.update({c["topic"]: c["id"] for c in msg["channels"]})
            subscriptions = {1: "/openral/tick", 2: "/joint_states"}
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [{"id": sid, "channelId": channels[t]} for sid, t in subscriptions.items()],
                    }
                )
            )
            received: dict[str, dict] = {}
            i = 0
            deadline = time.monotonic() + 10
            while len(received) < 2:
                assert time.monotonic() < deadline, f"no message data received, got {sorted(received)}"
                sink.on_tick(make_tick(i), make_world(i, with_frame=False))
                i += 1
                try:
                    frame = ws.recv(timeout=0.05)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes) and frame[0] == 0x01:  # Message Data
                    sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                    received[subscriptions[sub_id]] = json.loads(frame[13:])
                    assert abs(log_time - time.time_ns()) < 5_000_000_000
            assert "tick_ms" in received["/openral/tick"]
            assert received["/joint_states"]["name"] == NAMES


def test_a_runner_observer_records_every_tick_and_closes_at_deactivate(tmp_path: Path, sink_cls, read_mcap) -> None:
    clock = FakeClock()
    joints = ["j0", "j1", "j2"]
    skill = ScriptedSkill(joints, on_step=lambda _i: clock.advance(0.002))
    skill.configure()
    skill.activate()
    camera = ScriptedReader("front", clock, width=32, height=24)
    runner = HardwareRunner(
        hal=RecordingHAL(joints, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(
            joint_max_age_ms=100.0, sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns
        ),
        sensor_readers=[camera],
        rate_hz=30.0,
        clock=clock,
    )
    path = tmp_path / "deploy.mcap"
    sink = sink_cls(mcap_path=path)
    runner.observers.append(sink)  # before activate: deactivate closes it
    runner.activate()
    runner.run(30)
    runner.deactivate()

    messages = read_mcap(path)  # readable: deactivate finished the file
    ticks = [json.loads(m.data) for _, _, m in messages["/openral/tick"]]
    assert [t["tick_idx"] for t in ticks] == list(range(30))
    assert [t["tick_ms"] for t in ticks][-len(runner.recent_ticks) :] == [t.tick_ms for t in runner.recent_ticks]
    assert ticks[0]["inference_ms"] == pytest.approx(2.0)
    assert len(messages["/joint_states"]) == 30
    assert json.loads(messages["/joint_states"][0][2].data)["name"] == joints
    assert messages["/camera/front/compressed"]


def test_one_jpeg_encode_serves_the_thumbnail_span_and_the_foxglove_view(tmp_path: Path, sink_cls, read_mcap) -> None:
    clock = FakeClock()
    joints = ["j0", "j1", "j2"]
    skill = ScriptedSkill(joints)
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        hal=RecordingHAL(joints, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns),
        sensor_readers=[ScriptedReader("front", clock, width=32, height=24)],
        rate_hz=30.0,
        clock=clock,
        thumbnail_hz=1000.0,  # every frame is due: the schedule runs on the real clock
    )
    spans: list[object] = []
    (thumbnails,) = [o for o in runner.observers if isinstance(o, ThumbnailPublisher)]
    thumbnails._sinks[0] = spans.append  # the dashboard span sink, observed
    sink = sink_cls(mcap_path=tmp_path / "view.mcap")
    runner.observers.append(sink)
    runner.activate()
    runner.run(10)
    runner.deactivate()
    encoded = thumbnails.encoded
    assert encoded >= 1
    assert len(spans) == encoded  # every encoded thumbnail reached the span sink ...
    assert sink.images_published + sink.images_replaced == encoded  # ... and the view, from the same encode
    assert len(read_mcap(tmp_path / "view.mcap")["/camera/front/compressed"]) == sink.images_published


def test_a_deployment_configures_the_view_and_the_bag_in_its_observers_block(
    tmp_path: Path, sink_cls, read_mcap
) -> None:
    import subprocess  # noqa: PLC0415
    import sys  # noqa: PLC0415

    deployment = tmp_path / "view.yaml"
    deployment.write_text(
        "name: view\nrate_hz: 50\nhal: {robot_id: so101_follower, adapter: null}\nvla: {id: noop}\n"
        "safety: {client: envelope}\nobservers:\n  - id: foxglove\n    params: {port: 0}\n"
        "  - id: ros2_bag\n    params: {path: out/run.mcap}\n"
    )
    (tmp_path / "out").mkdir()
    run = subprocess.run(
        [sys.executable, "-m", "openral_cli", "deploy", "--config", str(deployment), "--max-ticks", "20", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    ticks = read_mcap(tmp_path / "out" / "run.mcap")["/openral/tick"]
    assert len(ticks) == 20

    deployment.write_text(deployment.read_text().replace("port: 0", "port: 0, fps: 3"))
    bad = subprocess.run(
        [sys.executable, "-m", "openral_cli", "validate", str(deployment)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert bad.returncode == 2
    assert "fps" in bad.stderr


def every_field_set() -> TickResult:
    """A tick with a value (not the default, not ``None``) in every field."""
    tick = make_tick(
        3,
        start_ns=5,
        withheld_reason="safety",
        safety_violations=["joint 'gripper' clamped"],
        stale_sensors=["front"],
        deadline_missed=True,
        lateness_ms=0.7,
        trace_context="00-" + "a" * 32 + "-" + "b" * 16 + "-01",
        step_idx=2,
        episode_idx=1,
        reward=0.25,
        terminated=True,
        truncated=True,
        intervention=True,
        active_skill="leader_arm",
        policy_action=[0.25, 0.5],
        handover_ramp=True,
    )
    unset = [name for name, info in TickResult.model_fields.items() if getattr(tick, name) == info.get_default()]
    assert unset == [], f"the probe leaves {unset} at their defaults"
    return tick


def test_a_tick_message_is_the_tick_result_under_the_tick_result_schema(tmp_path: Path, sink_cls, read_mcap) -> None:
    jsonschema = pytest.importorskip("jsonschema", reason="needs jsonschema (dev group)")
    path = tmp_path / "fields.mcap"
    tick = every_field_set()
    with sink_cls(mcap_path=path) as sink:
        sink.on_tick(tick, None)
    messages = read_mcap(path)
    ((schema, _, message),) = messages["/openral/tick"]
    payload = json.loads(message.data)
    assert {k: v for k, v in payload.items() if k not in ("timestamp", "dropped")} == tick.model_dump(mode="json")
    assert schema.encoding == "jsonschema"
    declared = json.loads(schema.data)
    assert set(declared["properties"]) == {"timestamp", "dropped", *TickResult.model_fields}
    for keyword in ("$ref", "anyOf"):  # the plain dialect a viewer reads
        assert keyword not in schema.data.decode()
    jsonschema.validate(payload, declared)
    jsonschema.validate({**payload, "withheld_reason": None, "reward": None}, declared)
    events = messages["/openral/safety"]
    assert [json.loads(m.data)["kind"] for _, _, m in events] == ["safety_violation", "action_withheld"]
    for event_schema, _, event in events:
        jsonschema.validate(json.loads(event.data), json.loads(event_schema.data))


def test_camera_images_do_not_wait_behind_a_stalled_tick_worker(tmp_path: Path, sink_cls) -> None:
    sink = sink_cls(mcap_path=tmp_path / "images.mcap")
    entered = threading.Event()
    release = threading.Event()
    real_publish = sink._publish_tick

    def stalled(item) -> None:
        entered.set()
        release.wait(60)
        real_publish(item)

    sink._publish_tick = stalled
    sink.on_tick(make_tick(0), make_world(0))
    assert entered.wait(5), "worker never picked up the first tick"
    frame = make_world(1).image_frames["wrist"]  # type: ignore[index]
    sink.on_thumbnail(encode_thumbnail(frame))
    deadline = time.monotonic() + 5
    while sink.images_published < 1:
        assert time.monotonic() < deadline, "the image waited for the tick worker"
        time.sleep(0.005)
    release.set()
    sink.close()
    assert (sink.ticks_published, sink.images_published, sink.publish_errors) == (1, 1, 0)


def test_a_queue_smaller_than_two_names_the_parameter(sink_cls) -> None:
    with pytest.raises(ROSConfigError, match="queue_size"):
        sink_cls(queue_size=1)
