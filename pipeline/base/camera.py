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

__all__ = ["CameraFrame", "Camera", "MappedCamera"]


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


class MappedCamera:
    """A camera whose every frame's image passes through :meth:`map_image` (a sensor profile's
    crop and turn, a shipped calibration's colour gain); everything else is the wrapped camera's.
    Subclasses define :meth:`map_image` and, where the image changes size, :attr:`shape`."""

    def __init__(self, camera):
        self.camera = camera

    def map_image(self, image: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def open(self) -> None:
        self.camera.open()

    def close(self) -> None:
        self.camera.close()

    def set_exposure(self, value: float) -> None:
        self.camera.set_exposure(value)

    def flush(self) -> int:
        return self.camera.flush()

    def read(self) -> CameraFrame:
        f = self.camera.read()
        return CameraFrame(self.map_image(f.image), f.timestamp, f.index, f.info)

    @property
    def shape(self) -> tuple[int, int]:
        return self.camera.shape

    def __str__(self) -> str:
        return str(self.camera)

    @property
    def is_file(self) -> bool:
        """Whether the camera is a video file (whose end is a normal end of input)."""
        return bool(getattr(self.camera, "is_file", False))
