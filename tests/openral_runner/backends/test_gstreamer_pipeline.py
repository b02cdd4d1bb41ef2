"""GStreamer pipeline builder: element choices per source and platform, tee legs, appsink naming.

Pure Python; only the parse check at the end needs PyGObject and skips without it.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

import pytest
import structlog

from openral_core import ROSConfigError
from openral_core.config import validate_model
from openral_runner.backends.gstreamer import pipeline as gp
from openral_runner.backends.gstreamer.pipeline import (
    LEAKY_BRANCH_QUEUE,
    TEE_NAME,
    Codec,
    PipelineSpec,
    PixelFormat,
    Platform,
    Source,
    build_pipeline_string,
    detect_platform,
    ensure_appsink_name,
    inspect_element_present,
    leaky_branch,
    nvmm_convert_element,
)


def everything(_name: str) -> bool:
    return True


def nothing(_name: str) -> bool:
    return False


def build(platform: Platform, probe=everything, **fields) -> str:
    return build_pipeline_string(PipelineSpec(**fields), platform, element_present=probe)


def elements(pipeline: str) -> list[str]:
    """First word of every ``!``-separated part (element names and caps)."""
    return [part.split()[0] for part in pipeline.replace("  ", " ! ").split(" ! ") if part.strip()]


DEVICES = {
    Source.TESTSRC: None,
    Source.USB: "/dev/video0",
    Source.CSI: "0",
    Source.RTSP: "rtsp://127.0.0.1:8554/cam",
    Source.FILE: "/tmp/clip.mp4",
}
ENCODINGS = {
    Source.TESTSRC: [None],
    Source.CSI: [None],
    Source.USB: [None, Codec.MJPEG, Codec.H264],
    Source.RTSP: [None, Codec.H264, Codec.H265, Codec.MJPEG],
    Source.FILE: [None, Codec.H264, Codec.H265, Codec.MJPEG],
}
CASES = [(source, codec) for source, codecs in ENCODINGS.items() for codec in codecs]


def spec_fields(source: Source, codec: Codec | None, **extra) -> dict:
    return {"source": source, "device": DEVICES[source], "encoded": codec, "width": 320, "height": 240, **extra}


# -- constants and the branch primitive --------------------------------------------------------


def test_constants_and_leaky_branch() -> None:
    assert TEE_NAME == "openral_cam_tee"
    assert LEAKY_BRANCH_QUEUE == "queue leaky=downstream max-size-buffers=2"
    assert leaky_branch("fakesink") == "openral_cam_tee. ! queue leaky=downstream max-size-buffers=2 ! fakesink"
    assert leaky_branch("fakesink", tee_name="t").startswith("t. ! queue leaky=downstream")


def test_importing_the_builder_loads_no_gi() -> None:
    code = "import sys, openral_runner.backends.gstreamer, openral_runner.backends.gstreamer.params; "
    code += "print('gi' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.strip() == "False"


# -- PipelineSpec validation -------------------------------------------------------------------


@pytest.mark.parametrize("source", [Source.USB, Source.RTSP, Source.FILE])
def test_device_is_required_for_usb_rtsp_file(source: Source) -> None:
    with pytest.raises(ValueError, match=f"source {source.value} needs device"):
        PipelineSpec(source=source)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"source": "testsrc", "device": "/dev/video0"}, "testsrc takes no device"),
        ({"source": "testsrc", "encoded": "h264"}, "raw video"),
        ({"source": "csi", "device": "/dev/video0"}, "numeric sensor id"),
        ({"source": "testsrc", "width": 640}, "both width and height"),
        ({"source": "testsrc", "event_appsink_name": "bad name"}, "not a valid GStreamer element name"),
        ({"source": "testsrc", "appsink_name": "sink.0"}, "not a valid GStreamer element name"),
        ({"source": "testsrc", "enable_ros_tee": True, "ros_appsink_name": "openral_sink"}, "must differ"),
        ({"source": "testsrc", "appsink_name": TEE_NAME}, "must differ"),
        ({"source": "testsrc", "pattern": "ball ! fakesink"}, "not a videotestsrc pattern"),
        ({"source": "testsrc", "colour": "red"}, "Extra inputs are not permitted"),
        ({"source": "testsrc", "fps": 0}, "greater than 0"),
    ],
)
def test_spec_rejects_inconsistent_fields(fields: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PipelineSpec(**fields)


def test_spec_defaults() -> None:
    spec = PipelineSpec(source="testsrc")
    assert (spec.appsink_name, spec.ros_appsink_name, spec.event_appsink_name) == (
        "openral_sink",
        "ros_sink",
        "event_sink",
    )
    assert spec.output_format is PixelFormat.BGR
    assert spec.max_buffers == 1
    assert spec.is_live
    assert not PipelineSpec(source="file", device="/x.mp4").is_live


# -- platform detection ------------------------------------------------------------------------


def test_detect_platform(tmp_path: Path) -> None:
    release = tmp_path / "nv_tegra_release"
    assert detect_platform(release, everything) is Platform.NVIDIA_DESKTOP
    assert detect_platform(release, nothing) is Platform.CPU_ONLY
    release.write_text("# R36 (release)\n")
    assert detect_platform(release, nothing) is Platform.CPU_ONLY, "cached: the platform does not change"
    detect_platform.cache_clear()
    assert detect_platform(release, nothing) is Platform.TEGRA
    asked: list[str] = []

    def probe(name: str) -> bool:
        asked.append(name)
        return False

    assert detect_platform(tmp_path / "absent", probe) is Platform.CPU_ONLY
    assert asked == ["nvh264dec"]


def test_inspect_element_present_without_the_tool(monkeypatch: pytest.MonkeyPatch) -> None:
    inspect_element_present.cache_clear()
    monkeypatch.setattr(gp.shutil, "which", lambda _tool: None)
    try:
        assert inspect_element_present("videotestsrc") is False
    finally:
        inspect_element_present.cache_clear()


def test_inspect_element_present_times_out_as_absent(monkeypatch: pytest.MonkeyPatch) -> None:
    def slow(*args, **kwargs):
        raise subprocess.TimeoutExpired(cmd=args[0], timeout=kwargs["timeout"])

    inspect_element_present.cache_clear()
    monkeypatch.setattr(gp.shutil, "which", lambda _tool: "/usr/bin/gst-inspect-1.0")
    monkeypatch.setattr(gp.subprocess, "run", slow)
    try:
        assert inspect_element_present("videotestsrc", timeout_s=0.01) is False
    finally:
        inspect_element_present.cache_clear()


def test_inspect_element_present_on_this_host() -> None:
    if gp.shutil.which("gst-inspect-1.0") is None:
        pytest.skip("gst-inspect-1.0 is not installed (apt-get install gstreamer1.0-tools)")
    assert inspect_element_present("videotestsrc") is True
    assert inspect_element_present("openral_no_such_element") is False


def test_nvmm_convert_element_preference() -> None:
    assert nvmm_convert_element(everything) == "nvvideoconvert"
    assert nvmm_convert_element(lambda name: name == "nvvidconv") == "nvvidconv"
    assert nvmm_convert_element(nothing) is None


# -- appsink naming ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("pipeline", "expected"),
    [
        ("videotestsrc ! appsink", "videotestsrc ! appsink name=cam"),
        ("videotestsrc ! appsink sync=false", "videotestsrc ! appsink sync=false name=cam"),
        ("videotestsrc ! appsink name=mine drop=true", "videotestsrc ! appsink name=cam drop=true"),
        ('videotestsrc ! appsink name="mine"', "videotestsrc ! appsink name=cam"),
        ("videotestsrc ! appsink name=cam", "videotestsrc ! appsink name=cam"),
        (
            "videotestsrc ! tee name=t  t. ! queue ! appsink name=cam  t. ! queue ! appsink",
            "videotestsrc ! tee name=t  t. ! queue ! appsink name=cam  t. ! queue ! appsink",
        ),
        (
            "videotestsrc ! tee name=t  t. ! queue ! appsink  t. ! queue ! appsink max-buffers=1",
            "videotestsrc ! tee name=t  t. ! queue ! appsink  t. ! queue ! appsink max-buffers=1 name=cam",
        ),
        (
            'filesrc location="/tmp/appsink ! x.avi" ! decodebin ! videoconvert ! video/x-raw,format=BGR ! appsink',
            'filesrc location="/tmp/appsink ! x.avi" ! decodebin ! videoconvert ! video/x-raw,format=BGR '
            "! appsink name=cam",
        ),
        (
            "videotestsrc ! appsink caps=video/x-raw,format=BGR",
            "videotestsrc ! appsink caps=video/x-raw,format=BGR name=cam",
        ),
    ],
)
def test_ensure_appsink_name(pipeline: str, expected: str) -> None:
    assert ensure_appsink_name(pipeline, "cam") == expected


def test_ensure_appsink_name_rejects_missing_appsink_and_bad_names() -> None:
    with pytest.raises(ROSConfigError, match="no appsink"):
        ensure_appsink_name("videotestsrc ! fakesink", "cam")
    with pytest.raises(ROSConfigError, match="valid GStreamer element name"):
        ensure_appsink_name("videotestsrc ! appsink", "two words")


# -- element choices per source and platform ---------------------------------------------------

DECODERS = {
    Platform.CPU_ONLY: {Codec.H264: "avdec_h264", Codec.H265: "avdec_h265", Codec.MJPEG: "jpegdec"},
    Platform.NVIDIA_DESKTOP: {Codec.H264: "nvh264dec", Codec.H265: "nvh265dec", Codec.MJPEG: "nvjpegdec"},
    Platform.TEGRA: {Codec.H264: "nvv4l2decoder", Codec.H265: "nvv4l2decoder", Codec.MJPEG: "nvjpegdec"},
}


@pytest.mark.parametrize(("platform", "case"), list(itertools.product(Platform, CASES)), ids=str)
def test_every_source_on_every_platform(platform: Platform, case: tuple[Source, Codec | None]) -> None:
    source, codec = case
    if source is Source.CSI and platform is not Platform.TEGRA:
        with pytest.raises(ROSConfigError, match="Jetson"):
            build(platform, **spec_fields(source, codec))
        return
    text = build(platform, **spec_fields(source, codec))
    names = elements(text)
    assert "nvvideoconvert" not in text, "DeepStream's nvvideoconvert is never emitted"
    if platform is not Platform.TEGRA:
        assert "NVMM" not in text
        assert "nvvidconv" not in text
    assert names[-1] == "appsink"
    assert "name=openral_sink" in text
    assert text.endswith("emit-signals=true enable-last-sample=false")
    assert "videoconvert ! video/x-raw,format=BGR ! appsink name=openral_sink" in text
    assert "tee" not in names
    expected_source = {
        Source.TESTSRC: "videotestsrc",
        Source.USB: "v4l2src",
        Source.CSI: "nvarguscamerasrc",
        Source.RTSP: "rtspsrc",
        Source.FILE: "filesrc",
    }[source]
    assert names[0] == expected_source
    decoding = codec or (Codec.H264 if source is Source.RTSP else None)
    if decoding is not None:
        assert DECODERS[platform][decoding] in names
        others = {d for table in DECODERS.values() for d in table.values()} - {DECODERS[platform][decoding]}
        assert not others & set(names)
    if platform is Platform.TEGRA and (source is Source.CSI or decoding in (Codec.H264, Codec.H265)):
        assert "nvvidconv ! video/x-raw,format=BGRx,width=320,height=240" in text
    sync = "sync=true" if source is Source.FILE else "sync=false"
    assert f"max-buffers=1 {sync} " in text


def test_testsrc_usb_csi_caps() -> None:
    test = build(Platform.CPU_ONLY, source="testsrc", width=161, height=120, fps=29.97, pattern="ball")
    assert test.startswith(
        "videotestsrc is-live=true pattern=ball ! video/x-raw,width=161,height=120,framerate=2997/100 ! "
    )
    usb = build(Platform.CPU_ONLY, source="usb", device="/dev/video2", encoded="mjpeg", width=640, height=480, fps=30)
    assert usb.startswith('v4l2src device="/dev/video2" ! image/jpeg,width=640,height=480,framerate=30/1 ! jpegdec ! ')
    raw = build(Platform.CPU_ONLY, source="usb", device="/dev/video0", fps=15)
    assert raw.startswith('v4l2src device="/dev/video0" ! video/x-raw,framerate=15/1 ! videoconvert')
    csi = build(Platform.TEGRA, source="csi", device="1", width=1280, height=720, fps=60)
    assert csi.startswith(
        "nvarguscamerasrc sensor-id=1 ! video/x-raw(memory:NVMM),width=1280,height=720,framerate=60/1 ! nvvidconv ! "
    )


def test_rtsp_and_file_heads() -> None:
    rtsp = build(Platform.CPU_ONLY, source="rtsp", device="rtsp://cam/stream?x=1&y=2")
    assert rtsp.startswith(
        'rtspsrc location="rtsp://cam/stream?x=1&y=2" latency=0 ! rtph264depay ! h264parse ! avdec_h264 ! '
    )
    h265 = build(Platform.CPU_ONLY, source="rtsp", device="rtsp://cam/s", encoded="h265")
    assert "rtph265depay ! h265parse ! avdec_h265" in h265
    mp4 = build(Platform.CPU_ONLY, source="file", device="/v/clip.MP4", encoded="h264")
    assert mp4.startswith('filesrc location="/v/clip.MP4" ! qtdemux ! h264parse ! avdec_h264 ! videoconvert')
    assert "matroskademux" in build(Platform.CPU_ONLY, source="file", device="/v/a.mkv", encoded="h264")
    assert "avidemux ! jpegdec" in build(Platform.CPU_ONLY, source="file", device="/v/a.avi", encoded="mjpeg")
    assert "parsebin ! h264parse" in build(Platform.CPU_ONLY, source="file", device="/v/a.h264", encoded="h264")
    auto = build(Platform.CPU_ONLY, source="file", device='/v/my "best" clip.avi', width=64, height=48)
    assert auto.startswith(
        'filesrc location="/v/my \\"best\\" clip.avi" ! decodebin ! videoscale ! video/x-raw,width=64,height=48 ! '
    )


def test_file_plays_at_real_rate_live_sources_do_not_sync() -> None:
    assert "sync=true" in build(Platform.CPU_ONLY, source="file", device="/a.mp4")
    for source in (Source.TESTSRC, Source.USB, Source.RTSP):
        assert "sync=false" in build(Platform.CPU_ONLY, source=source, device=DEVICES[source])


def test_output_format_and_appsink_options() -> None:
    text = build(Platform.CPU_ONLY, source="testsrc", output_format="GRAY8", appsink_name="front", max_buffers=3)
    assert "videoconvert ! video/x-raw,format=GRAY8 ! appsink name=front drop=true max-buffers=3 sync=false" in text


def test_desktop_never_uses_nvvideoconvert_even_when_installed() -> None:
    for source, codec in CASES:
        if source is Source.CSI:
            continue
        text = build(Platform.NVIDIA_DESKTOP, **spec_fields(source, codec, enable_ros_tee=True, enable_event_tee=True))
        assert "nvvideoconvert" not in text
        assert "memory:NVMM" not in text


def test_missing_accelerated_decoder_falls_back_to_the_cpu_with_a_warning() -> None:
    with structlog.testing.capture_logs() as logs:
        text = build(Platform.NVIDIA_DESKTOP, nothing, source="rtsp", device="rtsp://h/s")
    assert "avdec_h264" in text
    assert "nvh264dec" not in text
    assert any(entry["log_level"] == "warning" and entry["using"] == "avdec_h264" for entry in logs)
    tegra = build(Platform.TEGRA, nothing, source="file", device="/a.mp4", encoded="h265", enable_nvmm=True)
    assert "avdec_h265" in tegra
    assert "nvv4l2decoder" not in tegra
    assert "nvvidconv" not in tegra


def test_jetson_only_features_are_refused_elsewhere() -> None:
    for platform in (Platform.CPU_ONLY, Platform.NVIDIA_DESKTOP):
        with pytest.raises(ROSConfigError, match="enable_nvmm needs a Jetson"):
            build(platform, source="testsrc", enable_nvmm=True)
        with pytest.raises(ROSConfigError, match="csi"):
            build(platform, source="csi")
    with pytest.raises(ROSConfigError, match="nvarguscamerasrc"):
        build(Platform.TEGRA, nothing, source="csi")


def test_tegra_without_nvmm_lifts_once_before_the_tee() -> None:
    text = build(Platform.TEGRA, source="rtsp", device="rtsp://h/s", width=640, height=480, enable_ros_tee=True)
    head, _, legs = text.partition(f"tee name={TEE_NAME}")
    assert "nvv4l2decoder ! nvvidconv ! video/x-raw,format=BGRx,width=640,height=480 ! " in head
    assert "nvvidconv" not in legs


def test_tegra_with_nvmm_lifts_in_every_leg() -> None:
    text = build(
        Platform.TEGRA,
        source="file",
        device="/a.mp4",
        encoded="h264",
        width=640,
        height=480,
        enable_nvmm=True,
        enable_ros_tee=True,
        enable_event_tee=True,
    )
    head, _, legs = text.partition(f"tee name={TEE_NAME}")
    assert head.rstrip().endswith("nvv4l2decoder !")
    assert legs.count("nvvidconv ! video/x-raw,format=BGRx,width=640,height=480") == 3


# -- tee legs ----------------------------------------------------------------------------------


def test_tee_legs_are_leaky_branches_with_named_appsinks() -> None:
    text = build(
        Platform.CPU_ONLY,
        source="testsrc",
        width=320,
        height=240,
        enable_ros_tee=True,
        ros_rate_hz=10,
        enable_event_tee=True,
        event_rate_hz=2.5,
        event_appsink_name="motion",
    )
    assert text.count(f"tee name={TEE_NAME}") == 1
    assert text.count(f"{TEE_NAME}. ! {LEAKY_BRANCH_QUEUE} ! ") == 3
    legs = text.split(f"{TEE_NAME}. ! ")[1:]
    assert legs[0].strip() == (
        f"{LEAKY_BRANCH_QUEUE} ! videoconvert ! video/x-raw,format=BGR ! appsink name=openral_sink drop=true "
        "max-buffers=1 sync=false emit-signals=true enable-last-sample=false"
    )
    assert legs[1].strip() == (
        f"{LEAKY_BRANCH_QUEUE} ! videorate drop-only=true ! video/x-raw,framerate=10/1 ! videoconvert ! "
        "video/x-raw,format=BGR ! appsink name=ros_sink drop=true max-buffers=1 sync=false async=false"
    )
    assert legs[2].strip() == (
        f"{LEAKY_BRANCH_QUEUE} ! videorate drop-only=true ! video/x-raw,framerate=5/2 ! videoconvert ! "
        "video/x-raw,format=BGR ! appsink name=motion drop=true max-buffers=1 sync=false async=false"
    )


def test_ros_leg_alone_and_unthrottled() -> None:
    text = build(Platform.CPU_ONLY, source="testsrc", enable_ros_tee=True, output_format="RGB")
    assert text.count(f"{TEE_NAME}. ! ") == 2
    assert "format=RGB ! appsink name=openral_sink" in text
    assert "videoconvert ! video/x-raw,format=BGR ! appsink name=ros_sink" in text
    assert "videorate" not in text


# -- every string parses with the real GStreamer -----------------------------------------------


def _parse_all(platform: Platform) -> int:
    gi = pytest.importorskip(
        "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
    )
    gi.require_version("Gst", "1.0")
    from gi.repository import Gst  # noqa: PLC0415 - optional: the rest of this file needs no gi

    Gst.init(None)
    parsed = 0
    tees = [{}, {"enable_ros_tee": True, "ros_rate_hz": 5}, {"enable_ros_tee": True, "enable_event_tee": True}]
    for (source, codec), tee, fmt in itertools.product(CASES, tees, PixelFormat):
        if source is Source.CSI:
            continue
        for size in ({"width": 320, "height": 240}, {}):
            fields = {**spec_fields(source, codec, output_format=fmt, **tee), **size}
            if not size:
                fields.pop("width"), fields.pop("height")
            # What this host builds for that platform: its missing accelerated elements fall back.
            text = build_pipeline_string(PipelineSpec(**fields), platform, element_present=inspect_element_present)
            element = Gst.parse_launch(text)  # raises GLib.Error on an unknown element or property
            assert element.get_by_name("openral_sink") is not None
            if tee:
                assert element.get_by_name(TEE_NAME) is not None
            element.set_state(Gst.State.NULL)
            parsed += 1
    return parsed


@pytest.mark.parametrize("platform", list(Platform))
def test_every_built_string_parses_with_gst_parse_launch(platform: Platform) -> None:
    """On this host the real probe decides: missing accelerated elements are never emitted."""
    assert _parse_all(platform) > 100


def test_an_explicit_platform_builds_its_pipeline_whatever_this_host_has(monkeypatch: pytest.MonkeyPatch) -> None:
    probed: list[str] = []

    def host_probe(name: str) -> bool:
        probed.append(name)
        return False  # this host has no accelerated element at all

    monkeypatch.setattr("openral_runner.backends.gstreamer.pipeline.inspect_element_present", host_probe)
    csi = build_pipeline_string(PipelineSpec(source="csi", width=1280, height=720), Platform.TEGRA)
    assert elements(csi)[0] == "nvarguscamerasrc"
    assert "nvvidconv" in csi
    rtsp = build_pipeline_string(PipelineSpec(source="rtsp", device="rtsp://cam/s"), Platform.NVIDIA_DESKTOP)
    assert "nvh264dec" in elements(rtsp)
    assert probed == [], "an explicit platform is not probed on this host"
    told = build_pipeline_string(
        PipelineSpec(source="rtsp", device="rtsp://cam/s"), Platform.NVIDIA_DESKTOP, element_present=nothing
    )
    assert "avdec_h264" in elements(told), "a caller's own probe still decides"


def test_pipeline_pattern_error_quotes_the_value_escaped() -> None:
    with pytest.raises(ROSConfigError) as caught:
        validate_model(PipelineSpec, {"source": "testsrc", "pattern": "a\tb\nc"}, field_prefix="backend_params")
    assert str(caught.value).splitlines() == [str(caught.value)]
    assert "'a\\tb\\nc' is not a videotestsrc pattern" in str(caught.value)
