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

    def state(self) -> object:
        """What the detector carries from one frame to the next, as plain Python and numpy
        objects (its random generators' states, counters), for an episode checkpoint
        (:mod:`dronefl.experiments.loop_checkpoint`); ``None``: nothing. A detector that draws
        random numbers or keeps anything between frames overrides this and :meth:`restore`, so
        that a resumed episode continues bit-identically."""
        return None

    def restore(self, state: object) -> None:
        """Continue from ``state``, a :meth:`state` of a detector built the same way."""
        if state is not None:
            raise ValueError(f"{type(self).__name__} carries no state to restore, got {state!r}")

    def close(self) -> None:  # noqa: B027 - a hook: most detectors hold nothing to free
        """Free what the detector holds outside Python (a renderer's OpenGL context); the
        episode calls it when it ends. Left to the garbage collector, an EGL context is freed
        from whichever thread collects it, which EGL refuses (``EGL_BAD_ACCESS``)."""
