"""The scene-change detector: grey histograms over the full range, compared by chi-square."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openral_core import ROSConfigError
from openral_core.perception import SceneChangeMetadata
from openral_perception.detectors.scene_change import SceneChangeDetector
from openral_perception.frame import DetectorFrame

H, W = 48, 64


def grey_frame(level: int) -> DetectorFrame:
    return DetectorFrame.from_array(np.full((H, W, 3), level, dtype=np.uint8), sensor_id="cam")


frames = st.one_of(
    st.integers(0, 255).map(lambda level: np.full((H, W, 3), level, dtype=np.uint8)),
    st.integers(0, 2**32 - 1).map(lambda seed: np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)),
)


@settings(max_examples=60, deadline=None)
@given(first=frames, second=frames)
def test_any_frame_gives_a_distance_in_range_or_none(first, second):
    scene = SceneChangeDetector()
    assert scene.detect(DetectorFrame.from_array(first, sensor_id="cam")) is None  # nothing to compare with yet
    change = scene.detect(DetectorFrame.from_array(second, sensor_id="cam"))
    if change is not None:
        assert 0.5 < change.distance <= 2.0 + 1e-9
    same = SceneChangeDetector()
    same.detect(DetectorFrame.from_array(second, sensor_id="cam"))
    assert same.detect(DetectorFrame.from_array(second.copy(), sensor_id="cam")) is None


def test_an_all_white_frame_is_all_in_the_top_bin():
    detector = SceneChangeDetector()
    histogram = detector.histogram(grey_frame(255).grey)
    assert histogram[-1] == pytest.approx(1.0)


@pytest.mark.parametrize(("before", "after"), [(200, 240), (0, 255), (255, 0), (128, 200)])
def test_a_bright_scene_changing_fires(before, after):
    detector = SceneChangeDetector()
    detector.detect(grey_frame(before))
    found = detector.detect(grey_frame(after))
    assert isinstance(found, SceneChangeMetadata)
    assert found.distance == pytest.approx(2.0)
    assert found.mean_grey_after == pytest.approx(after, abs=1)


def test_a_grey_camera_is_read_as_it_is():
    detector = SceneChangeDetector()
    detector.detect(DetectorFrame.from_array(np.full((H, W), 10, dtype=np.uint8), sensor_id="mono"))
    found = detector.detect(DetectorFrame.from_array(np.full((H, W), 250, dtype=np.uint8), sensor_id="mono"))
    assert found is not None
    assert found.mean_grey_after == 250


def test_a_wrong_setting_is_named():
    with pytest.raises(ROSConfigError, match="threshold"):
        SceneChangeDetector.from_config({"threshold": 3.0})
    with pytest.raises(ROSConfigError, match="bins"):
        SceneChangeDetector.from_config({"bins": 1})
