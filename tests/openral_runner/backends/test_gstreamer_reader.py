"""GStreamerSensorReader over real GStreamer pipelines (needs PyGObject and the GStreamer apt packages)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from openral_core import (
    FrameEncoding,
    ROSConfigError,
    ROSPerceptionStale,
    ROSRuntimeError,
    SensorReaderConfig,
)
from openral_runner.backends.gstreamer.pipeline import TEE_NAME, PipelineSpec
from openral_runner.sensor_reader import SensorReader

pytestmark = pytest.mark.gstreamer

pytest.importorskip(
    "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
)
try:
    reader_module = importlib.import_module("openral_runner.backends.gstreamer.reader")
except ROSConfigError as exc:  # gi present, GStreamer typelibs missing
    pytest.skip(f"GStreamer introspection data missing: {exc}", allow_module_level=True)

from gi.repository import Gst  # noqa: E402

GStreamerSensorReader = reader_module.GStreamerSensorReader

SOLID = "foreground-color=0xff102030"  # ARGB: R=0x10 G=0x20 B=0x30
BGR = (0x30, 0x20, 0x10)
CLIP_COLOR = "foreground-color=0xff4080c0"  # mid-range colour: survives JPEG/H.264 with small error
CLIP_BGR = (0xC0, 0x80, 0x40)


def wait_for(predicate, timeout_s: float = 3.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.005)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def first_frame(reader, timeout_s: float = 3.0):
    def attempt():
        try:
            return reader.read_latest(max_age_ms=1e9)
        except ROSPerceptionStale:
            return None

    return wait_for(attempt, timeout_s, f"a frame from {reader.sensor_id}")


def live_pipeline(width: int, height: int, *, fmt: str = "BGR", extra: str = "", fps: int = 30) -> str:
    return (
        f"videotestsrc is-live=true {extra} ! video/x-raw,width={width},height={height},framerate={fps}/1 ! "
        f"videoconvert ! video/x-raw,format={fmt} ! appsink"
    )


def write_video(path: Path, encoder: str, *, frames: int = 15, width: int = 96, height: int = 64) -> Path:
    """Encode a short clip with GStreamer itself (15 frames at 30 fps = 0.5 s)."""
    pipeline = Gst.parse_launch(
        f"videotestsrc num-buffers={frames} pattern=solid-color {CLIP_COLOR} ! "
        f"video/x-raw,width={width},height={height},framerate=30/1 ! {encoder} ! filesink location={path}"
    )
    pipeline.set_state(Gst.State.PLAYING)
    message = pipeline.get_bus().timed_pop_filtered(10 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    pipeline.set_state(Gst.State.NULL)
    assert message is not None, f"writing {path} timed out"
    assert message.type == Gst.MessageType.EOS, f"could not write {path}: {message.parse_error()[0].message}"
    return path


def assert_clip_pixels(pixels: np.ndarray) -> None:
    """A decoded solid-colour clip: every row alike (no stride drift), the colour close (lossy codecs)."""
    values = pixels[:, :-16].astype(int)  # the last, partial 16-pixel block carries codec edge noise
    assert np.abs(values - values[:1]).max() <= 2, "rows drift: the row stride was ignored"
    assert np.abs(np.median(values, axis=(0, 1)) - CLIP_BGR).max() <= 16


def has(element: str) -> bool:
    return Gst.ElementFactory.find(element) is not None


# -- live test source --------------------------------------------------------------------------


def test_live_testsrc_delivers_declared_size_at_the_requested_rate() -> None:
    spec = PipelineSpec(source="testsrc", width=320, height=240, fps=30)
    reader = GStreamerSensorReader(sensor_id="front", spec=spec, default_max_age_ms=200)
    assert isinstance(reader, SensorReader)
    opened_ns = time.monotonic_ns()
    with reader:
        assert reader.is_open
        first = first_frame(reader)
        time.sleep(1.0)
        latest = reader.read_latest()
        read_ns = time.monotonic_ns()
        fps = reader.delivered_fps
    assert not reader.is_open
    assert latest.as_array().shape == (240, 320, 3)
    assert latest.encoding is FrameEncoding.BGR8
    frames = latest.seq - first.seq
    assert frames >= 15, f"only {frames} frames in 1 s at 30 fps"  # > 50 %: holds on a loaded machine
    assert 15 < fps < 45
    # Capture stamps, not arrival times: they lie on the source's 1/30 s grid, one step or more per
    # frame delivered (more when the sink dropped one), however late each frame arrived.
    periods = (latest.stamp_ns - first.stamp_ns) * 30 / 1e9
    assert abs(periods - round(periods)) < 1e-3, f"stamps {periods:.3f} frame periods apart: not the capture grid"
    assert round(periods) >= frames, "stamps follow the capture rate"
    assert latest.stamp_ns - first.stamp_ns <= read_ns - opened_ns, "stamps run faster than the clock"


def test_capture_stamps_are_monotonic_clock_times_and_frames_are_fresh() -> None:
    with GStreamerSensorReader(sensor_id="cam", pipeline=live_pipeline(64, 48)) as reader:
        first_frame(reader)
        ages, stamps = [], []
        for _ in range(20):
            time.sleep(0.011)
            now = time.monotonic_ns()
            frame = reader.read_latest()
            ages.append(frame.age_ms(time.monotonic_ns()))
            stamps.append(frame.stamp_ns)
            assert frame.stamp_ns <= now
    assert stamps == sorted(stamps)
    assert float(np.median(ages)) < 100.0, f"p50 age {np.median(ages):.1f} ms"


@pytest.mark.parametrize("width", [161, 160, 1])
def test_odd_width_bgr_gives_exact_pixels(width: int) -> None:
    pipeline = live_pipeline(width, 5, extra=f"pattern=solid-color {SOLID}")
    with GStreamerSensorReader(sensor_id="cam", pipeline=pipeline, width=width, height=5) as reader:
        frame = first_frame(reader)
    pixels = frame.as_array()
    assert pixels.shape == (5, width, 3)
    assert pixels.size == width * 5 * 3
    expected = np.empty((5, width, 3), np.uint8)
    expected[:] = BGR
    assert np.array_equal(pixels, expected), "row padding leaked into the pixels"
    assert np.shares_memory(pixels, frame.data), "as_array() is a view over the captured buffer"
    assert frame.data_bytes() == expected.tobytes()


def test_odd_width_rgb_and_gray_and_a_structured_pattern() -> None:
    rgb_pipeline = live_pipeline(161, 4, fmt="RGB", extra=f"pattern=solid-color {SOLID}")
    with GStreamerSensorReader(sensor_id="rgb", pipeline=rgb_pipeline) as reader:
        rgb = first_frame(reader)
    assert rgb.encoding is FrameEncoding.RGB8
    assert np.all(rgb.as_array() == (0x10, 0x20, 0x30))

    # SMPTE bars are vertical: every row of the top part is the same, and columns differ.
    with GStreamerSensorReader(sensor_id="gray", pipeline=live_pipeline(161, 30, fmt="GRAY8")) as reader:
        gray = first_frame(reader)
    with GStreamerSensorReader(sensor_id="bars", pipeline=live_pipeline(161, 30)) as reader:
        bars = first_frame(reader)
    assert gray.encoding is FrameEncoding.MONO8
    assert gray.as_array().shape == (30, 161)
    for frame in (gray, bars):
        top = frame.as_array()[:10]
        assert (top == top[0]).all(), "rows drift: the row stride was ignored"
        assert len(np.unique(top[0].reshape(161, -1), axis=0)) >= 5


def test_producer_video_meta_stride_and_offset_are_honoured() -> None:
    """A producer may lay rows out its own way (e.g. a camera's 20-byte rows at offset 8)."""
    from gi.repository import GstVideo  # noqa: PLC0415 - available once the reader imported

    width, height, stride, offset = 5, 3, 20, 8
    raw = np.zeros(offset + stride * height, np.uint8)
    expected = np.arange(height * width * 3, dtype=np.uint8).reshape(height, width, 3)
    for row in range(height):
        start = offset + row * stride
        raw[start : start + width * 3] = expected[row].reshape(-1)
        raw[start + width * 3 : start + stride] = 255  # padding that must not show
    pipeline = (
        f"appsrc name=src is-live=true format=time caps=video/x-raw,format=BGR,width={width},height={height},"
        "framerate=0/1 ! appsink"
    )
    with GStreamerSensorReader(sensor_id="cam", pipeline=pipeline) as reader:
        buffer = Gst.Buffer.new_wrapped(raw.tobytes())
        buffer.pts = 0
        GstVideo.buffer_add_video_meta_full(
            buffer,
            GstVideo.VideoFrameFlags.NONE,
            GstVideo.VideoFormat.BGR,
            width,
            height,
            1,
            [offset, 0, 0, 0],
            [stride, 0, 0, 0],
        )
        reader._pipeline.get_by_name("src").emit("push-buffer", buffer)
        frame = first_frame(reader)
    assert np.array_equal(frame.as_array(), expected)


def test_declared_size_mismatch_fails_the_reader() -> None:
    with GStreamerSensorReader(sensor_id="cam", pipeline=live_pipeline(64, 48), width=640, height=480) as reader:
        error = wait_for(lambda: reader._slot.error, what="size mismatch")
        with pytest.raises(ROSRuntimeError, match="delivers 64x48, the sensor declares 640x480"):
            reader.read_latest()
    assert isinstance(error, ROSRuntimeError)


# -- lifecycle ---------------------------------------------------------------------------------


def test_open_close_idempotent_and_reopen() -> None:
    reader = GStreamerSensorReader(sensor_id="cam", pipeline=live_pipeline(32, 24))
    with pytest.raises(ROSRuntimeError, match="closed"):
        reader.read_latest()
    reader.open()
    reader.open()
    first = first_frame(reader)
    reader.close()
    reader.close()
    with pytest.raises(ROSRuntimeError, match="closed"):
        reader.read_latest()
    reader.open()
    try:
        again = first_frame(reader)
        assert again.seq == 0
        assert again.stamp_ns > first.stamp_ns
    finally:
        reader.close()


def test_read_synced_waits_for_a_newer_frame() -> None:
    with GStreamerSensorReader(sensor_id="cam", pipeline=live_pipeline(32, 24)) as reader:
        frame = first_frame(reader)
        newer = reader.read_synced(time.monotonic_ns() + 500_000_000, newer_than_ns=frame.stamp_ns)
        assert newer.stamp_ns > frame.stamp_ns
        with pytest.raises(ROSPerceptionStale):
            reader.read_synced(time.monotonic_ns() + 10_000_000, newer_than_ns=time.monotonic_ns() + 10**12)


_WRAPPED_FIRST = textwrap.dedent(
    """
    import sys, time
    import gi
    gi.require_version("Gst", "1.0")
    from gi.repository import Gst
    Gst.init(None)
    from openral_runner.backends.gstreamer.pipeline import PipelineSpec, build_pipeline_string

    spec = PipelineSpec(source="testsrc", width=32, height=24, fps=30)
    probe = Gst.parse_launch(build_pipeline_string(spec))  # the application looks at openral's pipeline first
    sink = probe.get_by_name(spec.appsink_name)
    assert "gi.repository.GstApp" not in sys.modules and not hasattr(sink, "pull_sample"), type(sink)
    probe.set_state(Gst.State.NULL)

    from openral_runner.backends.gstreamer.reader import GStreamerSensorReader

    with GStreamerSensorReader(sensor_id="cam0", spec=spec) as reader:
        frame = reader.read_synced(time.monotonic_ns() + 10_000_000_000)  # returns on the first frame
    print("frame", frame.as_array().shape)
    """
)


def test_frames_flow_when_the_application_wrapped_an_appsink_before_the_reader_was_imported() -> None:
    # Which Python class wraps an appsink is fixed once per process: only a fresh one shows it.
    done = subprocess.run(
        [sys.executable, "-c", _WRAPPED_FIRST], check=False, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "frame (24, 32, 3)" in done.stdout


def test_tee_legs_do_not_slow_the_policy_leg() -> None:
    spec = PipelineSpec(
        source="testsrc", width=160, height=120, enable_ros_tee=True, ros_rate_hz=5, enable_event_tee=True
    )
    with GStreamerSensorReader(sensor_id="cam", spec=spec) as reader:
        assert f"tee name={TEE_NAME}" in reader.pipeline_string
        first = first_frame(reader)
        time.sleep(0.5)
        latest = reader.read_latest()
    assert latest.seq - first.seq >= 7  # 15 expected at 30 fps; the unread ROS/event sinks drop
    assert latest.as_array().shape == (120, 160, 3)


# -- files -------------------------------------------------------------------------------------


def test_file_plays_at_real_rate_and_eos_serves_the_last_frame_until_stale(tmp_path: Path) -> None:
    clip = write_video(tmp_path / "clip.avi", "jpegenc ! avimux")
    spec = PipelineSpec(source="file", device=str(clip), encoded="mjpeg", width=96, height=64)
    reader = GStreamerSensorReader(sensor_id="file", spec=spec, default_max_age_ms=250)
    assert "avidemux ! jpegdec" in reader.pipeline_string
    with reader:
        started = time.monotonic()
        first = first_frame(reader)
        wait_for(lambda: reader.eos, timeout_s=3.0, what="end of stream")
        played_s = time.monotonic() - started
        last = reader.read_latest()  # within the budget: still served
        assert last.seq >= 10
        assert last.seq > first.seq
        assert_clip_pixels(last.as_array())
        assert played_s > 0.3, f"15 frames at 30 fps took {played_s:.2f} s: not played at real rate"
        wait_for(lambda: last.age_ms(time.monotonic_ns()) > 260, timeout_s=2.0, what="the frame to age")
        with pytest.raises(ROSPerceptionStale):
            reader.read_latest()


def test_file_through_decodebin(tmp_path: Path) -> None:
    clip = write_video(tmp_path / "clip.avi", "jpegenc ! avimux", width=162, height=16)  # 486-byte rows, padded
    spec = PipelineSpec(source="file", device=str(clip))
    with GStreamerSensorReader(sensor_id="file", spec=spec, default_max_age_ms=1000) as reader:
        frame = first_frame(reader)
    assert frame.as_array().shape == (16, 162, 3)
    assert_clip_pixels(frame.as_array())


@pytest.mark.skipif(not has("openh264enc") or not has("avdec_h264"), reason="needs openh264enc and avdec_h264")
def test_h264_mp4_file_through_qtdemux(tmp_path: Path) -> None:
    clip = write_video(tmp_path / "clip.mp4", "openh264enc ! h264parse ! mp4mux", width=160, height=96)
    spec = PipelineSpec(source="file", device=str(clip), encoded="h264")
    with GStreamerSensorReader(sensor_id="mp4", spec=spec, platform="cpu_only", default_max_age_ms=1000) as reader:
        assert "qtdemux ! h264parse ! avdec_h264" in reader.pipeline_string
        frame = first_frame(reader)
    assert frame.as_array().shape == (96, 160, 3)
    assert_clip_pixels(frame.as_array())


# -- errors ------------------------------------------------------------------------------------


def test_missing_file_fails_open_naming_the_element() -> None:
    reader = GStreamerSensorReader(sensor_id="cam", pipeline="filesrc location=/nonexistent.avi ! decodebin ! appsink")
    with pytest.raises(
        ROSRuntimeError,
        match=r"the pipeline failed to start: GStreamer element 'filesrc\d+' failed.*No such file.*nonexistent",
    ) as info:
        reader.open()
    assert not isinstance(info.value, ROSConfigError)
    assert not reader.is_open


def test_bus_error_while_streaming_surfaces_on_read(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.avi"
    garbage.write_bytes(b"this is not a video" * 100)
    with GStreamerSensorReader(sensor_id="cam", spec=PipelineSpec(source="file", device=str(garbage))) as reader:
        wait_for(lambda: reader._slot.error, what="the bus error")
        with pytest.raises(ROSRuntimeError, match=r"sensor 'cam': GStreamer element '\w+' failed"):
            reader.read_latest()


def test_error_after_frames_beats_a_fresh_frame() -> None:
    pipeline = (
        "videotestsrc is-live=true ! video/x-raw,format=BGR,width=32,height=24,framerate=30/1 ! "
        "identity error-after=8 ! appsink"
    )
    with GStreamerSensorReader(sensor_id="cam", pipeline=pipeline, default_max_age_ms=5000) as reader:
        first_frame(reader)

        def failed() -> bool:
            try:
                reader.read_latest()
            except ROSRuntimeError as exc:
                return not isinstance(exc, ROSPerceptionStale)
            return False

        wait_for(failed, what="the identity error")
        with pytest.raises(ROSRuntimeError, match="identity0"):
            reader.read_latest()


def test_unsupported_format_is_rejected_at_open() -> None:
    reader = GStreamerSensorReader(sensor_id="cam", pipeline="videotestsrc ! video/x-raw,format=I420 ! appsink")
    with pytest.raises(ROSConfigError, match=r"delivers format I420.*takes BGR, RGB, GRAY8") as info:
        reader.open()
    assert "videoconvert" in str(info.value)
    assert not reader.is_open
    sink_caps = GStreamerSensorReader(sensor_id="cam", pipeline="videotestsrc ! appsink caps=video/x-raw,format=NV12")
    with pytest.raises(ROSConfigError, match="allow none of the formats"):
        sink_caps.open()


def test_any_capable_upstream_is_narrowed_to_a_supported_format() -> None:
    with GStreamerSensorReader(sensor_id="cam", pipeline="videotestsrc is-live=true ! appsink") as reader:
        frame = first_frame(reader)
    assert frame.encoding in (FrameEncoding.BGR8, FrameEncoding.RGB8, FrameEncoding.MONO8)


def test_parse_errors_are_config_errors_with_an_install_hint() -> None:
    reader = GStreamerSensorReader(sensor_id="cam", pipeline="videotestsrc ! avdec_nothing ! appsink")
    with pytest.raises(ROSConfigError, match=r"sensor 'cam'.*no element \"avdec_nothing\".*gstreamer1.0-libav"):
        reader.open()
    wrong_name = GStreamerSensorReader(sensor_id="cam", pipeline="videotestsrc ! appsink name=x", appsink_name="x")
    wrong_name.pipeline_string = "videotestsrc ! fakesink name=x"
    with pytest.raises(ROSConfigError, match="FakeSink, not an appsink"):
        wrong_name.open()


def test_spec_and_pipeline_are_exclusive() -> None:
    spec = PipelineSpec(source="testsrc")
    with pytest.raises(ROSConfigError, match="exactly one of spec"):
        GStreamerSensorReader(sensor_id="cam", spec=spec, pipeline=live_pipeline(8, 8))
    with pytest.raises(ROSConfigError, match="exactly one of spec"):
        GStreamerSensorReader(sensor_id="cam")
    with pytest.raises(ROSConfigError, match="no appsink"):
        GStreamerSensorReader(sensor_id="cam", pipeline="videotestsrc ! fakesink")


# -- from_config -------------------------------------------------------------------------------


def sensor(**fields) -> SensorReaderConfig:
    return SensorReaderConfig(sensor_id="cam", backend="gstreamer", **fields)


def from_config(config: SensorReaderConfig, **kwargs):
    return GStreamerSensorReader.from_config(config, hal=None, robot=None, **kwargs)


def test_from_config_builds_a_spec_from_the_sensor_fields() -> None:
    config = sensor(
        width=161,
        height=9,
        fps=15,
        encoding="rgb8",
        max_age_ms=300,
        publish_to_ros=True,
        publish_topic="/cam/image",
        publish_rate_hz=5,
        backend_params={"source": "testsrc", "pattern": "solid-color", "platform": "cpu_only"},
    )
    reader = from_config(config)
    assert reader.spec == PipelineSpec(
        source="testsrc",
        width=161,
        height=9,
        fps=15,
        pattern="solid-color",
        enable_ros_tee=True,
        ros_rate_hz=5,
        output_format="RGB",
    )
    assert "framerate=15/1" in reader.pipeline_string
    assert "ros_sink" in reader.pipeline_string
    with reader:
        frame = first_frame(reader)
    assert frame.as_array().shape == (9, 161, 3)
    assert frame.encoding is FrameEncoding.RGB8


def test_from_config_raw_pipeline_and_relative_file(tmp_path: Path) -> None:
    raw = from_config(sensor(backend_params={"pipeline": live_pipeline(8, 8), "appsink_name": "front"}))
    assert raw.pipeline_string.endswith("appsink name=front")
    write_video(tmp_path / "clip.avi", "jpegenc ! avimux", frames=2)
    built = from_config(sensor(backend_params={"source": "file", "device": "clip.avi"}), base_dir=tmp_path)
    assert f'location="{tmp_path / "clip.avi"}"' in built.pipeline_string


@pytest.mark.parametrize(
    ("fields", "field", "message"),
    [
        ({"backend_params": {"source": "testsrc", "patern": "ball"}}, "sensors[cam].backend_params.patern", "pattern"),
        ({"backend_params": {}}, "sensors[cam].backend_params", "exactly one of pipeline"),
        (
            {"backend_params": {"pipeline": "videotestsrc ! appsink", "source": "usb"}},
            "sensors[cam].backend_params",
            "exactly one of pipeline",
        ),
        (
            {"backend_params": {"pipeline": "videotestsrc ! appsink", "encoded": "h264"}},
            "sensors[cam].backend_params",
            "encoded only apply to a built pipeline",
        ),
        ({"backend_params": {"source": "usb"}}, "sensors[cam].backend_params", "needs device"),
        ({"backend_params": {"source": "webcam"}}, "sensors[cam].backend_params.source", "usb"),
        (
            {"backend_params": {"source": "testsrc", "appsink_name": "a b"}},
            "sensors[cam].backend_params.appsink_name",
            "element name",
        ),
        ({"encoding": "rgba8", "backend_params": {"source": "testsrc"}}, "sensors[cam].encoding", "rgba8"),
        (
            {"backend_params": {"source": "csi", "platform": "cpu_only"}},
            "sensors[cam].backend_params.source",
            "Jetson",
        ),
        (
            {"publish_to_ros": True, "publish_topic": "/x", "backend_params": {"pipeline": "videotestsrc ! appsink"}},
            "sensors[cam].publish_to_ros",
            "raw pipeline",
        ),
    ],
)
def test_from_config_errors_name_the_field(fields: dict, field: str, message: str) -> None:
    with pytest.raises(ROSConfigError, match=message) as info:
        from_config(sensor(**fields))
    assert info.value.field == field
    assert str(info.value).startswith(f"{field}: ")


def test_from_config_unknown_key_lists_the_allowed_keys() -> None:
    with pytest.raises(ROSConfigError) as info:
        from_config(sensor(backend_params={"source": "testsrc", "patern": "ball"}))
    text = str(info.value)
    assert "unknown key 'patern'" in text
    assert "allowed keys:" in text
    assert "pipeline" in text
    assert "source" in text
    assert info.value.hint == "did you mean 'pattern'?"


def test_explicit_platform_missing_here_is_named_when_the_deployment_is_built() -> None:
    if has("nvh264dec"):
        pytest.skip("this host has NVIDIA's decoder; the case is a host without it")
    config = sensor(backend_params={"source": "rtsp", "device": "rtsp://cam/s", "platform": "nvidia_desktop"})
    with pytest.raises(ROSConfigError, match="nvh264dec") as info:
        from_config(config)
    assert info.value.field is not None
    assert info.value.field.startswith("sensors[cam]")
