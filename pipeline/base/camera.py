"""The camera interface shared by the OpenCV camera wrapper and the virtual camera.

A camera behaves like a real webcam: frames are produced at the camera's own rate into a
small buffer, and :meth:`Camera.read` returns the *oldest* buffered frame. So after the LEDs
change, the first frames read may still show the old pattern; a capture must call
:meth:`Camera.flush` (drop buffered frames) and respect the settle time before it records.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["CameraFrame", "Camera"]


@dataclass
class CameraFrame:
    """One frame from a camera.

    Attributes
    ----------
    image : ndarray, shape (H, W, 3)
        RGB image (uint8, uint16 or float32).
    timestamp : float
        ``time.monotonic()`` seconds at the middle of the exposure.
    index : int
        Frame counter since the camera opened (gaps mean dropped frames).
    info : dict
        Anything the camera knows about the frame (exposure, for a virtual camera the LED
        state it rendered).
    """

    image: np.ndarray
    timestamp: float
    index: int
    info: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    """What the capture plan needs from a camera (real or virtual)."""

    def open(self) -> None: ...

    def close(self) -> None: ...

    def set_exposure(self, value: float) -> None: ...

    def read(self) -> CameraFrame: ...

    def flush(self) -> int:
        """Drop every buffered frame; return how many were dropped."""
        ...

    @property
    def shape(self) -> tuple[int, int]: ...
