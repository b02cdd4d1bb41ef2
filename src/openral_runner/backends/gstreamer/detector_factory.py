"""Manifest → detector at its specification path; it lives in :mod:`openral_perception.detectors.factory`."""

from openral_perception.detectors.factory import build_manifest_detector
from openral_perception.detectors.objects_params import model_path

__all__ = ["build_manifest_detector", "model_path"]
