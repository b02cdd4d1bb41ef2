"""Event detectors: the seam (:class:`EventDetector`), the frame view they share, and where object detectors run.

The kinds are plugins of the ``openral.detectors`` entry-point group
(:data:`~openral_perception.detectors.registry.DETECTOR_REGISTRY`): ``motion``
(:mod:`.motion`), ``scene_change`` (:mod:`.scene_change`) and ``objects`` (:mod:`.objects`, ONNX
Runtime, the ``policy`` extra). This package imports none of them. :mod:`.buffers` holds the
specification's form of the motion and scene-change detectors, called with an appsink's buffer.
"""

from openral_perception.detectors.base import DetectorClass, EventDetector
from openral_perception.detectors.tier import DetectorTier
from openral_perception.frame import DetectorFrame

__all__ = ["DetectorClass", "DetectorFrame", "DetectorTier", "EventDetector"]
