"""OpenCV camera wrapper: device index, device path or video file, with settings locked.

Photometric stereo needs every frame taken with the same exposure, gain and white balance, so
:meth:`OpenCVCamera.open` switches the automatic controls off and sets the requested values
where the backend allows, reads them back, and warns (``CameraSettingWarning``, also kept in
:attr:`OpenCVCamera.warnings` and in the capture's device info) for every control it could
not lock. Frames come out RGB (OpenCV delivers BGR), with a ``time.monotonic()`` timestamp.

A live camera queues frames in its driver; :meth:`OpenCVCamera.flush` drains that queue by
grabbing until a grab has to wait for a new frame. A video file has no such queue: its flush
drops nothing, and its frames are read in order.

Examples
--------
>>> import tempfile, os, cv2, warnings
>>> path = os.path.join(tempfile.mkdtemp(), "clip.avi")
>>> writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 30, (40, 32))
>>> for _ in range(3):
...     _ = writer.write(np.full((32, 40, 3), (255, 0, 0), np.uint8))   # BGR: pure blue
>>> writer.release()
>>> with warnings.catch_warnings():
...     warnings.simplefilter("ignore")
...     cam = OpenCVCamera(path)
...     cam.open()
>>> frame = cam.read()
>>> cam.shape, frame.image.shape, int(frame.image[0, 0, 2]) > 240   # RGB: blue is channel 2
((32, 40), (32, 40, 3), True)
>>> cam.close()
"""

from __future__ import annotations

import glob
import os
import time
import warnings
from typing import Any

import numpy as np

from pipeline.base.camera import CameraFrame
from pipeline.base.errors import UserError

__all__ = ["CameraSettingWarning", "CameraError", "OpenCVCamera", "video_devices"]


class CameraSettingWarning(UserWarning):
    """A camera control (exposure, gain, white balance, buffer size) could not be locked."""


class CameraError(UserError):
    """The camera cannot be opened or stopped delivering frames."""


def video_devices() -> list[str]:
    """Video device paths present on this machine (``/dev/video*``)."""
    return sorted(glob.glob("/dev/video*"))


