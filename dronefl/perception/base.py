"""The detector interface: one camera frame in, detections out (SPEC §3)."""

from __future__ import annotations

from abc import ABC, abstractmethod

from dronefl.types import CameraView, Detection


class Detector(ABC):
    """Turns one drone camera frame into detections.

    A detector reports at most one :class:`~dronefl.types.Detection` per target id (the most
    confident), with the box normalised to the detector image. Only these boxes are stored on
    the drone, never the frame.
    """

    #: Short name used on the command line (``--detector NAME``).
    name: str = "detector"

    @abstractmethod
    def detect(self, view: CameraView) -> tuple[Detection, ...]:
        """Detect the targets in ``view``; returns detections sorted by target id."""
