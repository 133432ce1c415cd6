"""A small virtual camera that images the ring's LED state directly, with a webcam-like buffer.

It stands in for the renderer's virtual camera where a test needs to *see* which pattern was
shown: every pixel shows one LED's RGB level times the global brightness, so a frame decodes
back to the exact LED state. It behaves like a real webcam in the way that matters for
capture: frames are exposed on the camera's own clock (period ``1/fps``, exposure window
``exposure_s``) whether or not anyone reads them, the driver queues at most ``buffer_size``
finished frames (newer frames are dropped while the queue is full, as V4L2 does), and
:meth:`LedStateCamera.read` returns the *oldest* queued frame. After the LEDs change, the next
frames read are stale unless the capture flushes and waits for the settle time.

A frame integrates the light over its exposure: when the LEDs change during an exposure the
frame is the time-weighted mix of the states shown, taken from the emulator's ground-truth
history (``ring.states_during(t0, t1)``).

Examples
--------
>>> from pipeline.capture.emulator import RingEmulator
>>> from pipeline.capture.client import RingClient
>>> with RingEmulator(led_count=4) as emu, RingClient(emu.path) as ring:
...     cam = LedStateCamera(emu, shape=(2, 4), fps=500.0)
...     cam.open()
...     _ = ring.show_pattern(np.eye(4, 3), 1.0)
...     time.sleep(cam.frame_period * 2)
...     _ = cam.flush()
...     frame = cam.read()
>>> frame.image[0, :, 0].tolist()   # LEDs 0..3, red channel
[255, 0, 0, 0]
>>> frame.info["led_levels"][:3].tolist()
[[255, 0, 0], [0, 255, 0], [0, 0, 255]]
"""

from __future__ import annotations

import time
from collections import deque
from typing import Protocol

import numpy as np

from pipeline.capture.camera_api import CameraFrame
from pipeline.capture.emulator import ShownState

__all__ = ["LedHistory", "LedStateCamera", "render_led_state"]


class LedHistory(Protocol):
    """Anything that can tell which LED states were shown during an interval."""

    def states_during(self, t0: float, t1: float) -> list[ShownState]: ...


def render_led_state(levels: np.ndarray, brightness: int, shape: tuple[int, int]) -> np.ndarray:
    """The image of one LED state: pixel (r, c) shows LED ``(r * W + c) % L``.

    Parameters
    ----------
    levels : ndarray, shape (L, 3), uint8
        RGB level per LED.
    brightness : int
        Global brightness level 0..255.
    shape : (H, W)
        Image size.

    Returns
    -------
    ndarray, shape (H, W, 3), float64
        Pixel values in [0, 255]: ``levels * brightness / 255``.

    Examples
    --------
    >>> render_led_state(np.array([[255, 0, 0], [0, 255, 0]], np.uint8), 255, (1, 3))[0, :, :2]
    array([[255.,   0.],
           [  0., 255.],
           [255.,   0.]])
    """
    levels = np.asarray(levels)
    if levels.ndim != 2 or levels.shape[1] != 3:
        raise ValueError(f"levels must have shape (L, 3), got {levels.shape}")
    h, w = shape
    index = np.arange(h * w).reshape(h, w) % levels.shape[0]
    return levels[index].astype(np.float64) * (brightness / 255.0)


