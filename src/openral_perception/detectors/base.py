"""The detector seam: what a detector does with a frame, and how a deployment builds one.

A detector kind is a class registered in the ``openral.detectors`` entry-point group (built-ins
included) and built with ``Cls.from_config(params, base_dir=...)``, which validates ``params`` with
its own typed model (``extra="forbid"``) and loads what it needs (a model file): nothing is opened
that the publisher would have to close.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

from pydantic import BaseModel

from openral_perception.frame import DetectorFrame


class EventDetector(Protocol):
    """Finds one kind of event in a frame.

    ``kind`` names the events (``openral/<robot>/perception/<kind>``); a publisher runs one
    detector per kind. ``detect`` is called on one worker thread, one frame at a time; a detector
    that compares frames keeps its own state per ``frame.sensor_id``.
    """

    kind: str

    def detect(self, frame: DetectorFrame) -> BaseModel | None:
        """What ``frame`` shows (``None``: nothing worth an event). Must not write to the frame's arrays."""
        ...

    def summarise(self, metadata: Any) -> str:
        """One line for people about what :meth:`detect` found."""
        ...


class DetectorClass(Protocol):
    """What the ``openral.detectors`` group registers: a class that builds its detector from a deployment's params."""

    def from_config(self, params: Mapping[str, Any], *, base_dir: Path | None = None) -> EventDetector:
        """Validate ``params`` with the detector's own model and build it.

        Args:
            params: The detector's ``params`` block of the deployment.
            base_dir: Folder a relative file path is resolved against (the deployment file's).

        Raises:
            ROSConfigError: A wrong or missing parameter, named by its key within ``params``.
        """
        ...
