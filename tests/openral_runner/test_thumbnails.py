"""Dashboard thumbnails: throttled per camera on an absolute schedule, encoded off the tick thread."""

from __future__ import annotations

import io
import threading

import numpy as np
from PIL import Image

from openral_core import FrameEncoding, SensorFrame
from openral_runner.frame_slot import frame_from_array
from openral_runner.thumbnails import ThumbnailPublisher, encode_thumbnail


class Seconds:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


def bgr_frame(sensor_id: str = "cam", width: int = 1280, height: int = 960, stamp_ns: int = 1):
    pixels = np.zeros((height, width, 3), np.uint8)
    pixels[:, :, 0] = 255  # pure blue in BGR
    return frame_from_array(sensor_id, pixels, stamp_ns=stamp_ns, seq=0, encoding=FrameEncoding.BGR8)


def test_encoded_thumbnail_fits_640x480_and_keeps_colours() -> None:
    thumb = encode_thumbnail(bgr_frame())
    assert thumb is not None
    image = Image.open(io.BytesIO(thumb.jpeg))
    assert image.format == "JPEG"
    assert image.size == (640, 480) == (thumb.width, thumb.height)
    r, g, b = np.asarray(image.convert("RGB")).reshape(-1, 3).mean(axis=0)
    assert b > 200  # BGR was converted, not shown as red
    assert r < 40
    assert g < 40


def test_small_frames_are_not_upscaled() -> None:
    thumb = encode_thumbnail(bgr_frame(width=160, height=120))
    assert thumb is not None
    assert (thumb.width, thumb.height) == (160, 120)


def test_offers_are_throttled_per_camera_without_burst_after_a_stall() -> None:
    clock = Seconds()
    publisher = ThumbnailPublisher(10.0, clock=clock, sink=lambda _t: None)  # worker not started
    taken = []
    for _ in range(30):  # 30 ticks at 100 Hz = 0.3 s
        taken.append(publisher.offer_frame(bgr_frame("a", 4, 4)))
        clock.t += 0.01
    assert sum(taken) == 3
    clock.t += 2.0  # a stall: 20 slots pass
    after = []
    for _ in range(10):
        after.append(publisher.offer_frame(bgr_frame("a", 4, 4)))
        clock.t += 0.01
    assert sum(after) == 1  # one thumbnail, not a burst of 20
    assert publisher.offer_frame(bgr_frame("b", 4, 4))  # other cameras have their own schedule


def test_worker_encodes_and_delivers_latest() -> None:
    got = []
    done = threading.Event()

    def sink(thumb) -> None:
        got.append(thumb)
        done.set()

    publisher = ThumbnailPublisher(5.0, sink=sink)
    before = set(threading.enumerate())
    publisher.start()
    try:
        assert publisher.offer_frame(bgr_frame(width=320, height=240, stamp_ns=42))
        assert done.wait(5.0)
    finally:
        publisher.stop()
    assert got[0].stamp_ns == 42
    assert publisher.latest("cam") is got[0]
    assert not any(t.name == "openral-thumbnails" for t in set(threading.enumerate()) - before), "its worker stopped"


def test_zero_rate_disables() -> None:
    publisher = ThumbnailPublisher(0.0)
    publisher.start()
    assert not publisher.offer_frame(bgr_frame(width=4, height=4))
    publisher.stop()


def test_a_small_jpeg_frame_passes_through_and_a_large_one_is_scaled() -> None:
    small = io.BytesIO()
    Image.new("RGB", (320, 240), (10, 200, 30)).save(small, format="JPEG")
    frame = SensorFrame(
        sensor_id="cam", stamp_ns=1, width=320, height=240, encoding=FrameEncoding.JPEG, data=small.getvalue()
    )
    thumb = encode_thumbnail(frame)
    assert thumb is not None
    assert thumb.jpeg == small.getvalue()  # not re-encoded
    large = io.BytesIO()
    Image.new("RGB", (1280, 960), (10, 200, 30)).save(large, format="PNG")
    frame = SensorFrame(
        sensor_id="cam", stamp_ns=1, width=1280, height=960, encoding=FrameEncoding.PNG, data=large.getvalue()
    )
    thumb = encode_thumbnail(frame)
    assert thumb is not None
    assert (thumb.width, thumb.height) == (640, 480)
    assert Image.open(io.BytesIO(thumb.jpeg)).format == "JPEG"
