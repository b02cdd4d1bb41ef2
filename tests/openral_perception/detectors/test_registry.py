"""Detector kinds come from the ``openral.detectors`` entry-point group; errors name the kinds and the fields."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

from openral_core import ROSConfigError, ROSDependencyMissing
from openral_core.plugins import DETECTORS_GROUP
from openral_perception.detectors import registry
from openral_perception.detectors.motion import MotionDetector
from openral_perception.detectors.registry import DETECTOR_REGISTRY, build_detector
from openral_perception.detectors.scene_change import SceneChangeDetector
from openral_perception.params import DetectorConfig, DetectorEntry, PerceptionParams


def _entries(params: dict[str, Any]) -> list[DetectorEntry]:
    return PerceptionParams.model_validate(params).detector_entries()


def test_the_built_in_kinds_are_registered_like_any_plugin():
    assert DETECTOR_REGISTRY.group == DETECTORS_GROUP == "openral.detectors"
    assert {"motion", "scene_change", "objects"} <= set(DETECTOR_REGISTRY)
    assert DETECTOR_REGISTRY["motion"] is MotionDetector
    assert DETECTOR_REGISTRY["scene_change"] is SceneChangeDetector


def test_an_unknown_kind_names_the_known_kinds_and_the_closest():
    (entry,) = _entries({"detectors": [{"kind": "motoin"}]})
    with pytest.raises(ROSConfigError, match="unknown detector 'motoin'") as info:
        build_detector(entry, field="observers[].params")
    error = info.value
    assert error.field == "observers[].params.detectors[0].kind"
    assert "motion, objects, scene_change" in str(error)
    assert error.hint == "did you mean 'motion'?"


def test_a_wrong_parameter_is_named_below_its_detector():
    first, second = _entries({"detectors": [{"kind": "scene_change"}, {"kind": "motion", "params": {"cels": 4}}]})
    assert isinstance(build_detector(first), SceneChangeDetector)
    with pytest.raises(ROSConfigError) as info:
        build_detector(second, field="observers[].params")
    error = info.value
    assert error.field == "observers[].params.detectors[1].params.cels"
    assert "allowed keys: cell, min_cell_fraction, min_cells, threshold" in str(error)
    assert error.hint == "did you mean 'cell'?"
    (shorthand,) = _entries({"motion": {"threshold": -1}})
    with pytest.raises(ROSConfigError) as info:
        build_detector(shorthand, field="sensors[cam].backend_params.perception")
    assert info.value.field == "sensors[cam].backend_params.perception.motion.threshold"


def test_a_detector_entry_takes_only_kind_and_params():
    with pytest.raises(ValueError, match="threshold"):
        PerceptionParams.model_validate({"detectors": [{"kind": "motion", "threshold": 3}]})


class NeedsALibrary:
    """A kind whose constructor finds its library missing."""

    kind = "needy"

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, base_dir: Path | None = None) -> NeedsALibrary:
        raise ROSDependencyMissing("acme_vision", extra="acme", needed_for="the needy detector")


class OneKind:
    """A registry that knows one kind."""

    def resolve(self, name: str, *, field: str | None = None) -> type[NeedsALibrary]:
        return NeedsALibrary


def test_a_missing_dependency_is_raised_as_it_is(monkeypatch):
    monkeypatch.setattr(registry, "DETECTOR_REGISTRY", OneKind())
    with pytest.raises(ROSDependencyMissing) as info:
        build_detector(
            DetectorEntry(DetectorConfig(kind="needy"), "detectors[0].kind", "detectors[0].params"),
            field="observers[].params",
        )
    assert info.value.field is None  # it says what to install, not where in the file