class LedStateCamera:
    """Virtual camera imaging the LED state (implements :class:`~pipeline.capture.camera_api.Camera`).

    Parameters
    ----------
    ring : LedHistory
        The LED ground truth, e.g. a :class:`~pipeline.capture.emulator.RingEmulator`.
    shape : (H, W)
        Image size.
    fps : float
        Frame rate of the camera's own clock.
    exposure_s : float or None
        Exposure per frame in seconds (default: 80 % of the frame period).
    buffer_size : int
        Driver queue length (frames).
    """

    #: Frames carry ``info["exposure"] = (start, end)`` in ``time.monotonic()`` seconds.
    reports_exposure = True

    def __init__(
        self,
        ring: LedHistory,
        *,
        shape: tuple[int, int] = (16, 24),
        fps: float = 200.0,
        exposure_s: float | None = None,
        buffer_size: int = 4,
    ) -> None:
        if fps <= 0 or buffer_size < 1:
            raise ValueError(f"need fps > 0 and buffer_size >= 1, got {fps}, {buffer_size}")
        self.ring = ring
        self._shape = (int(shape[0]), int(shape[1]))
        self.frame_period = 1.0 / fps
        self.buffer_size = buffer_size
        self.exposure_s = 0.8 * self.frame_period
        if exposure_s is not None:
            self.set_exposure(exposure_s)
        self._t0: float | None = None
        self._queue: deque[int] = deque()
        self._checked = -1  # last frame index whose completion was processed
        self.dropped_by_driver = 0

    # ------------------------------------------------------------------ Camera interface
    def open(self) -> None:
        """Start the camera's frame clock."""
        self._t0 = time.monotonic()
        self._queue.clear()
        self._checked = -1

    def close(self) -> None:
        """Stop the clock and drop the queue."""
        self._t0 = None
        self._queue.clear()

    def set_exposure(self, value: float) -> None:
        """Exposure in seconds; must fit in one frame period."""
        if not 0 <= value <= self.frame_period:
            raise ValueError(f"exposure must be in [0, {self.frame_period}] s, got {value}")
        self.exposure_s = float(value)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the frames."""
        return self._shape

    def read(self) -> CameraFrame:
        """The oldest queued frame, waiting for the next one if the queue is empty."""
        t0 = self._require_open()
        self._update(time.monotonic())
        while not self._queue:
            k = self._checked + 1
            time.sleep(max(0.0, t0 + k * self.frame_period + self.exposure_s - time.monotonic()))
            self._update(time.monotonic())
        return self._render(self._queue.popleft())

    def flush(self) -> int:
        """Drop every queued frame; return how many."""
        self._require_open()
        self._update(time.monotonic())
        n = len(self._queue)
        self._queue.clear()
        return n

    def describe(self) -> dict:
        """What to record about this camera in the capture's device info."""
        return {
            "kind": "led-state virtual camera",
            "fps": 1.0 / self.frame_period,
            "exposure_s": self.exposure_s,
            "buffer_size": self.buffer_size,
        }

    # ------------------------------------------------------------------ internals
    def _require_open(self) -> float:
        if self._t0 is None:
            raise RuntimeError("camera is not open")
        return self._t0

    def _update(self, now: float) -> None:
        """Queue the frames that finished by ``now`` (dropping them while the queue is full)."""
        t0 = self._require_open()
        done = int(np.floor((now - t0 - self.exposure_s) / self.frame_period))
        for k in range(self._checked + 1, done + 1):
            if len(self._queue) < self.buffer_size:
                self._queue.append(k)
            else:
                self.dropped_by_driver += 1
        self._checked = max(self._checked, done)

    def _render(self, k: int) -> CameraFrame:
        t0 = self._require_open()
        start = t0 + k * self.frame_period
        end = start + self.exposure_s
        states = self.ring.states_during(start, end)
        image = np.zeros((*self._shape, 3), np.float64)
        weights = []
        for i, s in enumerate(states):
            a = max(s.t, start)
            b = states[i + 1].t if i + 1 < len(states) else end
            weights.append((b - a) / (end - start) if end > start else float(i == len(states) - 1))
        for s, wgt in zip(states, weights):
            if wgt > 0:
                image += wgt * render_led_state(s.levels, s.brightness, self._shape)
        main = states[int(np.argmax(weights))]
        return CameraFrame(
            image=np.clip(np.floor(image + 0.5), 0, 255).astype(np.uint8),
            timestamp=0.5 * (start + end),
            index=k,
            info={
                "exposure": (start, end),
                "led_levels": main.levels,
                "brightness": main.brightness,
                "states_in_exposure": sum(w > 0 for w in weights),
            },
        )
