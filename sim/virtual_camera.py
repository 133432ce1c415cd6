"""A virtual IrisTac camera: renders the gel under whatever the LED ring shows, like a webcam.

It implements :class:`pipeline.base.camera.Camera`. A producer thread runs the
camera's own clock: at the start of each frame period it asks ``led_state()`` what the ring
shows and which scripted contact is pressed, and at the end of the period it puts the frame
into a small FIFO buffer (``buffer_size`` frames, dropping the *oldest* when full).
:meth:`VirtualCamera.read` returns the oldest buffered frame, blocking until one exists. So
right after the LEDs change, ``read()`` returns frames exposed under the *old* pattern; a
capture must :meth:`~VirtualCamera.flush` and wait for the settle time (one frame period).

A frame's content depends only on what was sampled at its exposure (LED state, contact) and
on ``(seed, frame index)``, so it is deterministic given the seed; the image itself is
rendered when the frame is read (the same pixels, without spending CPU on frames nobody
reads).

Examples
--------
>>> import time
>>> from sim.render import bare_ring_illumination, RenderSettings
>>> state = {"drive": np.ones((24, 3))}
>>> cam = VirtualCamera(bare_ring_illumination((12, 16), 1.0), lambda: (state["drive"], 1.0),
...                     settings=RenderSettings(exposure=1e5, bit_depth=8), fps=200.0)
>>> cam.open()
>>> frame = cam.read()
>>> frame.image.shape, frame.image.dtype.name, frame.info["brightness"]
((12, 16, 3), 'uint8', 1.0)
>>> cam.close()
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from pipeline.base.camera import CameraFrame
from sim.geometry.surface import HeightField
from sim.illumination_model import IlluminationModel
from sim.render import Renderer, RenderSettings

__all__ = ["VirtualCamera", "ring_led_state"]

LedState = Callable[[], tuple]


@dataclass
class _Exposure:
    """What the camera sampled for one frame (rendered to pixels when read)."""

    index: int
    start: float
    end: float
    drive: np.ndarray
    brightness: float
    contact: int  # index into the script, -1 = no script entry yet (flat gel)


def ring_led_state(ring) -> LedState:
    """``led_state`` callable that reads an LED ring emulator's currently shown state.

    ``ring`` needs ``states_during(t0, t1)`` returning states with ``levels`` (L, 3) uint8
    and ``brightness`` 0..255 (:class:`pipeline.capture.emulator.RingEmulator`); the drive
    is ``levels / 255`` and the brightness ``brightness / 255``.
    """

    def state():
        now = time.monotonic()
        s = ring.states_during(now, now)[-1]
        return np.asarray(s.levels, dtype=np.float64) / 255.0, float(s.brightness) / 255.0

    return state


class VirtualCamera:
    """Renders frames of a scripted contact scene under the ring's current LED state.

    Parameters
    ----------
    model : IlluminationModel
        Illumination of the sensor (ray-traced, calibrated or :func:`sim.render.bare_ring_illumination`).
    led_state : callable () -> (drive (L, 3), brightness)
        What the ring shows now; called once per frame at the start of its exposure.
    script : sequence of (time_s, HeightField or None)
        Scripted contact: from ``time_s`` after :meth:`open` the gel has that shape (None =
        no contact). Before the first entry the gel is flat.
    albedo : float or ndarray (H, W) or (H, W, 3)
    settings : RenderSettings
        Effects, exposure ``mu``, noise, bit depth. ``settings.seed`` seeds every frame.
    fps : float
        Frame rate of the camera's clock.
    buffer_size : int
        Frames the driver keeps (oldest dropped when full), like a webcam's queue.
    device : str
        torch device of the renderer.
    """

    def __init__(self, model: IlluminationModel, led_state: LedState, script: Sequence[tuple] = (), albedo=1.0,
                 settings: RenderSettings | None = None, fps: float = 30.0, buffer_size: int = 4, device="cpu"):
        if not fps > 0 or buffer_size < 1:
            raise ValueError(f"VirtualCamera: need fps > 0 and buffer_size >= 1, got {fps}, {buffer_size}")
        times = [float(t) for t, _ in script]
        if any(b < a for a, b in zip(times, times[1:])):
            raise ValueError(f"VirtualCamera: script times must not decrease, got {times}")
        for t, g in script:
            if g is not None and (not isinstance(g, HeightField) or g.shape != model.shape):
                raise ValueError(f"VirtualCamera: script entry at t={t} must be None or a HeightField of shape "
                                 f"{model.shape}, got {getattr(g, 'shape', type(g).__name__)}")
        self.model = model
        self.led_state = led_state
        self.script = list(script)
        self._times = np.array(times)
        self.albedo = albedo
        # A copy: set_exposure must not change the caller's settings object.
        self.settings = dataclasses.replace(settings) if settings is not None else RenderSettings()
        self.fps = float(fps)
        self.buffer_size = int(buffer_size)
        self._renderer = Renderer(model, self.settings, device=device)
        self._surface_index = -1  # the renderer holds the flat gel
        self._renderer.set_surface(None, albedo)
        self._buffer: deque[_Exposure] = deque(maxlen=self.buffer_size)
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._t0: float | None = None
        self.dropped = 0  # frames pushed out of the full buffer

    # -- Camera interface ------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the frames."""
        return self.model.shape

    def open(self) -> None:
        """Start the camera clock (frame 0 starts exposing now)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._produce, name="virtual-camera", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the clock and drop the buffer."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._thread = None
        with self._cond:
            self._buffer.clear()

    def set_exposure(self, value: float) -> None:
        """Set the exposure ``mu`` (DN per unit radiance) for frames read from now on."""
        if not value >= 0:
            raise ValueError(f"VirtualCamera.set_exposure: exposure must be >= 0, got {value}")
        self.settings.exposure = float(value)

    def read(self, timeout: float | None = 5.0) -> CameraFrame:
        """Return the oldest buffered frame, waiting for one if the buffer is empty.

        Raises
        ------
        RuntimeError
            Camera not open, or no frame within ``timeout`` seconds.
        """
        if self._thread is None:
            raise RuntimeError("VirtualCamera.read: camera is not open")
        with self._cond:
            if not self._cond.wait_for(lambda: len(self._buffer) > 0, timeout=timeout):
                raise RuntimeError(f"VirtualCamera.read: no frame within {timeout} s")
            exp = self._buffer.popleft()
        return self._render(exp)

    def flush(self) -> int:
        """Drop every buffered frame; return how many were dropped."""
        with self._cond:
            n = len(self._buffer)
            self._buffer.clear()
        return n

    @property
    def buffered(self) -> int:
        """Number of frames waiting in the buffer."""
        with self._cond:
            return len(self._buffer)

    def describe(self) -> dict:
        """What to record about this camera in a capture's device info."""
        return {"kind": "virtual camera (sim.render)", "fps": self.fps, "buffer_size": self.buffer_size,
                "effects": list(self.settings.effects), "exposure": self.settings.exposure}

    # -- internals -------------------------------------------------------------------------
    def contact_at(self, t: float) -> int:
        """Index of the script entry in force ``t`` seconds after open (-1: none yet)."""
        return int(np.searchsorted(self._times, t, side="right")) - 1

    def _produce(self) -> None:
        period = 1.0 / self.fps
        k = 0
        while not self._stop.is_set():
            start = self._t0 + k * period
            self._sleep_until(start)
            if self._stop.is_set():
                return
            # The LEDs and the contact are sampled when the exposure starts.
            drive, brightness = self.led_state()
            drive = np.array(drive, dtype=np.float64, copy=True)
            exp = _Exposure(k, start, start + period, drive, float(brightness), self.contact_at(start - self._t0))
            self._sleep_until(exp.end)
            with self._cond:
                if len(self._buffer) == self.buffer_size:
                    self.dropped += 1
                self._buffer.append(exp)  # deque(maxlen) drops the oldest
                self._cond.notify_all()
            k += 1

    def _sleep_until(self, t: float) -> None:
        while not self._stop.is_set():
            dt = t - time.monotonic()
            if dt <= 0:
                return
            self._stop.wait(min(dt, 0.05))

    def _render(self, exp: _Exposure) -> CameraFrame:
        if exp.contact != self._surface_index:
            surface = self.script[exp.contact][1] if exp.contact >= 0 else None
            self._renderer.set_surface(surface, self.albedo)
            self._surface_index = exp.contact
        image = self._renderer.render(exp.drive, exp.brightness, seed=self.frame_seed(exp.index))
        info = {"drive": exp.drive, "brightness": exp.brightness, "contact": exp.contact,
                "exposure": self.settings.exposure, "exposure_window": (exp.start, exp.end),
                "effects": list(self._renderer.computed)}
        return CameraFrame(image=image, timestamp=0.5 * (exp.start + exp.end), index=exp.index, info=info)

    def frame_seed(self, index: int) -> int:
        """Noise seed of frame ``index``: a function of ``settings.seed`` and the index only."""
        return (int(self.settings.seed) * 1_000_003 + int(index)) & 0x7FFF_FFFF_FFFF_FFFF