class OpenCVCamera:
    """A camera read through OpenCV ``VideoCapture`` (implements the ``Camera`` protocol).

    Parameters
    ----------
    source : int or str
        Device index (``0`` or ``"0"``), device path (``/dev/video2``) or video file.
    exposure : float, optional
        Exposure in the backend's units (V4L2: 100 µs steps); auto exposure is switched off.
    gain : float, optional
        Sensor gain in the backend's units.
    white_balance : float, optional
        White-balance temperature in kelvin; auto white balance is switched off regardless.
    settle_s : float, optional
        Wait after a pattern change before flushing (default: two frame periods, 0.1 s if
        the frame rate is unknown).
    """

    def __init__(
        self,
        source: int | str,
        *,
        exposure: float | None = None,
        gain: float | None = None,
        white_balance: float | None = None,
        settle_s: float | None = None,
    ) -> None:
        self.source: int | str = int(source) if str(source).isdigit() else source
        self.exposure = exposure
        self.gain = gain
        self.white_balance = white_balance
        self._settle = settle_s
        self.warnings: list[str] = []
        self.locked: dict[str, Any] = {}
        self._cap = None
        self._shape: tuple[int, int] | None = None
        self._index = 0
        self.is_file = isinstance(self.source, str) and os.path.isfile(self.source)
        self.frame_period: float | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the source, lock its settings (warning where impossible), learn the shape."""
        import cv2

        src = self.source
        if isinstance(src, str) and "://" not in src and not os.path.exists(src):
            raise CameraError(
                f"camera {src!r}: no such device or video file; video devices here: "
                f"{', '.join(video_devices()) or 'none found'}"
            )
        cap = cv2.VideoCapture(src)
        if not cap.isOpened():
            raise CameraError(
                f"camera {src!r}: OpenCV could not open it; video devices here: "
                f"{', '.join(video_devices()) or 'none found'}"
            )
        self._cap = cap
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.frame_period = 1.0 / fps if fps and fps > 0 else None
        if not self.is_file:
            self._try("buffer size", cv2.CAP_PROP_BUFFERSIZE, 1)
        # Auto exposure off: V4L2 wants 1 (manual), DirectShow-style backends 0.25.
        if not (self._set(cv2.CAP_PROP_AUTO_EXPOSURE, 1) or self._set(cv2.CAP_PROP_AUTO_EXPOSURE, 0.25)):
            self._warn("auto exposure could not be switched off")
        else:
            self.locked["auto_exposure"] = False
        if self.exposure is not None:
            self._try("exposure", cv2.CAP_PROP_EXPOSURE, self.exposure)
        if self.gain is not None:
            self._try("gain", cv2.CAP_PROP_GAIN, self.gain)
        self._try("auto white balance", cv2.CAP_PROP_AUTO_WB, 0)
        if self.white_balance is not None:
            self._try("white balance", cv2.CAP_PROP_WB_TEMPERATURE, self.white_balance)
        ok, bgr = cap.read()
        if not ok:
            self.close()
            raise CameraError(f"camera {src!r}: opened but delivered no frame")
        self._shape = (int(bgr.shape[0]), int(bgr.shape[1]))
        if self.is_file:
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)  # the probe frame is not lost from a file

    def close(self) -> None:
        """Release the device (idempotent)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def set_exposure(self, value: float) -> None:
        """Set the exposure (backend units), warning if the backend refuses it."""
        import cv2

        self.exposure = value
        if self._cap is not None:
            self._try("exposure", cv2.CAP_PROP_EXPOSURE, value)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the frames (known once open)."""
        if self._shape is None:
            raise CameraError(f"camera {self.source!r} is not open")
        return self._shape

    @property
    def settle_s(self) -> float:
        """Settle time after a pattern change before flushing."""
        if self._settle is not None:
            return self._settle
        return 2 * self.frame_period if self.frame_period else 0.1

    def read(self) -> CameraFrame:
        """The next frame, RGB, shape (H, W, 3), with a monotonic timestamp."""
        import cv2

        if self._cap is None:
            raise CameraError(f"camera {self.source!r} is not open")
        ok, bgr = self._cap.read()
        if not ok or bgr is None:
            what = "end of the video file" if self.is_file else "the device stopped delivering"
            raise CameraError(f"camera {self.source!r}: no frame ({what})")
        t = time.monotonic()
        if bgr.ndim == 2:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
        else:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        self._index += 1
        return CameraFrame(
            image=rgb,
            timestamp=t,
            index=self._index - 1,
            info={"pos_msec": float(self._cap.get(cv2.CAP_PROP_POS_MSEC))},
        )

    def flush(self) -> int:
        """Drop the frames queued in the driver; return how many (0 for a video file)."""
        if self._cap is None:
            raise CameraError(f"camera {self.source!r} is not open")
        if self.is_file:
            return 0
        period = self.frame_period or 1 / 30
        dropped = 0
        # A queued frame is grabbed at once; when a grab has to wait most of a frame period,
        # the queue was empty and that frame was exposed after the flush began.
        for _ in range(16):
            t = time.monotonic()
            if not self._cap.grab():
                break
            if time.monotonic() - t > 0.5 * period:
                break
            dropped += 1
        return dropped

    def describe(self) -> dict:
        """What to record about this camera in the capture's device info."""
        backend = self._cap.getBackendName() if self._cap is not None else None
        return {
            "kind": "opencv",
            "source": str(self.source),
            "backend": backend,
            "fps": 1.0 / self.frame_period if self.frame_period else None,
            "locked": dict(self.locked),
            "warnings": list(self.warnings),
        }

    # ------------------------------------------------------------------ settings
    def _set(self, prop: int, value: float) -> bool:
        try:
            return bool(self._cap.set(prop, value))  # type: ignore[union-attr]
        except Exception:  # noqa: BLE001 - some backends throw instead of returning False
            return False

    def _try(self, name: str, prop: int, value: float) -> None:
        if not self._set(prop, value):
            self._warn(f"{name} could not be set to {value}")
            return
        got = self._cap.get(prop)  # type: ignore[union-attr]
        if not np.isclose(got, value, rtol=1e-3, atol=1e-6):
            self._warn(f"{name} set to {value} but the camera reports {got}")
        self.locked[name] = float(got)

    def _warn(self, what: str) -> None:
        msg = f"camera {self.source!r}: {what} (backend does not allow it)"
        self.warnings.append(msg)
        warnings.warn(msg, CameraSettingWarning, stacklevel=3)
